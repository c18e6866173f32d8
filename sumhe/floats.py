"""numpy's routines for the few-element vectors of the estimators' per-sample paths, on plain floats and to the bit
(the same formulas in the same order): a numpy call on a 5-element array costs microseconds of set-up, the sum here
a fraction of that."""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence


def interp(x: float, xp: Sequence[float], fp: Sequence[float]) -> float:
    """``float(numpy.interp(x, xp, fp))`` for one ``x`` (``xp`` increasing, not empty): ``fp``'s ends beyond
    ``xp``'s, NaN for NaN (but ``fp[0]`` for a one-point ``xp``, as numpy gives)."""
    if len(xp) == 1:
        return fp[0]
    if math.isnan(x):
        return x
    j = bisect.bisect_right(xp, x) - 1
    if j < 0:
        return fp[0]
    if j >= len(xp) - 1 or xp[j] == x:
        return fp[j]
    y = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]) * (x - xp[j]) + fp[j]
    if math.isnan(y):  # numpy's second try, from the other end
        y = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j]) * (x - xp[j + 1]) + fp[j + 1]
        if math.isnan(y) and fp[j] == fp[j + 1]:
            y = fp[j]
    return y
