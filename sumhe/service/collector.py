"""The daemon and Python's cyclic garbage collector: its pauses measured, and the policy that keeps them short.

Measured (:class:`GcWatch`, through ``gc.callbacks``): each collection's generation and length, and when the
latest of each generation ended on the service clock, so that the status can say which slow estimates were in
flight while the collector ran (:meth:`GcWatch.during`).

Policy (:func:`settle`): a collection of the oldest generation traverses every tracked container the process has;
in ``sumhe run`` those are ~112 000 objects made by the imports (functions, types, modules of numpy, scipy, casadi,
python-can; 113 359 after 15 s of ``sumhe bench live``, 112 118 after 65 s), the service's own a few hundred. One
such pass took 9-29 ms on an idle core and up to 164 ms beside busy ones (24 Nov 2026), on whichever thread
allocated, while every other thread waits. Without a policy the daemon made its full collections during its imports
only (the old generation did not grow by the quarter that triggers one, in a minute as in an hour); any later one
(a burst of new objects: a reconnect, a late import) would stop the worker that answers the CAN samples as long.
``gc.freeze()`` moves every tracked object to the permanent generation, which the collector no longer traverses;
the service calls :func:`settle` twice: before it reads any input (imports done, estimator built) and once the
first GNSS epochs have been pushed and the worker is idle (the objects the first solves make lazily: solver
workspaces, late imports, the sources' buses), so later collections only see what was made since (a full one
0.1-0.3 ms, measured). Frozen objects are still freed when their last reference goes (reference counting is not
affected); only a reference cycle among them would stay, and each :func:`settle` runs a full collection first, so
no garbage is frozen. Collections of the young generations stay as they are (the default thresholds), and objects
made after a freeze are collected as before (``tests/test_collector.py`` holds the policy to that). The service
unfreezes when it stops.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

GENERATIONS = 3

YOUNG_THRESHOLD = 20_000
"""The young generation's collection threshold while a process makes many objects that live on (Python's default:
700 net new tracked objects), :func:`young_collections_every`. A replay's loop (:func:`sumhe.bench.reprocess.
replay_drive`): its collections there found nothing to free (bundled drive: 76 of the young generation and 6 of the
middle one, 0 objects collected, 11-12 ms of the 2.0 s loop); at 20 000 it makes none there. A command's start-up
(:func:`sumhe.cli.main`, the imports of its module): ~100 000 objects that live as long as the process, 190 young,
17 middle and one full collection before a replay's loop, 40-60 ms of CPU; at 20 000, 16, 1 and none."""


@dataclass
class GenerationStats:
    """Collections of one generation: how many, the longest and their total (ms)."""

    count: int = 0
    max_ms: float = 0.0
    total_ms: float = 0.0


class GcWatch:
    """Every collection's length per generation, and when the latest of each ended (``last_end``, on ``clock``, s).
    :meth:`install` hooks it into ``gc.callbacks``, :meth:`remove` unhooks it (both idempotent)."""

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self.clock = clock
        self.generations = [GenerationStats() for _ in range(GENERATIONS)]
        self.last_end = [-math.inf] * GENERATIONS
        self.frozen = 0
        """Objects frozen by the latest :func:`settle` (its caller sets it: ``gc.get_freeze_count()`` walks them all,
        ~10 ms for 110 000, too long for the status line)."""
        self._start = 0.0
        self._t0 = 0.0

    def install(self) -> None:
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)

    def remove(self) -> None:
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._start = self.clock()
            self._t0 = time.perf_counter()
            return
        ms = (time.perf_counter() - self._t0) * 1000.0
        gen = info["generation"]
        stats = self.generations[gen]
        stats.count += 1
        stats.total_ms += ms
        stats.max_ms = max(stats.max_ms, ms)
        self.last_end[gen] = self._start + ms / 1000.0

    def during(self, since: float) -> int:
        """The oldest generation collected, at least in part, after ``since`` (clock s); -1 for none."""
        return max((g for g, end in enumerate(self.last_end) if end >= since), default=-1)

    def figures(self) -> dict[str, Any]:
        """Per generation: count, longest and total pause (ms); and how many objects are frozen (``frozen``)."""
        return {
            **{
                f"gen{g}": {"count": s.count, "max_ms": round(s.max_ms, 3), "total_ms": round(s.total_ms, 3)}
                for g, s in enumerate(self.generations)
            },
            "frozen": self.frozen,
        }


@contextlib.contextmanager
def young_collections_every(threshold: int = YOUNG_THRESHOLD) -> Iterator[None]:
    """The young generation collected at most every ``threshold`` net new tracked objects while the block runs (no
    more often than it is already), its threshold restored after: a pass traverses at most that many young
    objects, and a reference cycle made meanwhile waits at most that long to be freed."""
    thresholds = gc.get_threshold()
    gc.set_threshold(max(thresholds[0], threshold), *thresholds[1:])
    try:
        yield
    finally:
        gc.set_threshold(*thresholds)


def settle(why: str) -> int:
    """Collect everything, then freeze what is left (the module docstring); the number of objects now frozen."""
    t0 = time.perf_counter()
    gc.collect()
    gc.freeze()
    frozen = gc.get_freeze_count()
    log.info("gc: %d objects frozen (%s) in %.1f ms", frozen, why, (time.perf_counter() - t0) * 1000.0)
    return frozen
