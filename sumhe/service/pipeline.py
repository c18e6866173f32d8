"""The synchronous core shared by ``sumhe run`` and ``sumhe replay``: samples in, estimates out.

:class:`TimeGuard` judges every sample's timestamp before the estimator sees it; :class:`Pipeline` converts GNSS
fixes to the local frame, feeds the estimator and turns its answers into geodetic estimates. Bad time never
crashes the service and never reaches the estimator; each kind has a counter and a log line (rate-limited).

Time rules (s; ``t`` is the sample's time on the service clock):

* ``t <= 0`` or not finite: dropped (``zero_time``);
* live only (a wall clock is given): ``t`` more than ``future_s`` ahead of the wall clock is dropped
  (``future``), more than ``stale_s`` behind it is dropped (``stale``);
* ``t`` more than ``jump_s`` away from the newest accepted time of any stream (either way): a clock jump; the
  estimator is reset and starts over at the next valid fix (``clock_resets``);
* otherwise older than the newest accepted time of its own stream (each CAN quantity, GNSS): dropped (``late``);
  the same sample twice: dropped (``duplicate``). Time order is judged per stream, not across them: samples reach
  the estimator as they arrive (no reorder hold), so a fix comes after the CAN samples of its latency, and the
  estimators insert it at its time (a fix too far behind the CAN data is theirs to drop: ``late_fixes``);
* GNSS fixes whose time is more than ``skew_s`` away from the newest CAN time, while both run: counted as
  ``skew`` and reported (a receiver latency or clock offset is misconfigured); the fix is still used.
"""

from __future__ import annotations

import bisect
import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from sumhe.config import Config
from sumhe.estimator.base import Estimator, to_estimate
from sumhe.frontend.fixes import FixConverter, LocalFix
from sumhe.messages import CanSample, Estimate, GnssFix, Sample

log = logging.getLogger(__name__)

LOG_EVERY_S = 10.0


@dataclass(frozen=True, slots=True)
class TimeRules:
    """Limits of :class:`TimeGuard` (s)."""

    future_s: float = 2.0
    stale_s: float = 10.0
    jump_s: float = 30.0
    skew_s: float = 1.0


@dataclass
class TimeStats:
    accepted: int = 0
    zero_time: int = 0
    future: int = 0
    stale: int = 0
    late: int = 0
    duplicate: int = 0
    clock_resets: int = 0
    skew: int = 0
    last_skew_s: float = 0.0


class TimeGuard:
    """Decides, per sample, ``"ok"``, ``"drop"`` or ``"reset"`` (a clock jump: reset, then take the sample)."""

    def __init__(self, rules: TimeRules, wall_clock: Callable[[], float] | None = None) -> None:
        self.rules = rules
        self.wall_clock = wall_clock
        self.stats = TimeStats()
        self._newest = -math.inf
        self._newest_can = -math.inf
        self._streams: dict[str | tuple[str, str], tuple[float, tuple[object, ...]]] = {}
        """Per stream (each CAN quantity by its name, GNSS as :data:`_GNSS`): the newest accepted time and that
        sample's identity (within its stream: the time and the values)."""
        self._next_log = 0.0

    def check(self, sample: Sample) -> str:
        t, r, s = sample.t, self.rules, self.stats
        verdict = "ok"
        if not math.isfinite(t) or t <= 0.0:
            s.zero_time += 1
            verdict = "drop"
        elif self.wall_clock is not None and t > self.wall_clock() + r.future_s:
            s.future += 1
            verdict = "drop"
        elif self.wall_clock is not None and t < self.wall_clock() - r.stale_s:
            s.stale += 1
            verdict = "drop"
        elif math.isfinite(self._newest) and abs(t - self._newest) > r.jump_s:
            s.clock_resets += 1
            log.warning("clock jump of %.1f s: estimator reset", t - self._newest)
            self._newest = self._newest_can = -math.inf
            self._streams.clear()
            verdict = "reset"
        # the stream and the identity that tells the same sample twice, by one type test (three, and two max() calls,
        # made the guard 1.5 times slower); in the method, not a function of its own: a call less a sample
        if isinstance(sample, CanSample):
            stream: str | tuple[str, str] = sample.quantity
            key: tuple[object, ...] = (t, sample.value)
            can = True
        else:
            stream, key, can = _GNSS, (t, sample.lat_deg, sample.lon_deg), False
        newest, last_key = self._streams.get(stream, _NEVER)
        if verdict == "ok" and t < newest:
            s.late += 1
            verdict = "drop"
        if verdict == "drop":
            self._log_drops()
            return verdict
        if key == last_key:
            s.duplicate += 1
            return "drop"
        self._streams[stream] = (t, key)
        if t > self._newest:  # t is finite here: max() without the call
            self._newest = t
        if can:
            if t > self._newest_can:
                self._newest_can = t
        elif math.isfinite(self._newest_can) and abs(t - self._newest_can) > r.skew_s:
            s.skew += 1
            s.last_skew_s = t - self._newest_can
        s.accepted += 1
        return verdict

    def _log_drops(self) -> None:
        now = time.monotonic()
        if now >= self._next_log:
            self._next_log = now + LOG_EVERY_S
            s = self.stats
            log.warning(
                "samples dropped for their time so far: zero %d, future %d, stale %d, late %d",
                s.zero_time,
                s.future,
                s.stale,
                s.late,
            )


_NEVER: tuple[float, tuple[object, ...] | None] = (-math.inf, None)
"""A stream's newest accepted time and identity before its first sample."""
_GNSS = ("gnss", "")
"""The GNSS stream's key in :attr:`TimeGuard._streams` (a tuple: no CAN quantity's name is one)."""


@dataclass
class PipelineStats:
    fixes: int = 0
    valid_fixes: int = 0
    can_samples: int = 0
    estimates: int = 0
    first_fix_t: float | None = None
    last_estimate: Estimate | None = field(default=None, repr=False)


class Pipeline:
    """Samples as they arrive -> time checks -> local frame -> estimator -> geodetic estimates."""

    def __init__(
        self,
        config: Config,
        estimator: Estimator,
        rules: TimeRules | None = None,
        wall_clock: Callable[[], float] | None = None,
    ) -> None:
        self.config = config
        self.estimator = estimator
        self.guard = TimeGuard(rules or TimeRules(), wall_clock)
        self.converter = FixConverter(config.datum)
        self.stats = PipelineStats()
        self._up_m = 0.0

    def push(self, sample: Sample) -> list[Estimate]:
        """Feed one sample; returns the estimates it produced (possibly none)."""
        verdict = self.guard.check(sample)
        if verdict != "ok":
            if verdict == "drop":
                return []
            self.estimator.reset()
        item: LocalFix | CanSample
        if isinstance(sample, GnssFix):
            item = self._local_fix(sample)
        else:
            self.stats.can_samples += 1
            item = sample
        frame = self.converter.frame
        if frame is None:
            return []
        states = self.estimator.push(item)
        if not states:  # two CAN samples in three (the yaw rate's) answer nothing
            return []
        out = [to_estimate(s, frame, self._up_m) for s in states]
        self._count(out)
        return out

    def finish(self) -> list[Estimate]:
        """The end of a recorded drive: what an offline smoother produces then (nothing for live estimators)."""
        finish = getattr(self.estimator, "finish", None)
        frame = self.converter.frame
        if finish is None or frame is None:
            return []
        out = [to_estimate(s, frame, self._up_m) for s in finish()]
        self._count(out)
        return out

    def _local_fix(self, fix: GnssFix) -> LocalFix:
        self.stats.fixes += 1
        local = self.converter.convert(fix)
        if local.valid:
            self.stats.valid_fixes += 1
            self._up_m = local.up_m
            if self.stats.first_fix_t is None:
                self.stats.first_fix_t = local.t
                log.info("first fix at t=%.3f: estimating", local.t)
        return local

    def _count(self, estimates: list[Estimate]) -> None:
        if estimates:
            self.stats.estimates += len(estimates)
            self.stats.last_estimate = estimates[-1]


MAX_HELD = 1000
"""Estimates the output edge holds at most (a GNSS time offset of a second at 100 Hz CAN data is a hundred)."""


def _stamp(est: Estimate) -> float:
    return est.t


class MonotonicOutput:
    """The output edge's time order. An estimate stamped before the last one let through is dropped and counted
    (``out_of_order``): a Kalman filter reports an epoch at the epoch's own time, up to the receiver latency before
    the CAN-rate estimate it already sent, and the next CAN-rate estimate carries the fix anyway. An estimate stamped
    after the input's clock (the newest sample's time) is held and let out in its place once the clock reaches it
    (``held``): the MHE stamps an epoch at the fix's true time on the CAN clock, which a positive GNSS time offset
    puts ahead of the CAN data; sent at once, it would drop every CAN-rate estimate up to its time (on a realistic
    simulated drive with a +0.29 s offset, 14 494 of 18 000 estimates). At most :data:`MAX_HELD` are held (the
    oldest goes out first beyond that); :meth:`flush` lets out the rest at the end. Estimators and benchmarks see
    every estimate; only what is sent or written goes through here."""

    def __init__(self) -> None:
        self.last_t = -math.inf
        self.out_of_order = 0
        self.held = 0
        self._held: list[Estimate] = []

    def release(self, estimates: Iterable[Estimate], now: float) -> list[Estimate]:
        """What may go out now, in time order: ``estimates`` (just made, the input's clock at ``now``) and the held
        ones whose time ``now`` has reached."""
        out: list[Estimate] = []
        held = self._held  # mostly empty: its releases are not called for then (two calls an estimate less)
        for est in estimates:
            if est.t > now:
                bisect.insort(held, est, key=_stamp)
                self.held += 1
                if len(held) > MAX_HELD:
                    self._admit(held.pop(0), out)
                continue
            if held:
                self._release_until(est.t, out)
            self._admit(est, out)
        if held:
            self._release_until(now, out)
        return out

    def flush(self) -> list[Estimate]:
        """The held estimates, in time order (the input has ended)."""
        out: list[Estimate] = []
        self._release_until(math.inf, out)
        return out

    def _release_until(self, t: float, out: list[Estimate]) -> None:
        while self._held and self._held[0].t <= t:
            self._admit(self._held.pop(0), out)

    def _admit(self, est: Estimate, out: list[Estimate]) -> None:
        if est.t < self.last_t:
            self.out_of_order += 1
            return
        self.last_t = est.t
        out.append(est)

    def reset(self) -> list[Estimate]:
        """A clock jump back: start over from the next estimate; the held ones, to go out before it."""
        held = self.flush()
        self.last_t = -math.inf
        return held
