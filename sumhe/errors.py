"""The error tree of sumhe: one root, multiply inheriting the builtins callers expect; :func:`printable` makes
any text safe to put in an error message."""


class SumheError(Exception):
    """Root of every error sumhe raises on purpose."""


class ConfigError(SumheError, ValueError):
    """A configuration file or value is wrong; the message names the file and the key."""


class SourceError(SumheError, ConnectionError):
    """A sensor source (serial port, CAN bus, log file) cannot be opened or read."""


class DecodeError(SumheError, ValueError):
    """Bytes that cannot be decoded (NMEA sentence, CAN frame, log line)."""


class SolverError(SumheError, RuntimeError):
    """An estimation problem that cannot be built or solved."""


class EstimatorInputError(SumheError, ValueError):
    """Data handed to an estimator that it cannot use (empty, NaN, time going backwards)."""


class CalibrationError(SumheError, ValueError):
    """A recorded drive that cannot be calibrated (no valid fix, no CAN speed); the message says what is missing."""


def printable(text: str, limit: int = 200) -> str:
    """``text`` safe for a terminal and a log line: control (C0, C1) and other non-printable characters escaped as in
    ``repr`` (no terminal escape sequence gets through), cut to ``limit`` characters."""
    out = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text[:limit])
    return out + ("..." if len(text) > limit else "")
