"""The measurement front-end of the streaming estimators: samples in, epochs and CAN ticks out.

Between the pipeline and every live estimator (MHE, Kalman peers), :class:`FrontEnd` decides once what a sample
is worth and when it counts:

* input checks: bad or non-finite values, CAN values beyond the vehicle limits, time going back (per quantity),
  fixes more than ``MAX_FIX_LAG_S`` behind the CAN data, valid fixes without a usable position ("no fix"): each
  counted in ``stats()`` and logged at its 1st, 10th, 100th ... occurrence, never raised;
* CAN: the samples' measurement time (timestamp - ``sensors.can.delay_s``, and ``speed_delay_s`` more for the
  speed) and a buffer of the recent ones
  (:class:`~sumhe.frontend.can.CanBuffer`) every estimator reads its CAN data from;
* GNSS timing (:class:`~sumhe.frontend.epochs.EpochClock`): the receiver's period, the fixes' delay behind the CAN
  data, the epochs it missed (silence over 1.5 periods: an :class:`Epoch` without a fix, ``missed=True``);
* each fix's measurements by the one policy of :mod:`sumhe.frontend.measurements` (:class:`FixMeasurement`), a
  heading weighed down where its turn disagrees with the CAN yaw rate's (:mod:`~sumhe.frontend.heading_check`,
  counted ``headings_off``);
* the GNSS time offset: a fix's time is moved by ``sensors.gnss.time_offset_s`` onto the CAN clock, or by the
  offset learned on line (:class:`~sumhe.frontend.alignment.ClockLearner`, ``learn_time_offset``), which the
  applied offset follows by at most ``OFFSET_SLEW`` of a period per fix (epochs stay in order); the learner needs
  the fixes' speed over ground: a valid fix without one is counted (``fixes_without_speed``; a receiver that
  sends none had left the offset at the config's all drive without a word: the shared real drive without its
  speed signal ran 0.37 s off, every estimate's ``eph`` carrying 0.3 s of it);
* the CAN mapping checked against the receiver (:class:`~sumhe.frontend.sensor_check.SensorCheck`): a yaw rate's
  flipped sign, a yaw rate that does not follow the azimuth, a yaw-rate gain or bias or a speed scale out of
  bounds, said once and counted; a flipped sign turned round and a gain, bias or scale out of bounds undone from
  the verdict on, the estimator starting over afresh there (``Epoch.fresh``);
* the start: nothing before the first usable fix, which comes as ``Epoch(start=True)``; no sample at all for
  ``MAX_DATA_GAP_S`` restarts there (counted ``restarts``).

Events come out in time order: an epoch a CAN sample's time reveals as missed comes before that sample's tick.

Where the inputs still to come belong (each one place): a course that errs by more than the speed says, or
differs from the heading (sideslip, mounting), is :func:`~sumhe.frontend.measurements.azimuth_measurement`'s; NMEA
without HDOP or GST falls to ``sensors.gnss.sigma_m`` in :func:`~sumhe.frontend.measurements.fix_sigmas`; sparse,
quantised CAN speed (OBD-II polling) is the buffer's and the DBC quantum's (:mod:`sumhe.io.quanta`), and which
samples make an estimate is :data:`OUTPUT_QUANTITY`'s and, between them, ``estimator.can_output_hz``'s
(:attr:`CanTick.output`); a fix arriving after newer CAN data is judged in :meth:`FrontEnd._fix` (``MAX_FIX_LAG_S``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

from sumhe.frontend.alignment import ClockLearner
from sumhe.frontend.can import CAN_USED, CanBuffer, centred_speed, speed_reads_low
from sumhe.frontend.epochs import EpochClock, bad_epoch_time
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.heading_check import HeadingCheck, HeadingFix
from sumhe.frontend.measurements import (
    azimuth_measurement,
    can_acceleration,
    gps_speed,
    gps_speed_sigma,
    timed_speed_sigma,
)
from sumhe.frontend.sensor_check import SensorCheck
from sumhe.frontend.tally import Tally
from sumhe.messages import CanSample
from sumhe.records import quick_init, replace
from sumhe.settings import EstimationSettings

MAX_DATA_GAP_S = 10.0
"""No sample at all for this long (a clock jump, a paused replay) restarts the estimator at the next usable fix."""
MAX_FIX_LAG_S = 1.0
"""Fixes older than this behind the newest CAN data are dropped (counted ``late_fixes``)."""
OUTPUT_QUANTITY = "speed"
"""The CAN quantity whose samples the estimators answer with an estimate (and the other's, between them, at most
``estimator.can_output_hz`` often: :attr:`CanTick.output`)."""
CAN_KEEP_S = 2.0
"""CAN samples are kept for this long, or three periods if longer, behind the newest epoch."""
SAME_EPOCH = 0.25
"""A fix within this fraction of a period after the last epoch handed out (on the CAN clock) is that epoch again."""
MISSED_KEPT = 32
"""At most this many epochs declared missed wait for a fix that comes after (:meth:`FrontEnd._after_missed`)."""
OFFSET_SLEW = 0.2
"""The applied GNSS time offset moves towards the learned one by at most this fraction of a period per fix."""
_NUMBER = (float, int)
"""What ``isinstance`` takes a sample's time and value for: a tuple, built once (``float | int`` in the call builds a
union per CAN sample)."""


@quick_init
@dataclass(frozen=True, slots=True)
class FixMeasurement:
    """What one usable fix measures at ``t`` (s, the measurement time on the CAN clock), with its 1-sigma errors:
    position (m, the local frame), azimuth (rad; a heading, or a course over ground) and speed (m/s, signed like
    the CAN speed), None where it measures none."""

    t: float
    east_m: float
    north_m: float
    sigma_east_m: float
    sigma_north_m: float
    azimuth_rad: float | None
    azimuth_sigma_rad: float
    heading: bool
    speed_mps: float | None
    speed_sigma_mps: float
    fix: LocalFix


@quick_init
@dataclass(frozen=True, slots=True)
class Epoch:
    """A GNSS epoch at ``t`` (s, measurement time): with a usable fix, or without (``fix`` None: the receiver said
    "no fix", or it was silent and the epoch is ``missed``). ``start``: the first usable fix since a (re)start,
    where the estimator starts over."""

    t: float
    fix: FixMeasurement | None
    missed: bool = False
    start: bool = False
    fresh: bool = False
    """With ``start``: the CAN data changed meaning before it (the yaw rate's sign turned round, its gain or bias or
    the speed's scale undone on line, :meth:`FrontEnd._remap`): the CAN sensor states learned before are no longer
    of these data."""
    fills: bool = False
    """The fix of an epoch handed out before as ``missed`` (it came after the epoch was declared missed): the
    estimator puts it in that epoch, as a late fix (:meth:`FrontEnd._after_missed`)."""


class CanTick(NamedTuple):
    """A CAN sample taken in: ``t`` its measurement time, ``stamp`` its timestamp (s); ``output``: the estimators
    answer it with an estimate (every ``speed`` sample; a yaw-rate sample where ``estimator.can_output_hz`` is set
    and the last estimate is at least its period old: between the sparse speed samples of an OBD-II poll, the
    estimate moved on by the model, not kept). A named tuple: one is made per CAN sample."""

    t: float
    stamp: float
    quantity: str
    value: float
    output: bool


def can_limits(settings: EstimationSettings) -> dict[str, float]:
    """The largest magnitude taken of each CAN quantity of :data:`CAN_USED` (m/s, rad/s; the yaw rate's with a
    margin of two)."""
    vehicle = settings.vehicle
    return {q: vehicle.max_speed_mps if q == "speed" else 2.0 * vehicle.max_yaw_rate_rps for q in CAN_USED}


_new_tuple = tuple.__new__
"""Makes a :class:`CanTick` from the tuple of its fields without the named tuple's own ``__new__`` (a Python
function: 170 -> 80 ns a CAN sample)."""


class FrontEnd:
    """Samples -> :class:`Epoch` and :class:`CanTick` events, for one estimator (see the module docstring).

    ``uses_gps_speed = False`` leaves the fixes' speed over ground out even with ``sensors.gnss.use_speed``.
    """

    def __init__(self, settings: EstimationSettings, tally: Tally, uses_gps_speed: bool = True) -> None:
        self.settings = settings
        self.tally = tally
        self.uses_gps_speed = uses_gps_speed and settings.gnss.use_speed
        self.fills_missed = True
        """Whether fixes that come after their epoch was declared missed fill it (:meth:`_after_missed`)."""
        self._limits = can_limits(settings)
        self.check = SensorCheck(settings, tally)
        """The on-line check of the CAN yaw rate's and speed's mapping (its verdicts outlive :meth:`reset`)."""
        self.reset()

    def reset(self) -> None:
        """Forget the CAN data and the stream's timing (the learned time offset too: a clock jump may change it);
        the next usable fix starts over."""
        gnss = self.settings.gnss
        self.can = CanBuffer()
        self.clock = EpochClock(gnss.period_s)
        self.learner = ClockLearner(gnss.time_offset_s)
        """The fits of the receiver's speed over ground against the CAN speed: the time offset learned (applied
        with ``learn_time_offset``: :attr:`aligner`) and the CAN speed's scale :attr:`check` judges."""
        self.aligner = self.learner if gnss.learn_time_offset else None
        self.check.clear()
        can = self.settings.can
        self.headings = HeadingCheck(gnss, can)
        """The receiver's headings against the CAN yaw rate: headings that turn otherwise weigh as far as they are
        off (:mod:`~sumhe.frontend.heading_check`)."""
        self._delay_s = can.delay_s
        self._age_s = {q: can.delay_of(q) for q in CAN_USED}
        """Each quantity's age: a sample is kept at its own measurement time (the speed's may differ, an OBD-II
        reply's), its tick (the estimate that answers it) at the common one, ``delay_s``, so the ticks stay in order."""
        self._speed_reads_low = speed_reads_low(can)
        rate = self.settings.estimator.can_output_hz
        self._between_s = 1.0 / rate if rate > 0 else None
        """The period (s) of the estimates at yaw-rate samples between the speed samples; None: none there."""
        self._t_output = -math.inf
        """The measurement time of the newest CAN sample answered with an estimate."""
        self.time_offset_s = gnss.time_offset_s
        self.started = False
        self._fresh = False
        self._t_last = -math.inf
        self._t_epoch = -math.inf
        """The time of the last epoch handed out, on the CAN clock."""
        self._missed_epochs: deque[float] = deque(maxlen=MISSED_KEPT)
        """The times of the recent epochs declared missed (CAN clock) whose fixes may still come."""

    @property
    def period_s(self) -> float:
        """The nominal GNSS period (s)."""
        return self.clock.period_s

    @property
    def time_offset_sigma_s(self) -> float:
        """The root mean square error (s) of the GNSS time offset applied (:attr:`time_offset_s`) where it is
        learned: the learner's standard deviation (:attr:`~sumhe.frontend.alignment.ClockLearner.sigma_s`) and the
        part of its offset the slew has not applied yet; 0 for a configured offset (a calibration)."""
        learner = self.aligner
        if learner is None:
            return 0.0
        return math.hypot(learner.sigma_s, learner.offset_s - self.time_offset_s)

    def timed_speed_sigma_mps(self, fix: FixMeasurement) -> float:
        """The sigma (m/s) of ``fix``'s speed over ground with the error of its uncertain time while the car
        accelerates (:func:`~sumhe.frontend.measurements.timed_speed_sigma` at :attr:`time_offset_sigma_s`, the
        acceleration the CAN speed's change over the last half second): a speed measured at the wrong instant differs
        from the CAN speed by the acceleration times the error. Without it the estimators' speed scale took the speed
        over ground of the first acceleration from standstill: the EKF's up to 13 % off with a sigma of 0.3 %, the
        MHE's to its bound (1.05 for 1.019) on a realistic simulated highway drive whose fixes were 0.29 s off."""
        time_sigma = self.time_offset_sigma_s
        if not time_sigma:
            return fix.speed_sigma_mps
        acceleration = can_acceleration(self.can["speed"], fix.t, self.settings.can.max_gap_s)
        return timed_speed_sigma(fix.speed_sigma_mps, acceleration, time_sigma)

    def push(self, sample: object) -> list[Epoch | CanTick]:
        """One sample in (time-ordered), its events out."""
        if isinstance(sample, CanSample):
            return self._can(sample)
        if isinstance(sample, LocalFix):
            return self._fix(sample)
        self.tally.count("bad_samples", "not a LocalFix or CanSample: %s", type(sample).__name__)
        return []

    def restart(self) -> None:
        """Start over at the next usable fix, keeping the CAN data and the timing (the estimator's own restart)."""
        self.started = False

    # ---- CAN --------------------------------------------------------------------------------------------------

    def _can(self, sample: CanSample) -> list[Epoch | CanTick]:
        """The events of a CAN sample (none for a quantity not in :data:`CAN_USED`). The front-end's hot path (31 502
        of the bundled drive's 33 603 samples): the quantity's limit looked up once (it says whether the quantity is
        used, too), the settings read once (:meth:`reset`), the missed epochs asked for only when one is due
        (:meth:`EpochClock.missed_due`): 1.18 -> 0.85 us a CAN sample (the learner off; median of 3 alternating
        pairs, each the minimum of 9 passes over the drive)."""
        q, value, stamp = sample.quantity, sample.value, sample.t
        limit = self._limits.get(q)
        if limit is None:
            return []
        if not (isinstance(stamp, _NUMBER) and isinstance(value, _NUMBER) and math.isfinite(stamp)):
            self.tally.count("bad_samples", "CAN %s sample with a non-finite time or value", q)
            return []
        t = stamp - self._delay_s
        measured = stamp - self._age_s[q]
        store = self.can.samples[q]
        newest = store.newest
        if measured < newest:
            self.tally.count("dropped_backwards", "CAN %s sample %.3f s back in time dropped", q, newest - measured)
            return []
        if not (math.isfinite(value) and abs(value) <= limit):
            self.tally.count("bad_samples", "CAN %s = %r beyond the vehicle limits dropped", q, value)
            return []
        self._check_gap(t)
        value = float(value)
        if q == "speed":
            value = centred_speed(value, self._speed_reads_low) * self.check.factor["speed"]
            self.learner.add_can_speed(measured, value)
        else:
            self.check.add_yaw(t, value)
            value = (value - self.check.offset["yaw_rate"]) * self.check.factor["yaw_rate"]
        store.add(measured, value)
        if not self.started:
            return []
        between = self._between_s
        output = q == OUTPUT_QUANTITY or (between is not None and t - self._t_output >= between)
        if output:
            self._t_output = t
        tick = _new_tuple(CanTick, (t, stamp, q, value, output))
        clock = self.clock
        t_fix_clock = t - clock.delay_s
        if not clock.missed_due(t_fix_clock):
            return [tick]
        events: list[Epoch | CanTick] = self._missed(t_fix_clock)
        events.append(tick)
        return events

    # ---- GNSS -------------------------------------------------------------------------------------------------

    def _fix(self, fix: LocalFix) -> list[Epoch | CanTick]:
        # the receiver's timing (period, delay, missed epochs) is kept on its own clock, the fixes' stamps; the
        # epochs handed out are at their times on the CAN clock (the stamp plus the GNSS time offset)
        stamp = fix.t
        bad = bad_epoch_time(stamp, self.clock.last_epoch)
        if bad is not None:
            filled = self._after_missed(stamp, self._moved(fix)) if bad[0] == "dropped_backwards" else None
            if filled is None:
                self.tally.count(*bad[:2], *bad[2])
            return filled or []
        fix = self._on_can_clock(fix)
        t = fix.t
        if t < self._t_epoch + SAME_EPOCH * self.period_s:  # the epoch already handed out (declared missed before
            # its fix came after CAN data newer than any fix's so far), or behind it by the time offset's slew since
            filled = self._after_missed(stamp, fix)
            if filled is None:
                self.tally.count("dropped_backwards", "GNSS epoch %.3f s back in time dropped", self._t_epoch - t)
            return filled or []
        newest_can = self.can.newest
        if self.started and t < newest_can - MAX_FIX_LAG_S:
            self.tally.count("late_fixes", "GNSS epoch %.2f s behind the CAN data dropped", newest_can - t)
            return []
        sigmas = fix.sigmas(self.settings.gnss)
        usable = fix.usable(sigmas)
        if fix.valid and not usable:
            self.tally.count("bad_fixes", "valid fix without a usable position or sigma taken as no fix")
        if fix.valid:
            self._check(fix)
            if usable:
                self._check_heading(fix)
        self.clock.observe(stamp, newest_can)
        self._check_gap(t)
        if not self.started:
            if not usable:
                return []
            self.clock.last_epoch = stamp
            self.started = True
            self.tally.counts["epochs"] += 1
            self.can.trim(t - max(CAN_KEEP_S, 3.0 * self.period_s))
            self._t_epoch = t
            fresh, self._fresh = self._fresh, False
            return [Epoch(t, self.measure(fix, sigmas), start=True, fresh=fresh)]
        events: list[Epoch | CanTick] = self._missed(stamp)
        self.clock.last_epoch = stamp
        self.tally.counts["epochs"] += 1
        self.can.trim(t - max(CAN_KEEP_S, 3.0 * self.period_s))
        events.append(Epoch(t, self.measure(fix, sigmas) if usable else None))
        self._t_epoch = t
        return events

    def _after_missed(self, stamp: float, fix: LocalFix) -> list[Epoch | CanTick] | None:
        """The events of a fix stamped ``stamp`` (``fix`` at its time on the CAN clock) whose epoch was already
        handed out, or None when it is that epoch's fix again (a duplicate, or back in time). A fix that came after
        its epoch was declared missed (its delay is learned: :meth:`EpochClock.observe_late`) fills that epoch:
        ``Epoch(fills=True)`` at its time, which the estimator puts in as a late fix, or drops (and counts
        ``fixes_after_missed``) where it cannot. It is dropped here, counted ``fixes_after_missed``, when no missed
        epoch is within ``SAME_EPOCH`` of it (each is filled once), when it is more than ``MAX_FIX_LAG_S`` behind
        the CAN data, without a usable position, or for an estimator that cannot put a fix in the past
        (``fills_missed`` False)."""
        newest_can, t = self.can.newest, fix.t
        if not (self.started and self.clock.observe_late(stamp, newest_can, MAX_FIX_LAG_S)):
            return None
        sigmas = fix.sigmas(self.settings.gnss)
        if self.fills_missed and newest_can - t <= MAX_FIX_LAG_S and fix.usable(sigmas) and self._take_missed(t):
            return [Epoch(t, self.measure(fix, sigmas), fills=True)]
        self.tally.count(
            "fixes_after_missed",
            "GNSS fix %.3f s behind the CAN data came after its epoch was declared missed: dropped, its delay learned",
            newest_can - t,
        )
        return []

    def _take_missed(self, t: float) -> bool:
        """Whether an epoch declared missed lies within ``SAME_EPOCH`` periods of ``t`` (s, CAN clock); it is then
        forgotten (filled), with the ones before it (their fixes would come before this one)."""
        tolerance = SAME_EPOCH * self.period_s
        while self._missed_epochs and self._missed_epochs[0] < t - tolerance:
            self._missed_epochs.popleft()
        if self._missed_epochs and abs(self._missed_epochs[0] - t) <= tolerance:
            self._missed_epochs.popleft()
            return True
        return False

    def _moved(self, fix: LocalFix) -> LocalFix:
        """The fix at its stamped time plus the GNSS time offset applied now."""
        return replace(fix, t=fix.t + self.time_offset_s) if self.time_offset_s else fix

    def _check(self, fix: LocalFix) -> None:
        """A valid fix (on the CAN clock) to the sensor check, with the learner's newest speed fit."""
        speed = fix.speed_mps
        if speed is None or not math.isfinite(speed):
            speed = self.can["speed"].at(fix.t, self.settings.can.max_gap_s)
        before = (self.check.factor.copy(), self.check.offset.copy())
        self.check.add_fix(fix, math.nan if speed is None else speed, self.can)
        self.check.check_speed(self.learner.newest, fix.t)
        if (self.check.factor, self.check.offset) != before:
            self._remap(*before)

    def _check_heading(self, fix: LocalFix) -> None:
        """A usable fix's heading (where it has one and headings are used) to :attr:`headings`, with the CAN yaw
        rate's turn since the fix before."""
        heading = fix.heading_rad
        if heading is None or not math.isfinite(heading) or not self.settings.gnss.use_heading:
            return
        yaw = self.can["yaw_rate"]
        before = self.headings.before
        mean = yaw.mean(before.t, fix.t) if before is not None else None
        turn = None if mean is None else mean[0] * (fix.t - before.t)  # type: ignore[union-attr]
        self.headings.add(HeadingFix(fix.t, heading, yaw.at(fix.t, self.settings.can.max_gap_s)), turn)

    def _remap(self, factor: dict[str, float], offset: dict[str, float]) -> None:
        """A CAN quantity's mapping was found wrong (:attr:`check`: the yaw rate's sign flipped, its gain or bias
        outside the bounds, the speed's scale outside them), its factor and offset changed from ``factor`` and
        ``offset``: the samples kept are mapped as the new ones will be, and the estimator starts over at this fix
        (its state and window hold the wrong turns or distances)."""
        for q, now in self.check.factor.items():
            shift = now * (offset[q] - self.check.offset[q])
            if now != factor[q] or shift:
                ratio = now / factor[q]
                self.can[q].remap(ratio, shift)
                if q == "speed":
                    self.learner.scale_can_speeds(ratio)
        self._fresh = True
        if self.started:
            self.started = False
            self.tally.counts["restarts"] += 1

    def _on_can_clock(self, fix: LocalFix) -> LocalFix:
        """The fix at its time on the CAN clock: its stamped time plus the GNSS time offset (module docstring)."""
        if isinstance(fix.t, _NUMBER) and math.isfinite(fix.t):
            self.learner.add_fix(fix.t, fix.speed_mps if fix.valid else None)
        if self.aligner is not None and isinstance(fix.t, _NUMBER) and math.isfinite(fix.t):
            if fix.valid and fix.speed_mps is None:
                self.tally.count(
                    "fixes_without_speed",
                    "valid GNSS fix without a speed over ground: the time offset is not learned from it (%.3f s "
                    "applied; sensors.gnss.time_offset_s sets it, sumhe calibrate measures it)",
                    self.time_offset_s,
                )
            step = OFFSET_SLEW * self.period_s
            self.time_offset_s += min(max(self.aligner.offset_s - self.time_offset_s, -step), step)
        return self._moved(fix)

    def measure(self, fix: LocalFix, sigmas: tuple[float, float]) -> FixMeasurement:
        """The measurements of a usable fix whose position ``sigmas`` are :meth:`LocalFix.sigmas`
        (:mod:`sumhe.frontend.measurements`); the CAN speed at its time signs its speed over ground and, when it
        has none of its own, decides whether its course counts."""
        s = self.settings
        can_speed = self.can["speed"].at(fix.t, s.can.max_gap_s)
        speed = fix.speed_mps if fix.speed_mps is not None and math.isfinite(fix.speed_mps) else can_speed
        angle = azimuth_measurement(fix.course_rad, fix.heading_rad, speed, s.gnss, fix.heading_sigma_rad)
        if angle is not None and angle[2]:
            angle = angle[0], self._heading_sigma(fix.t, angle[1]), True
        sigma_e, sigma_n = sigmas
        return FixMeasurement(
            t=fix.t,
            east_m=fix.east_m,
            north_m=fix.north_m,
            sigma_east_m=sigma_e,
            sigma_north_m=sigma_n,
            azimuth_rad=angle[0] if angle is not None else None,
            azimuth_sigma_rad=angle[1] if angle is not None else math.inf,
            heading=angle is not None and angle[2],
            speed_mps=gps_speed(fix.speed_mps, can_speed, s.gnss) if self.uses_gps_speed else None,
            speed_sigma_mps=gps_speed_sigma(s.gnss),
            fix=fix,
        )

    def _heading_sigma(self, t: float, sigma_rad: float) -> float:
        """A heading's sigma (rad): ``sigma_rad`` (configured or rated), or what :attr:`headings` finds where that
        is larger (counted ``headings_off``)."""
        checked = self.headings.sigma_rad(t)
        if not checked > sigma_rad:
            return sigma_rad
        self.tally.count(
            "headings_off",
            "the receiver's heading turns otherwise than the CAN yaw rate, by %.1f deg rms (beyond the errors the "
            "config allows them): its headings weigh at that (not %.2f deg) until they agree again",
            math.degrees(checked),
            math.degrees(sigma_rad),
        )
        return checked

    # ---- timing -----------------------------------------------------------------------------------------------

    def _missed(self, t_fix_clock: float) -> list[Epoch | CanTick]:
        """The epochs missed up to ``t_fix_clock`` (s, on the fixes' own clock), at their times on the CAN clock."""
        missed = self.clock.missed(t_fix_clock)
        if not missed:  # nearly every call (one per sample)
            return []
        times = [t + self.time_offset_s for t in missed]
        times = [t for t in times if t >= self._t_epoch + SAME_EPOCH * self.period_s]
        if times:
            self.tally.counts["epochs"] += len(times)
            self.tally.counts["missed_epochs"] += len(times)
            self._t_epoch = times[-1]
            self._missed_epochs.extend(times)
        return [Epoch(t, None, missed=True) for t in times]

    def _check_gap(self, t: float) -> None:
        """A restart after :data:`MAX_DATA_GAP_S` without data before ``t`` (s, finite: the newest time kept without
        a ``max()`` call)."""
        if self.started and t - self._t_last > MAX_DATA_GAP_S:
            self.tally.count("restarts", "no data for %.1f s: restarting at the next fix", t - self._t_last)
            self.started = False
        if t > self._t_last:
            self._t_last = t
