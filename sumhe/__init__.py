"""sumhe: vehicle position through GPS outages with a moving-horizon state-uniform estimator."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("sumhe")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"
