"""The daemon's garbage-collector watch and policy (``sumhe.service.collector``): pauses counted per generation,
collections in flight found, and frozen start-up objects that leave garbage made later collectable."""

from __future__ import annotations

import gc
import os
import time
import weakref

import pytest

from sumhe.bench.live import _run_queue, gc_line
from sumhe.service.app import slow_with_gc
from sumhe.service.collector import GcWatch, settle


class Node:
    """A container in a reference cycle with itself: only the cyclic collector frees it."""

    def __init__(self) -> None:
        self.me = self
        self.payload = [0.0] * 8


@pytest.fixture
def frozen_after():
    yield
    gc.unfreeze()


def test_the_watch_counts_each_generation_and_finds_collections_in_flight():
    watch = GcWatch()
    watch.install()
    watch.install()  # idempotent: one callback
    before = time.time()
    try:
        gc.collect(0)
        gc.collect(2)
    finally:
        watch.remove()
        watch.remove()
    figures = watch.figures()
    assert figures["gen0"]["count"] >= 1 and figures["gen2"]["count"] == 1
    assert figures["gen2"]["max_ms"] > 0.0 and figures["gen2"]["total_ms"] >= figures["gen2"]["max_ms"]
    assert watch.during(before) == 2
    assert watch.during(time.time() + 1.0) == -1
    counted = watch.generations[2].count
    gc.collect(2)
    assert watch.generations[2].count == counted  # removed: no longer called


def test_settle_collects_the_garbage_before_freezing(frozen_after):
    dead = weakref.ref(Node())
    assert dead() is not None  # only the cycle holds it
    frozen = settle("test")
    assert frozen == gc.get_freeze_count() > 0
    assert dead() is None


def test_after_settle_new_garbage_is_still_collected_and_memory_stays_bounded(frozen_after):
    settle("test")
    tracked = len(gc.get_objects())
    refs = []
    for k in range(50_000):  # automatic collections only: the thresholds as the service leaves them
        node = Node()
        if k % 1000 == 0:
            refs.append(weakref.ref(node))
        del node
    assert len(gc.get_objects()) < tracked + 5_000  # 50 000 cycles made, at most a few young ones left
    gc.collect()
    assert all(r() is None for r in refs)


def test_the_slow_sends_are_counted_with_the_collection_in_flight():
    latency = [1.0] * 98 + [30.0, 40.0]
    gens = [-1] * 98 + [2, -1]
    assert slow_with_gc(latency, gens, 99) == {"slow": 1, "gc_gen0": 0, "gc_gen1": 0, "gc_gen2": 0}
    assert slow_with_gc(latency, gens, 98) == {"slow": 2, "gc_gen0": 0, "gc_gen1": 0, "gc_gen2": 1}
    assert slow_with_gc([], [], 99) == {"slow": 0}


def test_bench_live_reads_the_run_queue_and_says_which_slow_sends_met_a_collection():
    waited, slices = _run_queue(os.getpid())
    assert waited >= 0.0 and slices >= 1
    watch = GcWatch()
    watch.install()
    try:
        gc.collect()
    finally:
        watch.remove()
    line = gc_line(watch.figures(), {"slow": 3, "gc_gen0": 0, "gc_gen1": 0, "gc_gen2": 1})
    assert "gen2 1 x" in line and "of its 3 sends at or above the p99, 0 / 0 / 1 were in flight" in line
