"""``numpy.linalg.inv`` and ``solve`` for the estimators' small matrices (5-15 rows, thousands of calls a drive):
the same LAPACK gufuncs numpy calls, the same results to the bit, without numpy's per-call checks and error-state
set-up (a third of the time of a call at these sizes). A singular matrix gives a non-finite result there, and
numpy's own call is then made again: it raises :class:`numpy.linalg.LinAlgError` as before."""

from __future__ import annotations

import numpy as np
from numpy.linalg import _umath_linalg  # type: ignore[attr-defined]
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def inv(a: FloatArray) -> FloatArray:
    """``numpy.linalg.inv(a)`` of a float matrix."""
    out: FloatArray = _umath_linalg.inv(a, signature="d->d")
    return out if np.isfinite(out).all() else np.linalg.inv(a)


def solve(a: FloatArray, b: FloatArray) -> FloatArray:
    """``numpy.linalg.solve(a, b)`` of a float matrix ``a`` and a float vector or matrix ``b``."""
    gufunc = _umath_linalg.solve1 if b.ndim == 1 else _umath_linalg.solve
    out: FloatArray = gufunc(a, b, signature="dd->d")
    return out if np.isfinite(out).all() else np.linalg.solve(a, b)
