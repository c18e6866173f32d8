"""The daemon's send latencies: the latest sends (each with the garbage collection it met) and every send since the
start. The worker thread that sends adds them while the status, in the event loop, reads them: both under one lock
(read unlocked, the status found the two columns of different lengths mid-send and the service stopped)."""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from sumhe.service.histogram import Histogram


def percentile(values: ArrayLike, q: float) -> float:
    """The ``q`` percentile of ``values`` (NaN when there are none)."""
    v = np.asarray(values, dtype=float)
    return float(np.percentile(v, q)) if v.size else math.nan


def slow_with_gc(latency_ms: Sequence[float], gens: Sequence[int], q: float) -> dict[str, int]:
    """Of the sends at or above the ``q`` percentile of ``latency_ms``: how many (``slow``), and how many of them
    were in flight while the collector took generation 0, 1 or 2 at the oldest (``gc_gen0`` ...; ``gens`` beside
    ``latency_ms``, -1 for no collection)."""
    lat = np.asarray(latency_ms, dtype=float)
    if not lat.size:
        return {"slow": 0}
    gen = np.asarray(gens, dtype=int)[lat >= np.percentile(lat, q)]
    return {"slow": int(gen.size), **{f"gc_gen{g}": int(np.sum(gen == g)) for g in range(3)}}


def run_figures(h: Histogram) -> dict[str, Any]:
    """A run's latency figures (ms): sends, p50, p99 (within 2.3 %: :class:`Histogram`), max."""
    return {"sends": h.n, **{f"p{q}": round(h.percentile(q), 3) for q in (50, 99)}, "max": round(h.max, 3)}


class SendLatency:
    """Latencies (ms) of the sends: the latest ``window`` beside the collector generation each met (-1 for none,
    :meth:`~sumhe.service.collector.GcWatch.during`), and a :class:`Histogram` of all. Thread-safe."""

    def __init__(self, window: int) -> None:
        self._lock = threading.Lock()
        self._recent: deque[tuple[float, int]] = deque(maxlen=window)
        self._run = Histogram()

    def add(self, ms: float, gen: int) -> None:
        with self._lock:
            self._recent.append((ms, gen))
            self._run.add(ms)

    def figures(self) -> dict[str, Any]:
        """The status's latency figures: p50 and p99 of the latest sends (NaN before any), the whole run's
        (:func:`run_figures`) and the slow sends with the collections they met (:func:`slow_with_gc`)."""
        with self._lock:
            recent = np.array(self._recent, dtype=float).reshape(-1, 2)
            run = run_figures(self._run)
        lat = recent[:, 0]
        return {
            "latency_ms_p50": round(percentile(lat, 50), 3),
            "latency_ms_p99": round(percentile(lat, 99), 3),
            "latency_run": run,
            "latency_slow": slow_with_gc(lat, recent[:, 1].astype(int), 99),
        }
