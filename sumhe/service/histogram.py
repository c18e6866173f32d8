"""Percentiles of a whole run in fixed memory: counts in logarithmic bins (the daemon's latency since it started,
beside the status line's window of the latest sends)."""

from __future__ import annotations

import math

import numpy as np

BINS_PER_DECADE = 100
"""Bins per factor of ten: a percentile is known within 2.3 % (``10^(1/100)``)."""


class LogHistogram:
    """Counts of values in ``[lo, hi)`` in :data:`BINS_PER_DECADE` logarithmic bins per decade, those below ``lo``
    (zero and negative ones included) in one bin of their own and those at or above ``hi`` in another; NaN is not
    counted. :meth:`percentile` answers with the upper edge of the bin the percentile falls in (``lo`` for the low
    bin, the largest value seen for the high one), so it is never below the exact percentile of the values."""

    def __init__(self, lo: float, hi: float) -> None:
        if not 0.0 < lo < hi:
            raise ValueError(f"lo, hi: need 0 < lo < hi, got {lo!r}, {hi!r}")
        self.lo, self.hi = lo, hi
        self._bins = math.ceil(math.log10(hi / lo) * BINS_PER_DECADE)
        self.counts = [0] * (self._bins + 2)
        self.count = 0
        self.max = -math.inf

    def add(self, value: float) -> None:
        if math.isnan(value):
            return
        if value < self.lo:
            i = 0
        elif value >= self.hi:
            i = self._bins + 1
        else:
            i = min(int(math.log10(value / self.lo) * BINS_PER_DECADE), self._bins - 1) + 1
        self.counts[i] += 1
        self.count += 1
        self.max = max(self.max, value)

    def percentile(self, q: float) -> float:
        """The ``q`` percentile (0-100) of the values counted, as the class docstring says (NaN before any)."""
        if self.count == 0:
            return math.nan
        rank = max(math.ceil(q / 100.0 * self.count), 1)
        i = int(np.searchsorted(np.cumsum(self.counts), rank))
        if i == 0:
            return self.lo
        if i > self._bins:
            return self.max
        return min(self.lo * 10.0 ** (i / BINS_PER_DECADE), self.max)
