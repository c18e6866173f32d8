"""``sumhe run``: the live service wired with asyncio.

sources (CAN bus, serial GNSS; or any async iterators of samples) -> an inbox -> the estimator, run off the event
loop in a worker thread -> the output edge (time order) -> sinks (UDP JSON / NMEA) and a status line.

* No hold: each sample goes to the estimator as it arrives, so a CAN sample's estimate leaves as soon as it is
  computed. Time order is judged per stream (:class:`~sumhe.service.pipeline.TimeGuard`): a GNSS fix arrives
  after the CAN samples of its latency and the estimators insert it at its time (the MHE builds its epoch from
  its CAN buffer, the Kalman family re-runs from its state stored before the fix). What waits while a
  push runs is taken earliest-stamped first (at most ``MAX_CHUNK`` samples at a time, :class:`Inbox`); after a
  stall (input older than ``STALL_S``: counted ``stalls``, a WARNING) the service waits ``STALL_WAIT_S`` once so
  the sources' backlogs meet, then takes them in time order.
* Readers never stall: sources run in their own threads; the estimator runs in ``asyncio.to_thread``, which
  sends each sample's estimates as soon as that sample is pushed (through the output edge, under a lock). An
  estimator with ``solve_aside`` (the MHE) solves each GNSS epoch in a thread of its own: the CAN samples that come
  meanwhile are answered from the propagated prediction, and the solution, once done, is propagated over them
  (mode ``"aside"`` for the epoch's own estimate, the prediction). Which CAN samples came while a solve ran is
  a matter of timing: a replay of the recorded inputs (solved inline) gives the estimates of the others again.
* Degraded, never silent: when the oldest waiting sample arrived more than ``BEHIND_S`` ago, the estimator has
  fallen behind: an ERROR line, ``degraded`` episodes counted, every estimate sent with ``mode = "degraded"``, and
  an estimator with ``defer_solves`` (the MHE) appends its GNSS epochs without a solve, so it keeps pace at CAN rate
  from its newest solved state; each chunk that finds the backlog under ``SOLVE_BACKLOG_S`` solves again (the
  appended epochs with it). Back under ``RECOVER_S``: normal again (an INFO line with the episode's length). No
  epoch is skipped. The inbox holds at most ``MAX_BACKLOG`` samples; beyond, the oldest are dropped and counted
  (``backlog_dropped``).
* Output time order: an estimate stamped before one already sent is dropped and counted (``out_of_order``,
  :class:`~sumhe.service.pipeline.MonotonicOutput`): the Kalman family reports an epoch at its own time, up to the
  receiver latency before the CAN-rate estimate before it. A clock jump (``time.clock_resets``) starts over.
* Time: every timestamp is on one service clock (``time.time()`` live; a scaled clock for faster-than-real-time
  demos), which also judges stale and future-dated samples. The backlog is measured on ``time.monotonic()``. A
  fix's time is its measurement time (:class:`~sumhe.io.fixtime.FixClock`: its UTC time, moved by the learned
  clock offset where the service clock is not on UTC).
* Inputs recorded: ``record`` (``sumhe run --record-inputs``) is called with every sample the estimator takes, in
  its order, with when it arrived and when its push began (``time.monotonic()``; :mod:`sumhe.service.inputs`);
  replaying them gives the same estimates.
* Health: a status line every ``output.status_interval_s`` (log, and JSON to ``output.status_udp`` if set); its
  latency is the service clock at the send minus the estimate's time (for a CAN-rate estimate: since the CAN
  frame's timestamp).
* Lifecycle, logged at INFO (``sumhe run`` shows it by default): ``sumhe starting`` (what is read and where the
  output goes, then the resolved config), ``sumhe ready`` (every source open), ``status: ...`` periodically,
  ``sumhe stopped`` (the final counters; also sent as the last JSON status). SIGINT/SIGTERM set the stop event;
  tasks unwind and buses, ports and sockets close in ``finally``. A source that ends with an error it cannot
  mend (a CAN interface that does not exist) stops the service with that error.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import gc
import heapq
import itertools
import json
import logging
import math
import signal
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

from sumhe import __version__
from sumhe.config import Config, describe
from sumhe.estimator.base import Estimator
from sumhe.io.fixtime import FixClock
from sumhe.io.source import SourceTimeout
from sumhe.io.udp import UdpSender, UdpSink
from sumhe.messages import Estimate, GnssFix, Sample
from sumhe.service.collector import GcWatch, settle
from sumhe.service.latency import SendLatency, percentile
from sumhe.service.pipeline import MonotonicOutput, Pipeline, TimeRules

log = logging.getLogger(__name__)

BEHIND_S = 0.25
"""The oldest waiting sample arrived this long ago (s): the estimator has fallen behind (degraded)."""
SOLVE_BACKLOG_S = 0.1
"""While degraded, a chunk taken with a backlog under this (s) is solved normally (time allows)."""
RECOVER_S = 0.05
"""Degraded ends when a chunk is taken with a backlog under this (s)."""
STALL_S = 1.0
"""The earliest waiting sample is older than this on the service clock (s): the service stalled (SIGSTOP, a
starved process) and the sources' backlogs come in; it waits ``STALL_WAIT_S`` once so that all sources deliver
theirs before the estimator takes them in time order."""
STALL_WAIT_S = 0.1
MAX_CHUNK = 64
"""Samples pushed per call of the worker thread (estimates are sent after each)."""
MAX_BACKLOG = 20_000
"""Samples waiting at most; beyond, the oldest are dropped (``backlog_dropped``)."""
SOLVE_WINDOW = 2000
SETTLE_EPOCHS = 10
"""GNSS epochs pushed (the estimator's objects made, its solver's too) before the worker's first idle moment
freezes what exists (:func:`~sumhe.service.collector.settle`; the first freeze is at start-up)."""
READY_POLL_S = 0.1
SOURCE_COUNTERS = (
    "reconnects",
    "dropped",
    "decode_errors",
    "crc_errors",
    "stale",
    "error_frames",
    "fd_frames",
    "long_frames",
    "remote_frames",
    "restamped",
    "lost",
)
"""Source counters shown in the status line when not zero (the JSON status has them all)."""


@dataclass
class ServiceStats:
    """What the status line reports (besides the sources' and the estimator's own counters)."""

    started_wall: float = field(default_factory=time.monotonic)
    received: dict[str, int] = field(default_factory=dict)
    timeouts: dict[str, int] = field(default_factory=dict)
    batches: int = 0
    sent: int = 0
    out_of_order: int = 0
    degraded: int = 0
    degraded_sent: int = 0
    degraded_s: float = 0.0
    backlog_dropped: int = 0
    stalls: int = 0
    solve_ms: deque[float] = field(default_factory=lambda: deque(maxlen=SOLVE_WINDOW))
    latency: SendLatency = field(default_factory=lambda: SendLatency(SOLVE_WINDOW))
    """Every send's latency and the garbage collection it met (from the estimate's time to its send)."""


class Inbox:
    """Samples as they arrive, taken in chunks of the earliest-stamped (each stream is in time order already, so
    this only orders backlogs of several sources against each other: nothing waits for order); the arrival times
    (``time.monotonic()``) say how far behind the consumer is. Holds at most ``max_len`` samples, dropping the
    earliest-stamped beyond (counted)."""

    def __init__(self, max_len: int = MAX_BACKLOG) -> None:
        self._heap: list[tuple[float, int, Sample, float]] = []
        self._arrivals: deque[float] = deque()
        self._seq = itertools.count()
        self.max_len = max_len
        self.dropped = 0
        self.event = asyncio.Event()
        self.last_arrivals: list[float] = []
        """When each sample the last :meth:`take` handed out arrived (``time.monotonic()``), in its order."""

    def put(self, sample: Sample, arrived: float) -> None:
        if len(self._heap) >= self.max_len:
            heapq.heappop(self._heap)
            self._arrivals.popleft()
            self.dropped += 1
        t = sample.t if math.isfinite(sample.t) else -math.inf
        heapq.heappush(self._heap, (t, next(self._seq), sample, arrived))
        self._arrivals.append(arrived)
        self.event.set()

    def earliest_t(self) -> float:
        """The earliest time stamped on a waiting sample (inf when empty)."""
        return self._heap[0][0] if self._heap else math.inf

    def take(self, n: int) -> tuple[list[Sample], float]:
        """Up to ``n`` earliest-stamped samples in time order, and when the oldest waiting sample arrived."""
        arrived = self._arrivals[0] if self._arrivals else time.monotonic()
        k = min(n, len(self._heap))
        for _ in range(k):
            self._arrivals.popleft()
        taken = [heapq.heappop(self._heap) for _ in range(k)]
        self.last_arrivals = [item[3] for item in taken]
        return [item[2] for item in taken], arrived

    def __len__(self) -> int:
        return len(self._heap)


class Service:
    """One running instance: ``await Service(...).run(stop)``."""

    def __init__(
        self,
        config: Config,
        estimator: Estimator,
        sources: dict[str, AsyncIterator[Sample]],
        sink: Callable[[Estimate], None] | None = None,
        rules: TimeRules | None = None,
        clock: Callable[[], float] = time.time,
        clock_rate: float = 1.0,
        record: Callable[[Sample, float, float], None] | None = None,
    ) -> None:
        self.config = config
        self.estimator = estimator
        self.sources = sources
        self.clock = clock
        self.clock_rate = clock_rate
        self.pipeline = Pipeline(config, estimator, rules, wall_clock=clock)
        self.stats = ServiceStats()
        self.inbox = Inbox()
        self.output = MonotonicOutput()
        self.fix_clock = FixClock(config.gps)
        self.degraded_since: float | None = None
        self._clock_resets = 0
        self._udp = UdpSink(config.output, config.blame)
        status_udp = config.output.status_udp
        self._status_udp = (
            UdpSender([status_udp], "output.status_udp", config.blame("output.status_udp"), config.output.allow_remote)
            if status_udp
            else None
        )
        self._extra_sink = sink
        self._record = record
        self._output_lock = threading.Lock()
        self.gc = GcWatch(clock)
        self._settled = False
        if hasattr(estimator, "solve_aside"):
            estimator.solve_aside = True  # the CAN samples after an epoch do not wait for its solve (docstring)

    async def run(self, stop: asyncio.Event) -> None:
        """Run until ``stop`` is set; everything is closed when this returns."""
        self.gc.install()
        self.gc.frozen = settle("start-up")  # before "sumhe starting": a player starts on that line
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
            with self._output_lock:  # a worker thread still pushing sends under it too
                for est in self.output.flush():  # held ahead of the input's clock when it stopped
                    self._send(est)
            log.info("sumhe stopped after %.1f s: %s", time.monotonic() - self.stats.started_wall, self.status_line())
            self._send_status()
            self.gc.remove()
            gc.unfreeze()  # the policy ends with the service (a process that goes on, as a test does, collects all)
            self.gc.frozen = 0
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
                sample = self.fix_clock.stamp(sample)
            self.inbox.put(sample, time.monotonic())

    async def _estimate(self) -> None:
        stalled = False
        while True:
            if not self.inbox:
                if not self._settled and len(self.stats.solve_ms) >= SETTLE_EPOCHS:
                    self._settled = True
                    self.gc.frozen = settle(f"after the first {SETTLE_EPOCHS} GNSS epochs, the worker idle")
                self.inbox.event.clear()
                await self.inbox.event.wait()
                continue
            if self.clock() - self.inbox.earliest_t() <= STALL_S:
                stalled = False
            elif not stalled:
                stalled = True
                self.stats.stalls += 1
                log.warning(
                    "input %.1f s old: a stall; taking the sources' backlogs in time order",
                    self.clock() - self.inbox.earliest_t(),
                )
                await asyncio.sleep(STALL_WAIT_S / self.clock_rate)
            chunk, arrived = self.inbox.take(MAX_CHUNK)
            backlog = time.monotonic() - arrived
            self._judge_backlog(backlog)
            self.stats.batches += 1
            epoch_ms = await asyncio.to_thread(self._push_all, chunk, self.inbox.last_arrivals)
            self.stats.solve_ms.extend(epoch_ms)

    def _judge_backlog(self, backlog: float) -> None:
        """Enter or leave the degraded state for a chunk taken ``backlog`` s after its first sample arrived, and
        tell an estimator that can defer its solves whether to (the module docstring)."""
        now = time.monotonic()
        if self.degraded_since is None and backlog > BEHIND_S:
            self.degraded_since = now
            self.stats.degraded += 1
            log.error(
                "estimator behind by %.2f s: degraded output (epochs appended unsolved; %d episodes so far)",
                backlog,
                self.stats.degraded,
            )
        elif self.degraded_since is not None and backlog < RECOVER_S:
            length = now - self.degraded_since
            self.stats.degraded_s += length
            self.degraded_since = None
            log.info("estimator caught up after %.1f s degraded: normal output", length)
        if hasattr(self.estimator, "defer_solves"):
            self.estimator.defer_solves = self.degraded_since is not None and backlog >= SOLVE_BACKLOG_S

    def _push_all(self, batch: list[Sample], arrivals: list[float]) -> list[float]:
        """Push a batch (in the worker thread), each sample's estimates sent as soon as it is pushed (not after the
        batch, nor through the event loop: the CAN sample taken after a GNSS epoch's solve does not wait for the rest
        of the batch); the update time (ms) of each GNSS epoch. ``arrivals``: when each sample arrived (monotonic s,
        for the recording)."""
        epoch_ms: list[float] = []
        now = -math.inf
        for sample, arrived in zip(batch, arrivals, strict=True):
            if self._record is not None:
                self._record(sample, arrived, time.monotonic())
            t0 = time.perf_counter()
            estimates = self.pipeline.push(sample)
            if isinstance(sample, GnssFix) and self.pipeline.stats.first_fix_t is not None:
                epoch_ms.append((time.perf_counter() - t0) * 1000.0)
            now = max(now, sample.t)
            with self._output_lock:
                ready: list[Estimate] = []
                if self.pipeline.guard.stats.clock_resets != self._clock_resets:
                    self._clock_resets = self.pipeline.guard.stats.clock_resets
                    ready = self.output.reset()
                ready += self.output.release(estimates, now)
                self.stats.out_of_order = self.output.out_of_order
                for est in ready:
                    self._send(est)
        return epoch_ms

    def _send(self, est: Estimate) -> None:
        if self.degraded_since is not None:
            est = dataclasses.replace(est, mode="degraded")
            self.stats.degraded_sent += 1
        self.stats.latency.add((self.clock() - est.t) * 1000.0, self.gc.during(est.t))
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
            "out_of_order": self.stats.out_of_order,
            "degraded": self.stats.degraded,
            "degraded_sent": self.stats.degraded_sent,
            "degraded_s": round(self.stats.degraded_s + self._degraded_now(), 3),
            "backlog": len(self.inbox),
            "backlog_dropped": self.inbox.dropped,
            "stalls": self.stats.stalls,
            "solve_ms_p50": round(percentile(self.stats.solve_ms, 50), 3),
            "solve_ms_p99": round(percentile(self.stats.solve_ms, 99), 3),
            **self.stats.latency.figures(),
            "gc": self.gc.figures(),
            "window": est.window if est else 0,
            "mode": est.mode if est else "no fix yet",
            "gps": est.gps if est else "outage",
            "estimator": dict(self.estimator.stats()),
        }

    def _degraded_now(self) -> float:
        return time.monotonic() - self.degraded_since if self.degraded_since is not None else 0.0

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
            f"out_of_order={s['out_of_order']} degraded={s['degraded']} backlog={s['backlog']} "
            f"time_drops={time_drops}{sources}{down}"
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
