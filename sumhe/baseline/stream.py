"""The recursive baselines' side of the stream: :class:`RecursiveEstimator` on the front-end's epochs and ticks.

The stream (input checks, CAN buffer and delay, GNSS timing and missed epochs, each fix's measurements and sigmas)
is the front-end's (:mod:`sumhe.frontend`, through :class:`~sumhe.estimator.base.StreamEstimator`); this module
implements once what every recursive filter does with it, and a filter supplies only the maths, as hooks on its
own state:

* ``_start(x0, P0)``: a state and covariance at the first usable fix (layout of :mod:`.kinematics`);
* ``_predict(dt, inputs)``: move the state ``dt`` seconds on (``inputs``: the newest CAN data);
* ``_can_update(inputs)``: use the CAN speed / yaw rate at a CAN speed sample (measurements, or just inputs);
* ``_innovation(kind, z, R, lag)``: a GNSS measurement's innovation and its covariance, with a ``commit``
  that applies the update; the gate here decides whether to commit;
* ``_inflate(kind, nu, R)``: widen the state so that a re-acquired fix can pull it (after a rejected run);
* ``_init_heading(phi, sigma)``: the first azimuth measurement sets the azimuth outright;
* ``_mean()``: the state estimate now (layout of :mod:`.kinematics`, speed and yaw rate filled in);
* ``_covariance()``, optional: its covariance (a Gaussian filter's own, the particles' weighted spread, the
  mixture's, dead reckoning's growth model); every estimate's error figures (:mod:`sumhe.estimator.uncertainty`)
  come from it, carried to the estimate's time by the model's Jacobian and process noise; a filter without it
  reports none;
* ``snapshot_attrs`` (the attributes that hold its state), or ``_snapshot()``/``_restore()`` where copying them is
  not enough (the RTS's and ``mskf-em``'s step records): the late fixes' history below.

Timing: the filter's state lives at ``t_state``, the newest CAN speed sample's measurement time (or fix, if
newer); a CAN-rate estimate is reported at the sample's timestamp. Each epoch's estimate is reported at the
epoch's own time, so it may be up to the receiver's latency older than the CAN-rate estimate before it.

A fix older than the state (the receiver's latency: CAN samples of the meantime came first, and nothing holds them
back) is put in at its own time, as robot_localization does: the filter keeps a :class:`History` of its state after
each CAN tick and each fix over the last ``estimator.late_fix_history_s`` seconds (1.5 s; the front-end drops fixes
more than ``MAX_FIX_LAG_S`` = 1 s behind the CAN data), goes back to the newest state at or before the fix, moves
to the fix's time, applies it (through the same gate) and re-applies the CAN ticks since, storing their states
anew; several late fixes in a burst each do so in turn (the front-end hands out epochs in time order, so only CAN
ticks are ever re-applied). A fix that came after its epoch was declared missed (``Epoch.fills``: the receiver's
latency grew) is put in the same way, or dropped (counted ``fixes_after_missed``) when it is older than the
history; the epoch is counted ``missed_epochs_filled`` (it was counted an outage when it was missed). Estimates
already sent are not sent again: the epoch's estimate is the state at the
fix, and the CAN-rate estimates after it carry the correction. The result is the filter fed in time order (a
seeded particle filter draws the same numbers: its generator's state is part of the history). A fix older than
the history is compared with the state through the model run back by the lag, as before the history (counted
``late_fixes_run_back``; the re-runs ``late_fixes_rerun``). Costs on the 60 s contract drive (50 Hz CAN speed,
fixes 0.25 s late, load average ~8 on the 2 shared cores): a CAN sample's push 0.102 against 0.096 ms without the
history (EKF), a late fix's push with its re-run of ~12 CAN ticks p50 1.2 ms (EKF), 7.4 ms (IMM); in memory
about 1 kB per stored state for the EKF, 37 kB for the 500-particle filter (75 states at 50 Hz). ``gtsam-fls`` keeps
no history: its graph takes a late fix at the fix's own node.

Measurement noise: a fix's position sigmas (the front-end's) times ``gps_scale``; a course's sigma with the
filter's model error ``course_rad`` added (``hypot``); a heading's as it is; the speed over ground's as it is
(``_speed_sigma``; the Gaussian filters add what the fix's uncertain time makes of it while the car accelerates). A
numerical failure (non-finite state) restarts the filter from the next usable fix.
"""

from __future__ import annotations

import logging
import math
from abc import abstractmethod
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from sumhe.baseline.kinematics import (
    AZIMUTH,
    GPS_SPEED,
    OMEGA,
    PHI,
    POSITION,
    E,
    FloatArray,
    Layout,
    N,
    V,
    chi2_threshold,
    process_noise,
    step,
    step_jacobian,
)
from sumhe.estimator.base import StateEstimate, StreamEstimator, on_a_line
from sumhe.estimator.uncertainty import Spread
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.measurements import chord_azimuth
from sumhe.frontend.stream import OUTPUT_QUANTITY, CanTick, Epoch, FixMeasurement
from sumhe.messages import CanSample, GpsStatus
from sumhe.settings import EstimationSettings, NoiseSettings

HEADING_UNKNOWN_RAD = math.pi / math.sqrt(3.0)
"""Prior sigma of the azimuth when the first fix has none (the sigma of a uniform angle)."""
REACQUIRE_SPREAD_SIGMAS = 4.0
"""Rejected innovations agree when each is within this many measurement sigmas of their straight line in time."""
REACQUIRE_MIN_FIXES = 3

HISTORY_MAX_ENTRIES = 1000
"""At most this many states are kept in the history, whatever its span (1.5 s of CAN speed at over 600 Hz)."""

Decision = Literal["ok", "rejected", "reacquire"]
STATUS_COUNTERS: dict[str, str] = {"ok": "gps_ok", "rejected": "gps_rejected", "outage": "outage_epochs"}

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Inputs:
    """The newest CAN data: speed (m/s), yaw rate (rad/s, mean of the samples since the previous speed
    sample), None when missing or older than ``can_max_gap_s``; ``standstill`` when the CAN speed reads 0."""

    speed: float | None
    yaw_rate: float | None
    standstill: bool


@dataclass(frozen=True, slots=True)
class Pending:
    """A GNSS measurement's innovation ``nu`` and its covariance ``S``; ``commit()`` applies the update."""

    nu: FloatArray
    S: FloatArray
    commit: Callable[[], None]


class Gate:
    """Chi-square innovation gate with re-acquisition.

    A fix is accepted when its normalised innovation squared is within ``threshold``. Rejected fixes are
    remembered; once they have agreed with each other for ``reacquire_s`` seconds, it is the filter that is wrong
    (it drifted through an outage with too small a covariance) and the gate says ``"reacquire"``. They agree when
    each innovation lies within ``REACQUIRE_SPREAD_SIGMAS`` measurement sigmas of their straight line in time: a
    filter that drifted in speed or heading as well as position sees innovations that grow steadily from fix to
    fix, which agree as much as constant ones (with the mean instead, such a run never agreed, and the IMM stayed
    1.6 km off on the shared real drive). Without this rule a long outage can lock GPS out for good (a known
    robot_localization failure).
    """

    def __init__(self, threshold: float, reacquire_s: float) -> None:
        self.threshold = threshold
        self.reacquire_s = reacquire_s
        self._run: list[tuple[float, FloatArray]] = []

    def clear(self) -> None:
        self._run.clear()

    def check(self, t: float, nu: FloatArray, d2: float, sigma: float) -> Decision:
        """Decide on one innovation ``nu`` (normalised square ``d2``) at time ``t``; ``sigma``: measurement sigma."""
        if d2 <= self.threshold:
            self._run.clear()
            return "ok"
        self._run.append((t, nu))
        if not on_a_line(self._run, REACQUIRE_SPREAD_SIGMAS * sigma):
            self._run = [(t, nu)]
        if len(self._run) >= REACQUIRE_MIN_FIXES and t - self._run[0][0] >= self.reacquire_s:
            self._run.clear()
            return "reacquire"
        return "rejected"


@dataclass(frozen=True, slots=True)
class Entry:
    """One state of the history: the stream's times (``t`` the state's, ``t_speed`` the newest CAN speed sample's),
    the CAN tick whose update made it (None: a fix's) and the filter's own snapshot (:meth:`~RecursiveEstimator.
    _snapshot`)."""

    t: float
    t_speed: float
    tick: CanTick | None
    state: object


class History:
    """The filter's states of the last ``span_s`` seconds, one after each CAN tick and each fix, oldest first: a
    ring buffer by time (the oldest is dropped once the next one is ``span_s`` older than the newest, so that
    the whole span stays covered), at most ``HISTORY_MAX_ENTRIES`` long."""

    def __init__(self, span_s: float) -> None:
        self.span_s = span_s
        self._entries: deque[Entry] = deque(maxlen=HISTORY_MAX_ENTRIES)

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def oldest_t(self) -> float:
        """The time of the oldest state kept (inf: none)."""
        return self._entries[0].t if self._entries else math.inf

    def clear(self) -> None:
        self._entries.clear()

    def add(self, entry: Entry) -> None:
        entries = self._entries
        entries.append(entry)
        while len(entries) > 1 and entries[1].t <= entry.t - self.span_s:
            entries.popleft()

    def rewind(self, t: float) -> tuple[Entry, list[CanTick]] | None:
        """The newest state at or before ``t`` and the CAN ticks applied after it, which are dropped from the
        history (the caller re-applies them); None, and the history kept, when ``t`` is older than every state."""
        entries = self._entries
        if not entries or entries[0].t > t:
            return None
        later: list[CanTick] = []
        while entries[-1].t > t:
            tick = entries.pop().tick
            # the front-end's epochs come in time order: every fix applied so far is older than this one
            assert tick is not None, "a fix newer than a later one"
            later.append(tick)
        later.reverse()
        return entries[-1], later


def _saved(value: Any) -> Any:
    """A copy of one attribute of a filter's state that later changes to the filter do not touch (arrays copied,
    lists and deques copied with their items' arrays, a random generator's state), the value itself if immutable."""
    if isinstance(value, np.ndarray):
        return value.copy()
    if isinstance(value, list):
        return [_saved(v) for v in value]
    if isinstance(value, deque):
        return deque(value, value.maxlen)  # of items that are replaced, never changed
    if isinstance(value, np.random.Generator):
        return value.bit_generator.state
    return value


def _restored(current: Any, saved: Any) -> Any:
    """The attribute set back to ``saved`` (a random generator keeps its object and takes the saved state)."""
    if isinstance(current, np.random.Generator):
        current.bit_generator.state = saved
        return current
    return _saved(saved)


class _NumericFailure(Exception):
    """The state went non-finite; the filter restarts."""


class RecursiveEstimator(StreamEstimator):
    """Base of the recursive baselines (the module docstring). ``gated = False`` turns the innovation gate off (dead
    reckoning takes every fix as it is). ``azimuth_from_motion``: where the fixes carry no course or heading (a
    receiver that sends neither), the chord from the previous epoch's fix measures the azimuth
    (:meth:`_motion_angle`): ``"start"``, the first such chord sets it (a filter whose azimuth only a measurement
    of it sets: ``gtsam-fls`` opened no graph and stayed at the newest fix); ``"always"``, every one is an
    azimuth measurement (``mskf-em``, whose position stage does not turn its heading stage, ran on the CAN yaw
    rate from an azimuth of 0: both 96-557 m off the removed fixes of the shared real drive without its
    headings); ``"never"``: the filter finds the azimuth in the positions (the Kalman filters and the particle
    filters; the chord's start left the particle filter's heading 60-140 deg off after the first 60 s outage of
    the shared drive without its headings, and its 60 s outages 745 m off on average). The chords taken are
    counted (``motion_azimuths`` in :meth:`stats`). ``snapshot_attrs``: the
    attributes that hold the filter's state (the default :meth:`_snapshot` copies them); None: the filter keeps no
    history (it places a late fix itself)."""

    gated: ClassVar[bool] = True
    azimuth_from_motion: ClassVar[Literal["never", "start", "always"]] = "never"
    snapshot_attrs: ClassVar[tuple[str, ...] | None] = None

    def __init__(self, settings: EstimationSettings, noise: NoiseSettings) -> None:
        self.noise = noise
        self.layout = Layout.from_settings(settings, noise)
        prob = noise.gate_prob if self.gated else 1.0
        self._pos_gate = Gate(chi2_threshold(prob, 2), noise.reacquire_s)
        self._az_gate = Gate(chi2_threshold(prob, 1), noise.reacquire_s)
        self._sog_gate = Gate(chi2_threshold(prob, 1), noise.reacquire_s)
        keeps = self.snapshot_attrs is not None and settings.estimator.late_fix_history_s > 0
        self._history = History(settings.estimator.late_fix_history_s) if keeps else None
        super().__init__(settings)
        self.frontend.fills_missed = keeps
        self.reset_state()

    @property
    def history(self) -> History | None:
        """The stored states a late fix re-runs from (None: the filter keeps none)."""
        return self._history

    # ---- the StreamEstimator's methods ----------------------------------------------------------------------

    def reset_state(self) -> None:
        """Forget the state; the next usable fix starts over."""
        self._started = False
        self._heading_known = False
        self._previous_fix: FixMeasurement | None = None
        self._t_state = math.nan
        self._t_speed = -math.inf
        self._status: GpsStatus = "outage"
        self._pos_gate.clear()
        self._az_gate.clear()
        self._sog_gate.clear()
        if self._history is not None:
            self._history.clear()
        self._reset_filter()

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        """Feed one sample; a numerical failure restarts the filter (and the stream) from the next usable fix."""
        try:
            return super().push(sample)
        except (_NumericFailure, np.linalg.LinAlgError) as e:
            self.tally.count("numeric_failures", "numerical failure (%s); restarting from the next fix", e)
            self.reset()
            return []

    def on_epoch(self, epoch: Epoch) -> StateEstimate | None:
        t = epoch.t
        later: list[CanTick] = []
        if epoch.fills and (self._history is None or self._history.oldest_t > t):
            self.tally.count(
                "fixes_after_missed",
                "GNSS fix of a missed epoch %.3f s older than the history (estimator.late_fix_history_s): dropped",
                self._t_state - t,
            )
            return None
        if epoch.start:
            assert epoch.fix is not None  # the front-end starts at a usable fix
            self._begin(epoch.fix)
            status: GpsStatus = "ok"
        elif epoch.fix is not None:
            if t < self._t_state and self.snapshot_attrs is not None:
                later = self._rewind(t)
            self._advance(t, self._inputs(t))
            status = self._fix_updates(epoch.fix, self._t_state - t)
        else:
            status = "outage"
            self._previous_fix = None
        # an epoch is counted once: a missed one as an outage, and its fix that came after it as filling it
        self.tally.counts["missed_epochs_filled" if epoch.fills else STATUS_COUNTERS[status]] += 1
        self._status = status
        if epoch.fix is not None:
            self._keep(None)
        estimate = self._report(t, status)
        for tick in later:
            self._apply_can(tick)
        return estimate

    def on_can(self, tick: CanTick) -> StateEstimate | None:
        """A CAN speed tick moves the filter to it and updates it with the CAN data there; a yaw-rate tick the
        front-end marks for an estimate (between sparse speed samples, ``estimator.can_output_hz``) is answered by
        :meth:`_between`."""
        if not tick.output or not self._started:
            return None
        if tick.quantity != OUTPUT_QUANTITY:
            return self._between(tick)
        self._apply_can(tick)
        self.tally.counts["can_updates"] += 1
        return self._report(tick.stamp, self._status, epoch=False)

    def _between(self, tick: CanTick) -> StateEstimate:
        """The estimate at a yaw-rate tick between speed samples: the filter moved to it with the CAN data so far
        (the yaw-rate samples since the last speed sample), reported, and set back (the next speed tick moves it on
        as before); a filter that keeps no snapshots (``snapshot_attrs`` None) reports its state moved there by the
        model alone (its yaw rate that of the last speed tick)."""
        if self.snapshot_attrs is None:
            return self._report(tick.stamp, self._status, epoch=False)
        saved, t_state = self._snapshot(), self._t_state
        try:
            self._advance(tick.t, self._inputs(tick.t))
            return self._report(tick.stamp, self._status, epoch=False)
        finally:
            self._restore(saved)
            self._t_state = t_state

    # ---- hooks ------------------------------------------------------------------------------------------------

    @abstractmethod
    def _reset_filter(self) -> None:
        """Drop the filter's state."""

    @abstractmethod
    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        """Initialise at the first valid fix."""

    @abstractmethod
    def _predict(self, dt: float, inputs: Inputs) -> None:
        """Move the state ``dt`` s on."""

    @abstractmethod
    def _can_update(self, inputs: Inputs) -> None:
        """Use the CAN data at a CAN speed sample."""

    @abstractmethod
    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        """The innovation of a GNSS measurement of ``kind`` (taken ``lag`` s before the state's time)."""

    @abstractmethod
    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        """Widen the state along the rows of ``kind`` so that a re-acquired measurement can pull it."""

    @abstractmethod
    def _init_heading(self, phi: float, sigma: float) -> None:
        """Set the azimuth (rad) with the given sigma."""

    @abstractmethod
    def _mean(self) -> FloatArray:
        """The state estimate at ``t_state``."""

    def _covariance(self) -> FloatArray | None:
        """The covariance of the state estimate at ``t_state`` (n x n); None (an estimator that has none): its
        estimates carry no error estimate."""
        return None

    def _snapshot(self) -> object:
        """A copy of the filter's state (the attributes ``snapshot_attrs`` names) that :meth:`_restore` sets back."""
        assert self.snapshot_attrs is not None
        return tuple(_saved(getattr(self, name)) for name in self.snapshot_attrs)

    def _restore(self, state: object) -> None:
        """Set the filter's state back to a :meth:`_snapshot` (which stays valid: it can be restored again)."""
        assert self.snapshot_attrs is not None and isinstance(state, tuple)
        for name, saved in zip(self.snapshot_attrs, state, strict=True):
            setattr(self, name, _restored(getattr(self, name), saved))

    def _on_report(self, estimate: StateEstimate, epoch: bool) -> None:
        """Called with every estimate returned, ``epoch`` False for the CAN-rate ones (the RTS records them)."""

    def _window(self) -> int:
        return 0

    # ---- the filter on the stream -----------------------------------------------------------------------------

    def _inputs(self, t: float) -> Inputs:
        """The CAN data at ``t``: the speed sample at or before it, the mean yaw rate since the previous speed
        sample (else the sample at or before ``t``), within ``sensors.can.max_gap_s``."""
        can, gap = self.frontend.can, self.settings.can.max_gap_s
        speed = can["speed"].at(t, gap)
        mean = can["yaw_rate"].mean(max(self._t_speed, t - gap), t)
        yaw = mean[0] if mean is not None else can["yaw_rate"].at(t, gap)
        still = speed is not None and abs(speed) <= 0.5 * self.settings.can.speed_quantum_mps
        return Inputs(speed, yaw, still)

    def _advance(self, t: float, inputs: Inputs) -> None:
        if t > self._t_state:
            self._predict(t - self._t_state, inputs)
            self._t_state = t

    def _apply_can(self, tick: CanTick) -> None:
        """Move the state to a CAN speed tick and update it with the CAN data there; keep the state."""
        inputs = self._inputs(tick.t)
        self._advance(tick.t, inputs)
        self._can_update(inputs)
        self._t_speed = tick.t
        self._keep(tick)

    def _keep(self, tick: CanTick | None) -> None:
        """Store the state in the history (after ``tick``, or after a fix with None)."""
        if self._history is not None:
            self._history.add(Entry(self._t_state, self._t_speed, tick, self._snapshot()))

    def _rewind(self, t: float) -> list[CanTick]:
        """For a fix at ``t``, older than the state: set the state back to the newest stored one at or before
        ``t`` and return the CAN ticks to re-apply after the fix. Beyond the history (or without one): the state
        stays, the fix is compared with it through the model run back by the lag (counted), and the history
        starts again after the fix."""
        found = self._history.rewind(t) if self._history is not None else None
        if found is None:
            if self._history is not None:
                self._history.clear()
            self.tally.count(
                "late_fixes_run_back",
                "GNSS fix %.3f s older than the state, beyond the history (estimator.late_fix_history_s): "
                "compared through the model run back",
                self._t_state - t,
                level=logging.INFO,
            )
            return []
        entry, later = found
        log.debug("%s: fix %.3f s old: re-running %d CAN ticks", self.name, self._t_state - t, len(later))
        self._restore(entry.state)
        self._t_state, self._t_speed = entry.t, entry.t_speed
        self.tally.counts["late_fixes_rerun"] += 1
        return later

    def _begin(self, fix: FixMeasurement) -> None:
        t = fix.t
        inputs = self._inputs(t)
        angle = self._fix_angle(fix)
        self._heading_known = angle is not None
        phi, sigma_phi = angle if angle is not None else (0.0, HEADING_UNKNOWN_RAD)
        x0 = np.zeros(self.layout.n)
        x0[E], x0[N], x0[PHI] = fix.east_m, fix.north_m, phi
        x0[V] = inputs.speed if inputs.speed is not None else 0.0
        x0[OMEGA] = inputs.yaw_rate if inputs.yaw_rate is not None and not inputs.standstill else 0.0
        scale = self.noise.gps_scale
        sig = [scale * fix.sigma_east_m, scale * fix.sigma_north_m, sigma_phi]
        sig += [self.noise.speed0_mps, self.noise.yaw_rate0_rps]
        if self.layout.b is not None:
            sig.append(0.5 * self.settings.can.yaw_rate_bias_max_rps)
        if self.layout.k is not None:
            x0[self.layout.k] = 1.0
            sig.append(0.5 * self.settings.can.speed_scale_max)
        if self.layout.g is not None:
            x0[self.layout.g] = 1.0
            sig.append(self.noise.gain0)
        self._reset_filter()
        self._pos_gate.clear()
        self._az_gate.clear()
        self._sog_gate.clear()
        if self._history is not None:
            self._history.clear()
        self._t_state = t
        self._previous_fix = fix
        self._start(x0, np.diag(np.square(sig)))
        self._started = True

    def _fix_angle(self, fix: FixMeasurement) -> tuple[float, float] | None:
        """The azimuth a fix measures (rad) and its sigma: a heading's, or a course's with the filter's model
        error ``course_rad``."""
        if fix.azimuth_rad is None:
            return None
        if fix.heading:
            return fix.azimuth_rad, fix.azimuth_sigma_rad
        return fix.azimuth_rad, math.hypot(self.noise.course_rad, fix.azimuth_sigma_rad)

    def _fix_updates(self, fix: FixMeasurement, lag: float) -> GpsStatus:
        scale = self.noise.gps_scale
        sigma_e, sigma_n = scale * fix.sigma_east_m, scale * fix.sigma_north_m
        z = np.array([fix.east_m, fix.north_m])
        R = np.diag([sigma_e**2, sigma_n**2])
        t = fix.t
        status = self._gated_update(POSITION, z, R, lag, self._pos_gate, t, max(sigma_e, sigma_n))
        if status != "rejected":
            self._angle_update(fix, lag)
        self._previous_fix = fix  # the receiver's fix, whatever the gate said of the filter
        if status == "rejected":
            return status
        if fix.speed_mps is not None:
            sigma_v = self._speed_sigma(fix)
            R = np.array([[sigma_v**2]])
            z = np.array([fix.speed_mps])
            if self._gated_update(GPS_SPEED, z, R, lag, self._sog_gate, t, sigma_v) == "rejected":
                self.tally.count("speed_rejected", "GNSS speed over ground rejected by the gate")
        return status

    def _speed_sigma(self, fix: FixMeasurement) -> float:
        """The sigma (m/s) the filter gives a fix's speed over ground: the front-end's."""
        return fix.speed_sigma_mps

    def _motion_angle(self, fix: FixMeasurement) -> tuple[float, float] | None:
        """The azimuth (rad) at ``fix`` and its sigma (a course's, with the filter's ``course_rad`` and the fixes'
        sigmas x ``gps_scale``) that the chord from the previous epoch's fix measures, reversed when the car
        reverses; None after an epoch without a fix (across a gap the chord is a long way's mean azimuth, its sigma
        the smaller the longer the way: with such chords ``mskf-em`` was 9.87 m off in the 60 s outages of the
        shared real drive without its headings, 6.40 m without), where the receiver sent a course or heading (below
        the course's minimum speed a chord is as much noise), below that speed, or when it says no more than
        :data:`HEADING_UNKNOWN_RAD`."""
        before = self._previous_fix
        if before is None or fix.fix.course_rad is not None or fix.fix.heading_rad is not None:
            return None
        speed = fix.speed_mps if fix.speed_mps is not None else self._inputs(fix.t).speed
        if speed is None or abs(speed) < self.settings.gnss.course_min_speed_mps:
            return None
        de, dn = fix.east_m - before.east_m, fix.north_m - before.north_m
        yaw = self.frontend.can["yaw_rate"].mean(before.t, fix.t)
        across = [  # the fixes' variances across the chord
            (s_e * dn) ** 2 + (s_n * de) ** 2
            for s_e, s_n in ((before.sigma_east_m, before.sigma_north_m), (fix.sigma_east_m, fix.sigma_north_m))
        ]
        distance2 = de * de + dn * dn
        sigma = self.noise.gps_scale * math.sqrt(sum(across) / distance2) if distance2 > 0.0 else 0.0
        chord = chord_azimuth(de, dn, sigma, fix.t - before.t, yaw[0] if yaw is not None else 0.0)
        if chord is None:
            return None
        sigma_phi = math.hypot(self.noise.course_rad, chord[1])
        if not sigma_phi < HEADING_UNKNOWN_RAD:
            return None
        return (chord[0] + (math.pi if speed < 0.0 else 0.0)) % (2.0 * math.pi), sigma_phi

    def _angle_update(self, fix: FixMeasurement, lag: float) -> None:
        angle = self._fix_angle(fix)
        use = self.azimuth_from_motion
        if angle is None and (use == "always" or (use == "start" and not self._heading_known)):
            angle = self._motion_angle(fix)
            if angle is not None:
                self.tally.counts["motion_azimuths"] += 1
        if angle is None:
            return
        phi, sigma_phi = angle
        if not self._heading_known:
            self._init_heading(phi, sigma_phi)
            self._heading_known = True
            return
        R = np.array([[sigma_phi**2]])
        if self._gated_update(AZIMUTH, np.array([phi]), R, lag, self._az_gate, fix.t, sigma_phi) == "rejected":
            self.tally.count("azimuth_rejected", "GNSS course/heading rejected by the gate")

    def _gated_update(
        self, kind: str, z: FloatArray, R: FloatArray, lag: float, gate: Gate, t: float, sigma: float
    ) -> GpsStatus:
        pending = self._innovation(kind, z, R, lag)
        d2 = float(pending.nu @ np.linalg.solve(pending.S, pending.nu))
        decision = gate.check(t, pending.nu, d2, sigma)
        if decision == "rejected":
            return "rejected"
        if decision == "reacquire":
            self.tally.count(
                "reacquired", "re-acquired GNSS %s after %.1f s of agreeing rejected fixes", kind, gate.reacquire_s
            )
            self._inflate(kind, pending.nu, R)
            pending = self._innovation(kind, z, R, lag)
        pending.commit()
        return "ok"

    def _report(self, t: float, status: GpsStatus, epoch: bool = True) -> StateEstimate:
        x, P = self._mean(), self._covariance()
        if t != self._t_state:
            dt = t - self._t_state
            if P is not None:
                F = step_jacobian(x, dt)
                P = F @ P @ F.T + process_noise(abs(dt), self.noise, self.layout)
            x = step(x, dt)
        if not np.all(np.isfinite(x)) or (P is not None and not np.all(np.isfinite(P))):
            raise _NumericFailure("non-finite state")
        estimate = StateEstimate(
            t=t,
            east_m=float(x[E]),
            north_m=float(x[N]),
            azimuth_rad=float(x[PHI] % (2.0 * math.pi)),
            speed_mps=float(x[V]),
            yaw_rate_rps=float(x[OMEGA]),
            gps=status,
            mode=self.name,
            window=self._window(),
            solve_ms=self.elapsed_ms(),
            spread=Spread.from_covariance(P, E, N, V, PHI) if P is not None else None,
        )
        self._on_report(estimate, epoch)
        return estimate
