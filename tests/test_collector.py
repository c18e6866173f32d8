"""The daemon's garbage-collector watch and policy (``sumhe.service.collector``): pauses counted per generation,
collections in flight found, frozen start-up objects that leave garbage made later collectable, and the send
latencies the status reads beside each send's collection."""

from __future__ import annotations

import gc
import math
import os
import threading
import time
import weakref

import pytest

from sumhe.bench.live import _run_queue, gc_line
from sumhe.service.collector import YOUNG_THRESHOLD, GcWatch, settle, young_collections_every
from sumhe.service.latency import SendLatency, slow_with_gc


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


def test_send_latencies_read_while_a_thread_adds_them_stay_whole():
    """The status reads the latencies in the event loop while the worker thread adds them (the status once found
    the latency and collection columns of different lengths and stopped the service)."""
    latency = SendLatency(window=500)
    stop = threading.Event()
    count = 0

    def send() -> None:
        nonlocal count
        while not stop.is_set():
            latency.add(1.0 + count % 7, count % 4 - 1)
            count += 1

    sender = threading.Thread(target=send)
    sender.start()
    seen = []
    try:
        while not count:
            time.sleep(0.001)
        deadline = time.monotonic() + 0.5
        while time.monotonic() < deadline:
            seen.append(latency.figures())
    finally:
        stop.set()
        sender.join()
    assert len(seen) > 10 and count > 1000
    assert all(f["latency_slow"]["slow"] >= 1 and f["latency_ms_p50"] <= f["latency_ms_p99"] for f in seen)
    assert latency.figures()["latency_run"]["sends"] == count
    assert latency.figures()["latency_ms_p99"] == 7.0


def test_send_latencies_before_any_send_are_empty():
    figures = SendLatency(window=10).figures()
    assert math.isnan(figures["latency_ms_p50"]) and figures["latency_slow"] == {"slow": 0}
    assert figures["latency_run"]["sends"] == 0


def test_young_collections_every_raises_the_threshold_only_and_restores_it_even_on_an_error() -> None:
    before = gc.get_threshold()
    try:
        gc.set_threshold(700, *before[1:])
        with young_collections_every():
            assert gc.get_threshold() == (YOUNG_THRESHOLD, *before[1:])
        assert gc.get_threshold() == (700, *before[1:])
        gc.set_threshold(50_000, *before[1:])
        with pytest.raises(KeyError), young_collections_every():
            assert gc.get_threshold()[0] == 50_000  # never more often than it already is
            raise KeyError
        assert gc.get_threshold() == (50_000, *before[1:])
    finally:
        gc.set_threshold(*before)
