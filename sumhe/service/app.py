"""``sumhe run``: the live service wired with asyncio.

sources (CAN bus, serial GNSS; or any async iterators of samples) -> a short reorder buffer (time order across
sources) -> the estimator, run off the event loop in a worker thread -> sinks (UDP JSON / NMEA) and a status line.

* Readers never stall: sources run in their own threads; the estimator runs in ``asyncio.to_thread``.
* No backlog: samples released while a solve runs are taken as one batch; when the batch comes out later than
  one hold time (the estimator fell behind) and holds several GNSS epochs, only the newest is solved, the older
  ones are skipped and counted (``skipped_epochs``).
* The reorder buffer releases samples in time order, each ``hold_s`` after its own timestamp (or after its
  arrival, if that was earlier: a future-dated sample never blocks the rest), on the service clock. A fix is
  stamped ``latency`` before it arrives and its epoch is complete only after the serial source's idle gap
  (50 ms), so the default hold is the receiver latency + 100 ms: the price of strict time order, paid by every
  output (the status line reports it as latency).
* Time: every timestamp is on one service clock (``time.time()`` live; a scaled clock for faster-than-real-time
  demos), which also judges stale and future-dated samples.
* Health: a status line every ``output.status_interval_s`` (log, and JSON to ``output.status_udp`` if set).
* Lifecycle, logged at INFO (``sumhe run`` shows it by default): ``sumhe starting`` (what is read and where the
  output goes, then the resolved config), ``sumhe ready`` (every source open), ``status: ...`` periodically,
  ``sumhe stopped`` (the final counters; also sent as the last JSON status). SIGINT/SIGTERM set the stop event;
  tasks unwind and buses, ports and sockets close in ``finally``. A source that ends with an error it cannot
  mend (a CAN interface that does not exist) stops the service with that error.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import itertools
import json
import logging
import math
import signal
import time
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sumhe import __version__
from sumhe.config import Config, describe
from sumhe.estimator.base import Estimator
from sumhe.io.fixtime import stamp_fix
from sumhe.io.source import SourceTimeout
from sumhe.io.udp import UdpSender, UdpSink
from sumhe.messages import Estimate, GnssFix, Sample
from sumhe.service.pipeline import Pipeline, TimeRules

log = logging.getLogger(__name__)

REORDER_MARGIN_S = 0.1
SOLVE_WINDOW = 2000
READY_POLL_S = 0.1
SOURCE_COUNTERS = (
    "reconnects",
    "dropped",
    "decode_errors",
    "crc_errors",
    "stale",
    "error_frames",
    "fd_frames",
    "remote_frames",
)
"""Source counters shown in the status line when not zero (the JSON status has them all)."""


@dataclass
class ServiceStats:
    """What the status line reports (besides the sources' and the estimator's own counters)."""

    started_wall: float = field(default_factory=time.monotonic)
    received: dict[str, int] = field(default_factory=dict)
    timeouts: dict[str, int] = field(default_factory=dict)
    skipped_epochs: int = 0
    batches: int = 0
    sent: int = 0
    solve_ms: deque[float] = field(default_factory=lambda: deque(maxlen=SOLVE_WINDOW))
    latency_ms: deque[float] = field(default_factory=lambda: deque(maxlen=SOLVE_WINDOW))


class Reorder:
    """Holds samples until ``min(t, arrival) + hold_s`` (service clock) and releases them in time order."""

    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self._heap: list[tuple[float, int, float, Sample]] = []
        self._seq = itertools.count()
        self.event = asyncio.Event()

    def put(self, sample: Sample, now: float) -> None:
        due = min(sample.t, now) + self.hold_s if math.isfinite(sample.t) else now
        heapq.heappush(self._heap, (sample.t, next(self._seq), due, sample))
        self.event.set()

    def release(self, now: float) -> tuple[list[Sample], float]:
        """Samples due by ``now``, in time order (a sample waits for any earlier-stamped one still held), and how
        late (s) the earliest-due of them is released: more than ``hold_s`` means the consumer fell behind."""
        out: list[Sample] = []
        first_due = now
        while self._heap and self._heap[0][2] <= now:
            _, _, due, sample = heapq.heappop(self._heap)
            first_due = min(first_due, due)
            out.append(sample)
        return out, now - first_due

    def next_due(self) -> float | None:
        """When the earliest-stamped sample is due (it gates all later-stamped ones)."""
        return self._heap[0][2] if self._heap else None

    def clear(self) -> None:
        self._heap.clear()


def newest_epoch_only(batch: list[Sample]) -> tuple[list[Sample], int]:
    """Drop all GNSS epochs of a batch but the newest; returns the batch and how many were skipped."""
    fix_positions = [i for i, s in enumerate(batch) if isinstance(s, GnssFix)]
    if len(fix_positions) <= 1:
        return batch, 0
    skip = set(fix_positions[:-1])
    return [s for i, s in enumerate(batch) if i not in skip], len(skip)


def percentile(values: deque[float] | list[float], q: float) -> float:
    return float(np.percentile(np.fromiter(values, float), q)) if values else float("nan")


class Service:
    """One running instance: ``await Service(...).run(stop)``."""

    def __init__(
        self,
        config: Config,
        estimator: Estimator,
        sources: dict[str, AsyncIterator[Sample]],
        sink: Callable[[Estimate], None] | None = None,
        hold_s: float | None = None,
        rules: TimeRules | None = None,
        clock: Callable[[], float] = time.time,
        clock_rate: float = 1.0,
    ) -> None:
        self.config = config
        self.estimator = estimator
        self.sources = sources
        self.clock = clock
        self.clock_rate = clock_rate
        self.pipeline = Pipeline(config, estimator, rules, wall_clock=clock)
        self.stats = ServiceStats()
        epoch_s = config.gps.epoch_span_s if config.gps.source == "can" else 0.0  # a CAN GNSS epoch may come late
        self.reorder = Reorder(config.gps.latency_s + epoch_s + REORDER_MARGIN_S if hold_s is None else hold_s)
        self._udp = UdpSink(config.output, config.blame)
        status_udp = config.output.status_udp
        self._status_udp = (
            UdpSender([status_udp], "output.status_udp", config.blame("output.status_udp"), config.output.allow_remote)
            if status_udp
            else None
        )
        self._extra_sink = sink

    async def run(self, stop: asyncio.Event) -> None:
        """Run until ``stop`` is set; everything is closed when this returns."""
        log.info("sumhe starting (version %s): %s", __version__, self.summary())
        log.info("config: %s", json.dumps(describe(self.config), default=str))
        for src in self.sources.values():
            start = getattr(src, "start", None)
            if start is not None:
                await start()  # idempotent: a caller may have started them already
        tasks = [asyncio.create_task(self._read(name, src), name=f"read-{name}") for name, src in self.sources.items()]
        tasks.append(asyncio.create_task(self._estimate(), name="estimate"))
        tasks.append(asyncio.create_task(self._status(), name="status"))
        ready = asyncio.create_task(self._ready(), name="ready")  # ends by itself: not watched
        try:
            stopper = asyncio.create_task(stop.wait())
            done, _ = await asyncio.wait([stopper, *tasks], return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if task is not stopper and task.exception() is not None:
                    raise task.exception()  # type: ignore[misc]
        finally:
            for task in (*tasks, ready):
                task.cancel()
            await asyncio.gather(*tasks, ready, return_exceptions=True)
            for src in self.sources.values():
                close = getattr(src, "close", None)
                if close is not None:
                    with contextlib.suppress(Exception):
                        await close()
            log.info("sumhe stopped after %.1f s: %s", time.monotonic() - self.stats.started_wall, self.status_line())
            self._send_status()
            self._udp.close()
            if self._status_udp is not None:
                self._status_udp.close()

    def summary(self) -> str:
        """What the service reads and where its output goes (the start-up line)."""
        c = self.config
        reads = []
        for name in self.sources:
            if name == "can":
                quantities = ", ".join([*c.can.signals, *(f"gps {q}" for q in c.gps.signals)])  # gps: source "can"
                reads.append(f"can {c.can.interface} {c.can.channel} ({quantities}; DBC {', '.join(c.can.dbc_files)})")
            elif name == "gps":
                reads.append(f"gps {c.gps.port} at {c.gps.baudrate} Bd")
            else:
                reads.append(name)
        return (
            f"estimator {self.estimator.name}; reading {'; '.join(reads)}; sending {self._udp.describe()}; "
            f"config {c.source}"
        )

    async def _ready(self) -> None:
        """Log ``sumhe ready`` once every source is open (sources without a ``stats.connected`` count as open)."""
        while True:
            waiting = [n for n, s in self.sources.items() if not getattr(getattr(s, "stats", None), "connected", 1)]
            if not waiting:
                log.info("sumhe ready: %s open; estimates follow the first GNSS fix", ", ".join(self.sources))
                return
            await asyncio.sleep(READY_POLL_S)

    async def _read(self, name: str, source: AsyncIterator[Sample]) -> None:
        self.stats.received[name] = 0
        self.stats.timeouts[name] = 0
        while True:
            try:
                sample = await anext(source)
            except SourceTimeout:
                self.stats.timeouts[name] += 1
                if self.stats.timeouts[name] in (1, 10) or self.stats.timeouts[name] % 60 == 0:
                    log.warning("%s: nothing received (%d timeouts so far)", name, self.stats.timeouts[name])
                continue
            except StopAsyncIteration:
                log.info("%s: source ended", name)
                return
            self.stats.received[name] += 1
            if isinstance(sample, GnssFix):
                sample = stamp_fix(sample, self.config.gps)
            self.reorder.put(sample, self.clock())

    async def _estimate(self) -> None:
        while True:
            due = self.reorder.next_due()
            if due is None:
                self.reorder.event.clear()
                await self.reorder.event.wait()
                continue
            delay = (due - self.clock()) / self.clock_rate
            if delay > 0:
                self.reorder.event.clear()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self.reorder.event.wait(), delay)
                continue
            batch, lag = self.reorder.release(self.clock())
            skipped = 0
            if lag > self.reorder.hold_s:  # the estimator fell behind: solve the newest epoch only
                batch, skipped = newest_epoch_only(batch)
            if skipped:
                self.stats.skipped_epochs += skipped
                log.warning("estimator behind: %d GNSS epochs skipped (%d so far)", skipped, self.stats.skipped_epochs)
            self.stats.batches += 1
            estimates, epoch_ms = await asyncio.to_thread(self._push_all, batch)
            self.stats.solve_ms.extend(epoch_ms)
            for est in estimates:
                self._send(est)

    def _push_all(self, batch: list[Sample]) -> tuple[list[Estimate], list[float]]:
        """Push a batch (in the worker thread): the estimates, and the update time (ms) of each GNSS epoch."""
        out: list[Estimate] = []
        epoch_ms: list[float] = []
        for sample in batch:
            t0 = time.perf_counter()
            out.extend(self.pipeline.push(sample))
            if isinstance(sample, GnssFix) and self.pipeline.stats.first_fix_t is not None:
                epoch_ms.append((time.perf_counter() - t0) * 1000.0)
        return out, epoch_ms

    def _send(self, est: Estimate) -> None:
        self.stats.latency_ms.append((self.clock() - est.t) * 1000.0)
        if self._udp is not None:
            self._udp.send(est)
        if self._extra_sink is not None:
            self._extra_sink(est)
        self.stats.sent += 1

    async def _status(self) -> None:
        interval = self.config.output.status_interval_s
        while True:
            await asyncio.sleep(interval)
            log.info("status: %s", self.status_line())
            self._send_status()

    def _send_status(self) -> None:
        if self._status_udp is not None:
            self._status_udp.send(json.dumps(self.status(), default=str, separators=(",", ":")).encode())

    def status(self) -> dict[str, Any]:
        """The health figures as plain data (the JSON status datagram)."""
        elapsed = max(time.monotonic() - self.stats.started_wall, 1e-9)
        ps = self.pipeline.stats
        est = ps.last_estimate
        return {
            "class": "STATUS",
            "rates_hz": {k: round(v / elapsed, 2) for k, v in self.stats.received.items()},
            "source_timeouts": dict(self.stats.timeouts),
            "sources": {k: _counters(s) for k, s in self.sources.items()},
            "time": vars(self.pipeline.guard.stats),
            "fix": "no fix yet" if ps.first_fix_t is None else "ok",
            "estimates": ps.estimates,
            "sent": self.stats.sent,
            "skipped_epochs": self.stats.skipped_epochs,
            "solve_ms_p50": round(percentile(self.stats.solve_ms, 50), 3),
            "solve_ms_p99": round(percentile(self.stats.solve_ms, 99), 3),
            "latency_ms_p50": round(percentile(self.stats.latency_ms, 50), 3),
            "latency_ms_p99": round(percentile(self.stats.latency_ms, 99), 3),
            "window": est.window if est else 0,
            "mode": est.mode if est else "no fix yet",
            "gps": est.gps if est else "outage",
            "estimator": dict(self.estimator.stats()),
        }

    def status_line(self) -> str:
        s = self.status()
        t = s["time"]
        time_drops = t["zero_time"] + t["future"] + t["stale"] + t["late"] + t["duplicate"]
        rates = " ".join(f"{k}={v:g}Hz" for k, v in s["rates_hz"].items())
        sources = "".join(
            f" {name}[{' '.join(f'{k}={c[k]}' for k in SOURCE_COUNTERS if c.get(k))}]"
            if any(c.get(k) for k in SOURCE_COUNTERS)
            else ""
            for name, c in s["sources"].items()
        )
        down = "".join(
            f" {name}=DOWN({c.get('last_error', '')})"
            for name, c in s["sources"].items()
            if c.get("connected") is False and c.get("last_error")
        )
        return (
            f"{rates} fix={s['fix']} gps={s['gps']} mode={s['mode']} window={s['window']} "
            f"solve p50/p99={s['solve_ms_p50']}/{s['solve_ms_p99']} ms sent={s['sent']} "
            f"skipped={s['skipped_epochs']} time_drops={time_drops}{sources}{down}"
        )


def _counters(source: object) -> dict[str, Any]:
    counters = getattr(source, "counters", None)
    return dict(counters()) if counters is not None else {}


def install_signal_handlers(stop: asyncio.Event) -> None:
    """SIGINT, SIGTERM and SIGHUP set ``stop`` (where the platform allows it). SIGHUP (the terminal hung up) stops
    cleanly as the others do; it does not re-read the config: a new config means new sources and a new estimator,
    which a restart gives (``systemctl restart sumhe``)."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", signal.SIGTERM)):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)
