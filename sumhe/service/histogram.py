"""Percentiles in fixed memory: counts in logarithmic bins (the daemon's latency since it started; the benchmarks'
latencies, errors and solve times). Histograms of several runs add up."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

LATENCY_EDGES_MS = np.logspace(-4.0, 5.0, 9 * 100 + 1)
"""Bin edges (ms) of latency histograms: 0.1 us to 100 s, 100 bins per decade (percentiles to within 2.3 %)."""


def latency_histogram(ms: ArrayLike) -> NDArray[np.int64]:
    """Counts of latencies (ms) in the bins of :data:`LATENCY_EDGES_MS` (values beyond the edges go to the end
    bins). Histograms of several runs add up; :func:`histogram_percentile` reads percentiles back."""
    v = np.clip(np.asarray(ms, dtype=float).ravel(), LATENCY_EDGES_MS[0], LATENCY_EDGES_MS[-1])
    counts, _ = np.histogram(v, bins=LATENCY_EDGES_MS)
    return counts.astype(np.int64)


def histogram_percentile(counts: ArrayLike, q: float) -> float:
    """The ``q`` percentile (ms) of a :func:`latency_histogram`: the geometric centre of the bin where the
    cumulative count reaches ``q`` % (NaN for an empty histogram)."""
    c = np.asarray(counts, dtype=float)
    total = c.sum()
    if total <= 0:
        return math.nan
    k = int(np.searchsorted(np.cumsum(c), q / 100.0 * total, side="left"))
    k = min(k, len(c) - 1)
    return float(math.sqrt(LATENCY_EDGES_MS[k] * LATENCY_EDGES_MS[k + 1]))


FOLD_EVERY = 4096
"""Values a :class:`Histogram` holds before it bins them (vectorised)."""


class Histogram:
    """Counts of positive values in the fixed log bins of :func:`latency_histogram` (1e-4 to 1e5, 100 bins a
    decade: percentiles to within 2.3 %), with their exact count, sum and maximum; NaN is not counted. Fixed size
    whatever the number of values (values are binned :data:`FOLD_EVERY` at a time): the replay's errors and solve
    times, the daemon's latency since it started."""

    def __init__(self) -> None:
        self._counts = latency_histogram([])
        self._n = 0
        self._total = 0.0
        self._max = math.nan
        self._pending: list[float] = []

    def add(self, value: float) -> None:
        self._pending.append(value)
        if len(self._pending) >= FOLD_EVERY:
            self._fold()

    def extend(self, values: ArrayLike) -> None:
        self._fold()
        v = np.asarray(values, dtype=float).ravel()
        v = v[np.isfinite(v)]
        if v.size:
            self._counts += latency_histogram(v)
            self._n += int(v.size)
            self._total += float(v.sum())
            self._max = float(v.max()) if math.isnan(self._max) else max(self._max, float(v.max()))

    @property
    def counts(self) -> np.ndarray:
        self._fold()
        return self._counts

    @property
    def n(self) -> int:
        self._fold()
        return self._n

    @property
    def mean(self) -> float:
        self._fold()
        return self._total / self._n if self._n else math.nan

    @property
    def max(self) -> float:
        self._fold()
        return self._max

    def percentile(self, q: float) -> float:
        return histogram_percentile(self.counts, q)

    def _fold(self) -> None:
        if self._pending:
            values, self._pending = self._pending, []
            self.extend(values)
