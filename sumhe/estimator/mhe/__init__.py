"""The moving-horizon estimator in parts: :mod:`.estimator` conducts :mod:`.window` (which steps the horizon keeps),
:mod:`.outputs` (a step's measurements), :mod:`.propagate` (CAN-rate propagation), :mod:`.gate` (which fixes
enter), :mod:`.arrival` (what leaving steps leave behind), :mod:`.solve` (buckets, bounds, retries) and the window
problem (:mod:`.problem`) with its solvers (:mod:`.sqp`, :mod:`.nlp`)."""

from sumhe.estimator.mhe.estimator import MovingHorizonEstimator

__all__ = ["MovingHorizonEstimator"]
