"""``numpy.linalg.inv`` and ``solve`` for the estimators' small matrices (5-15 rows, thousands of calls a drive):
the same LAPACK gufuncs numpy calls, the same results to the bit, without numpy's per-call checks and error-state
set-up (a third of the time of a call at these sizes). A singular matrix gives a non-finite result there, and
numpy's own call is then made again: it raises :class:`numpy.linalg.LinAlgError` as before.

The gufuncs live in numpy's private ``numpy.linalg._umath_linalg``: where a numpy release moves or renames them,
:func:`inv` and :func:`solve` are numpy's own public calls (:func:`gufuncs` says which path runs)."""

from __future__ import annotations

from types import ModuleType

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

GUFUNCS = ("inv", "solve", "solve1")
"""The gufuncs of ``numpy.linalg._umath_linalg`` used here."""


def _private() -> ModuleType | None:
    """numpy's private LAPACK gufunc module, or None where it is absent or lacks one of :data:`GUFUNCS`."""
    try:
        from numpy.linalg import _umath_linalg  # type: ignore[attr-defined]
    except ImportError:
        return None
    return _umath_linalg if all(callable(getattr(_umath_linalg, name, None)) for name in GUFUNCS) else None


_umath_linalg = _private()


def gufuncs() -> bool:
    """Whether the private gufuncs are used (False: numpy's public ``inv``/``solve``)."""
    return _umath_linalg is not None


def inv(a: FloatArray) -> FloatArray:
    """``numpy.linalg.inv(a)`` of a float matrix."""
    if _umath_linalg is None:
        return np.linalg.inv(a)
    out: FloatArray = _umath_linalg.inv(a, signature="d->d")
    return out if np.isfinite(out).all() else np.linalg.inv(a)


def solve(a: FloatArray, b: FloatArray) -> FloatArray:
    """``numpy.linalg.solve(a, b)`` of a float matrix ``a`` and a float vector or matrix ``b``."""
    if _umath_linalg is None:
        return np.linalg.solve(a, b)
    gufunc = _umath_linalg.solve1 if b.ndim == 1 else _umath_linalg.solve
    out: FloatArray = gufunc(a, b, signature="dd->d")
    return out if np.isfinite(out).all() else np.linalg.solve(a, b)
