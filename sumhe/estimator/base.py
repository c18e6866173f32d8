"""The one interface every estimator answers to (MHE, batch replays, EKF, UKF, particle filter, IMM).

The service, the replay and the benchmark feed samples in time order and collect estimates; they never branch
on which estimator runs. Positions are in the local east/north frame (a :class:`~sumhe.frontend.fixes.FixConverter`
turns :class:`~sumhe.messages.GnssFix` into :class:`~sumhe.frontend.fixes.LocalFix` with the datum policy; a
:class:`StateEstimate` becomes a geodetic :class:`~sumhe.messages.Estimate` with :func:`to_estimate`).

Contract of :meth:`Estimator.push`:

* a :class:`~sumhe.frontend.fixes.LocalFix` (valid or not) is a GNSS epoch: the estimator returns exactly one
  estimate for it, with ``gps`` ``"ok"`` (fix used), ``"rejected"`` (fix failed the gate) or ``"outage"`` (no
  usable fix);
* a :class:`~sumhe.messages.CanSample` updates the motion inputs; for each ``speed`` sample the estimator returns
  one estimate (the newest state propagated with the newest CAN data), so the output runs at CAN rate between GNSS
  epochs; when GNSS is silent for more than ``1.5`` nominal periods, the missed epochs are taken as outage epochs
  (returned as estimates with ``gps="outage"``);
* nothing is returned before the first valid fix ("no fix yet");
* an estimator never raises for bad data in the stream: it is dropped and counted.

The live estimators implement it once, in :class:`StreamEstimator`: its ``push`` runs the measurement front-end
(:class:`~sumhe.frontend.stream.FrontEnd`: input checks, CAN buffer, GNSS timing and missed epochs, each fix's
measurements and sigmas) and hands each estimator the front-end's events; an estimator implements only
``reset_state``, ``on_epoch`` and ``on_can``. Offline smoothers (``su-batch``) also provide
``finish() -> list[StateEstimate]``, called once at the end of a recorded drive; the pipeline calls it where it
exists (:meth:`sumhe.service.pipeline.Pipeline.finish`).
"""

from __future__ import annotations

import logging
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from sumhe.estimator.uncertainty import K1, InnovationScale, Spread, along, drift_variance, gpsd_errors
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.stream import CanTick, Epoch, FixMeasurement, FrontEnd
from sumhe.frontend.tally import Tally
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, Estimate, GpsStatus
from sumhe.records import quick_init
from sumhe.settings import EstimationSettings


@quick_init
@dataclass(frozen=True, slots=True)
class StateEstimate:
    """An estimator's answer in the local frame: east/north (m), azimuth (rad, clockwise from north),
    speed (m/s), yaw rate (rad/s, anticlockwise); the GNSS status and the estimator's mode; ``bound_*`` the
    half-widths of the set of positions consistent with model and data, where the estimator knows them; the window
    length (steps) and the time of the push that made it (ms); ``spread`` the estimator's own 1-sigma error figures
    (:mod:`sumhe.estimator.uncertainty`), ``sats``/``hdop`` the receiver's of the newest fix used
    (:meth:`StreamEstimator.push` fills them in)."""

    t: float
    east_m: float
    north_m: float
    azimuth_rad: float
    speed_mps: float
    yaw_rate_rps: float
    gps: GpsStatus
    mode: str
    bound_east_m: float | None = None
    bound_north_m: float | None = None
    window: int = 0
    solve_ms: float = 0.0
    spread: Spread | None = None
    sats: int | None = None
    hdop: float | None = None


@runtime_checkable
class Estimator(Protocol):
    """What the service, replay and benchmark call. See the module docstring for the contract of ``push``."""

    name: str

    def reset(self) -> None:
        """Forget everything (a clock jump or a new drive); the next valid fix starts over."""

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        """Feed one sample (time-ordered); returns the estimates it produced."""

    def stats(self) -> Mapping[str, float | int | str]:
        """Counters and figures for the status line (e.g. solves, failures, rejected fixes, window)."""


class StreamEstimator(ABC):
    """Base of the live estimators: :meth:`push` runs the front-end once for all and calls the three methods an
    estimator implements (the module docstring).

    * :meth:`reset_state`: forget the estimate (the front-end is reset by :meth:`reset`);
    * :meth:`on_epoch`: one GNSS epoch (a usable fix or none; ``epoch.start``: begin here) -> its estimate, at
      ``epoch.t``, with ``gps`` ``"ok"``, ``"rejected"`` or ``"outage"``, or None (a fix of a missed epoch,
      ``epoch.fills``, the estimator could not take: counted ``fixes_after_missed``);
    * :meth:`on_can`: one CAN sample taken in -> an estimate at its time, or None (the MHE and the Kalman peers
      answer each ``speed`` sample).

    ``uses_gps_speed = False`` leaves the fixes' speed over ground out of the measurements; ``averages_fixes``: see
    :class:`Receiver`. ``self.tally`` counts
    what the estimator reports in ``stats()``.

    Error estimates: each estimate's own spread (the estimator's 1-sigma figures) has its position covariance scaled
    by ``self.consistency`` (:class:`~sumhe.estimator.uncertainty.InnovationScale`), fed at every fix used with the
    innovation of the estimator's own prediction of it (:func:`predicted_at`: its estimates since the previous
    epoch), except where it started over at the fix (``epoch.start``, or ``self.started_over`` set by
    :meth:`on_epoch`: the MHE's gate restarts), then the fix's offset and the error of its time added
    (:class:`Receiver`), and, from a fix the estimator refused until it uses one again, that fix's offset from its
    estimate (:func:`refused_offset`). The estimates themselves are not changed.
    """

    name: ClassVar[str] = ""
    uses_gps_speed: ClassVar[bool] = True
    averages_fixes: ClassVar[bool] = True
    """False for an estimator that takes each fix as it is (dead reckoning): its own covariance already holds the
    fix's error, and :class:`Receiver` adds none; its residual at every fix is nil, so the consistency scales are fed
    its prediction at consecutive fixes too (:meth:`_match`)."""

    def __init__(self, settings: EstimationSettings) -> None:
        self.settings = settings
        self.tally = Tally(self.name, logging.getLogger(type(self).__module__))
        self.frontend = FrontEnd(settings, self.tally, self.uses_gps_speed)
        self._push_t0 = time.perf_counter()
        self._receiver: Receiver | None = None
        self.consistency = InnovationScale()
        self._drift = sensor_drift(settings)
        self._since_epoch: list[StateEstimate] = []
        self._at_fix: tuple[float, Spread | None, float] = (math.nan, None, 0.0)
        self.started_over = False
        self.unsettled = False
        self._pending_use: tuple[FixMeasurement, tuple[float, float, float, float] | None, bool] | None = None
        self._refused: tuple[float, float, float] | None = None

    def reset(self) -> None:
        """Forget the estimate, the stream (CAN data, GNSS timing) and the consistency scales; counters are kept."""
        self.frontend.reset()
        self._receiver = None
        self.consistency.reset()
        self._since_epoch = []
        self._at_fix = (math.nan, None, 0.0)
        self._pending_use = None
        self._refused = None
        self.reset_state()

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        """Feed one sample (time-ordered); returns the estimates it produced. Never raises for bad data."""
        self._push_t0 = time.perf_counter()
        out = []
        for event in self.frontend.push(sample):
            if isinstance(event, Epoch):
                fix = event.fix
                ahead = self.settings.can.max_gap_s  # farther on, the CAN data are missing: no prediction
                predicted = predicted_at(self._since_epoch, fix.t, ahead) if fix is not None else None
                prior = predicted
                self.started_over, self.unsettled = event.start, False
                if event.fresh:  # the CAN data changed meaning: what the scales learned of the errors is past
                    self.consistency.reset()
                estimate: StateEstimate | None = self.on_epoch(event)
                self._since_epoch = []
                self._heed(estimate, fix)
                if estimate is not None and estimate.gps == "ok" and event.fix is not None:
                    used = (event.fix, prior, self.started_over)
                    if self.unsettled:
                        self._pending_use = used
                    else:
                        self._use(estimate, *used)
            else:
                estimate = self.on_can(event)
            if estimate is not None:
                self._since_epoch.append(estimate)
                out.append(self._finished(estimate))
        return out

    def _use(
        self,
        estimate: StateEstimate,
        fix: FixMeasurement,
        prior: tuple[float, float, float] | None,
        restart: bool,
    ) -> None:
        """A fix used by the epoch's ``estimate``: the consistency scales fed (:meth:`_match`; not where the
        estimator started over at it, ``restart``), the spread at the fix (and its considered part,
        :meth:`considered_m2`) and the :class:`Receiver` set."""
        if prior is not None and not restart:
            self._match(fix, estimate, *prior)
        else:
            self.consistency.skip()
        self._at_fix = (fix.t, estimate.spread, self.considered_m2())
        white = self.consistency.white_m2(fix.sigma_east_m**2 + fix.sigma_north_m**2)
        motion = (estimate.speed_mps, estimate.azimuth_rad)
        sigma_s = self.frontend.time_offset_sigma_s
        self._receiver = Receiver(fix, self._calibrated(estimate), self.averages_fixes, white, sigma_s, motion)

    def settled(self, estimate: StateEstimate | None) -> None:
        """The estimate of the epoch :meth:`on_epoch` left unsettled (it set ``self.unsettled``: its estimate was a
        prediction, its solve still running, as the MHE's solved aside), once solved (None: given up). Its fix, if
        still used, then counts as :meth:`push` counts the others at once: the scales learn from the solved
        estimate, not from the prediction."""
        pending, self._pending_use = self._pending_use, None
        if pending is not None:
            self._heed(estimate, pending[0])
        if pending is not None and estimate is not None and estimate.gps == "ok":
            self._use(estimate, *pending)

    def _heed(self, estimate: StateEstimate | None, fix: FixMeasurement | None) -> None:
        """Remember the offset of a fix the epoch's ``estimate`` refused (:func:`refused_offset`) until a fix is
        used again."""
        if estimate is None or fix is None:
            return
        if estimate.gps == "rejected":
            self._refused = refused_offset(fix, estimate)
        elif estimate.gps == "ok":
            self._refused = None

    def _match(self, fix: FixMeasurement, used: StateEstimate, east_m: float, north_m: float, trace_p: float) -> None:
        """Feed the consistency scales one used fix (:class:`InnovationScale`): after a gap, the own prediction at
        its time (``east_m``, ``north_m``, own trace ``trace_p``); else the estimate that used it (``used``); and
        its residual from ``used`` (a gap's growth is measured by the innovation's change since the residual before
        it). An estimator that takes each fix as it is (not :attr:`averages_fixes`) is fed its prediction at every
        fix: its residuals are nil, and the white part of the fixes' error (half the mean squared change of the
        innovation from the residual at the fix before) is read from the predictions' innovations over one period,
        the difference of two fixes' errors, not from nil residuals (dead reckoning's white part read nil where its
        one-period innovations said 0.5-1.3 m^2 on the realistic drives)."""
        t0, spread0, _ = self._at_fix
        periods = (fix.t - t0) / self.frontend.period_s if math.isfinite(t0) else 0.0
        trace_r = fix.sigma_east_m**2 + fix.sigma_north_m**2
        consecutive = periods <= self.consistency.gap_periods
        if consecutive and used.spread is not None and self.averages_fixes:
            east_m, north_m = used.east_m, used.north_m
            trace_p = used.spread.var_east_m2 + used.spread.var_north_m2
            spread0 = used.spread
        trace0 = min(spread0.var_east_m2 + spread0.var_north_m2, trace_p) if spread0 is not None else trace_p
        nu = np.array([fix.east_m - east_m, fix.north_m - north_m])
        residual = np.array([fix.east_m - used.east_m, fix.north_m - used.north_m])
        drift = self._drift_m2(fix.t, used) if not consecutive else 0.0
        self.consistency.add(fix.t, nu, trace_r, trace0, trace_p - trace0, periods, drift, residual)

    def _drift_m2(self, t: float, estimate: StateEstimate) -> float:
        """What the CAN calibration's drift makes of the position's error (trace, m^2) at ``t`` since the newest fix
        used, at the speed of ``estimate`` (:func:`~sumhe.estimator.uncertainty.drift_variance`)."""
        t0 = self._at_fix[0]
        return drift_variance(t - t0, estimate.speed_mps, *self._drift) if math.isfinite(t0) else 0.0

    def _calibrated(self, estimate: StateEstimate) -> Spread | None:
        """An estimate's own spread with its position covariance scaled by the consistency scales."""
        if estimate.spread is None:
            return None
        _, at_fix, considered = self._at_fix
        drift = self._drift_m2(estimate.t, estimate)
        return self.consistency.calibrated(estimate.spread, at_fix, drift, considered)

    def considered_m2(self) -> float:
        """The part (trace, m^2) of the newest estimate's own position covariance that considered parameters make
        (carried in the covariance, never estimated: ``mskf-em``'s receiver heading offset), which the consistency
        scale at a fix may shrink (:meth:`InnovationScale.at_fix_m2`); none by default."""
        return 0.0

    def _finished(self, estimate: StateEstimate) -> StateEstimate:
        """The estimate as pushed out (one new estimate): its spread calibrated (:meth:`_calibrated`) and, after
        the first fix used, tagged by its :class:`Receiver`; widened by the newest refused fix's offset while no
        fix has been used since (:func:`refused_offset`)."""
        spread = self._calibrated(estimate)
        if spread is not None and self._refused is not None:
            spread = spread.grown(*self._refused)
        if self._receiver is not None:
            return _tagged(estimate, *self._receiver.tag(estimate.gps, spread))
        return estimate if spread is None else _tagged(estimate, spread, estimate.sats, estimate.hdop)

    def stats(self) -> Mapping[str, float | int | str]:
        """The estimator's name, the nominal GNSS period, the GNSS time offset applied (s: a fix's stamped time plus
        it is its time on the CAN clock) and its root mean square error (s, ``gps_time_offset_sigma_s``:
        :attr:`~sumhe.frontend.stream.FrontEnd.time_offset_sigma_s`), the consistency scales of its error
        estimates (:class:`InnovationScale`: ``eph_scale`` at a fix, ``eph_growth_scale`` of the growth since) and
        every counter (front-end and estimator)."""
        out: dict[str, float | int | str] = {
            "estimator": self.name,
            "period_s": self.frontend.period_s,
            "gps_time_offset_s": self.frontend.time_offset_s,
            "gps_time_offset_sigma_s": self.frontend.time_offset_sigma_s,
            "eph_scale": self.consistency.scale,
            "eph_growth_scale": self.consistency.growth_scale,
        }
        out.update(self.tally.counts)
        return out

    @property
    def period_s(self) -> float:
        """The nominal GNSS period (s) of the stream."""
        return self.frontend.period_s

    def elapsed_ms(self) -> float:
        """Time since the current ``push`` began (ms): the ``solve_ms`` of its estimates."""
        return 1000.0 * (time.perf_counter() - self._push_t0)

    @abstractmethod
    def reset_state(self) -> None:
        """Forget the estimate; the next epoch with ``start`` begins again."""

    @abstractmethod
    def on_epoch(self, epoch: Epoch) -> StateEstimate | None:
        """The estimate of one GNSS epoch (None: a missed epoch's fix not taken)."""

    @abstractmethod
    def on_can(self, tick: CanTick) -> StateEstimate | None:
        """The estimate at a CAN sample, or None."""


class Receiver:
    """What the newest fix used said of itself, for every estimate after it: satellites used and HDOP (and the
    estimate's horizontal 1-sigma, m, when it was used), and its position sigmas (m, the front-end's).

    The error a filter cannot see: GNSS position errors are correlated over minutes (multipath, atmosphere), and a
    filter that takes each fix as independent shrinks its covariance below the fix's own sigma although the
    offset the fixes share does not average out; every estimator's estimate carries that offset into an outage.
    So every estimate's position covariance gets that offset's variance on top of the estimator's own (:meth:`tag`),
    unless ``offset`` is False (an estimator whose covariance holds it already): the fix's own (its 1-sigma per axis)
    less the white part, ``white_m2`` (the trace, m^2, :meth:`InnovationScale.white_m2`), which does not carry from
    one fix to the next. The calibrated covariance at the fix holds that part already (the consistency scale at a
    fix is what the innovations say beyond it, and an estimator that weighs the fixes smooths some of it into its
    estimate); adding the fix's whole variance counted it twice (the MHE, which follows the fixes, had 98.3 % of its
    errors within ``eph`` with GPS on the realistic drives, 99.5 % at a fix: its squared error there 9.7 m^2 on the
    mean where its ``eph`` claimed about 19).

    The fix's time is an error of the whole stream too: the front-end places each fix on the CAN clock with a GNSS
    time offset of standard deviation ``time_sigma_s`` (s, :attr:`~sumhe.frontend.stream.FrontEnd.time_offset_sigma_s`:
    :data:`~sumhe.frontend.alignment.UNLEARNED_TIME_OFFSET_SD_S` before the clock learner's first fit, its fits'
    standard error after, 0 for a configured offset), and an estimate that follows fixes placed ``dt`` late is
    where the vehicle was ``dt`` earlier: off along the track by the speed times ``dt``, which no innovation sees
    (the estimates follow the misplaced fixes). An outage inherits that offset as it was at the newest fix used
    (the estimate's speed and azimuth there, ``motion``: m/s, rad clockwise from north); the estimate's own growth
    since does not change it. So every estimate's covariance, dead reckoning's too, gets a position error of
    ``speed time_sigma_s`` (1-sigma) along the azimuth at that fix. On the shared real drive the offset learned
    is -0.36 s, and 0 s (sigma 0.3 s) until the learner's first fit after 160 s: the estimates entered the outage
    at 150 s at 9.7 m/s 7.7-8.7 m behind the removed fixes, 3.5 m of it the offset's."""

    def __init__(
        self,
        fix: FixMeasurement,
        spread: Spread | None,
        offset: bool = True,
        white_m2: float = 0.0,
        time_sigma_s: float = 0.0,
        motion: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        gnss = fix.fix.fix
        self.sats = gnss.sats if gnss is not None else None
        self.hdop = fix.fix.hdop
        trace = fix.sigma_east_m**2 + fix.sigma_north_m**2
        scale = max(1.0 - white_m2 / trace, 0.0) if offset and trace > 0.0 else 0.0
        speed_mps, azimuth_rad = motion
        east, north, self.cov_en_m2 = along(speed_mps * time_sigma_s, azimuth_rad)
        self.var_east_m2 = scale * fix.sigma_east_m**2 + east
        self.var_north_m2 = scale * fix.sigma_north_m**2 + north
        self.sigma_m = horizontal_sigma(self._grow(spread))

    def _grow(self, spread: Spread | None) -> Spread | None:
        return None if spread is None else spread.grown(self.var_east_m2, self.var_north_m2, self.cov_en_m2)

    def tag(self, gps: GpsStatus, spread: Spread | None) -> tuple[Spread | None, int | None, float | None]:
        """An estimate's spread, satellites and HDOP from its GNSS status and (calibrated) spread: the fix's
        position covariance added to its own; the fix's satellites and HDOP while GPS is used; in outages (and for
        rejected fixes) no satellites and the fix's HDOP grown as the estimate's horizontal sigma grew since (so
        that a consumer who reads only HDOP sees the error grow)."""
        spread = self._grow(spread)
        if gps == "ok":
            return spread, self.sats, self.hdop
        sigma = horizontal_sigma(spread)
        hdop = self.hdop
        if hdop is not None and sigma is not None and self.sigma_m:
            hdop = hdop * max(sigma / self.sigma_m, 1.0)
        return spread, 0, hdop


def sensor_drift(settings: EstimationSettings, sigmas: float = 1.0) -> tuple[float, float]:
    """The random-walk densities of the yaw-rate bias (rad/s per square-root s) and of the speed scale (1 per
    square-root s) the config allows: ``estimator.mhe.theta_drift`` of their half-ranges
    (``sensors.can.yaw_rate_bias_max_rps``, ``speed_scale_max``) per square-root minute, the MHE's own figure of
    how far the CAN calibration may drift (by default 0.057 deg/s per square-root minute for the bias, the top of
    the drifts of real yaw-rate sensors the realistic profile draws from: docs/simulator.md), read as ``sigmas``
    standard deviations (1 for the peers; the MHE reads it as the bound of ``estimator.r_cap_sigmas`` sigmas its
    arrival cost makes of it: :mod:`sumhe.estimator.mhe.newest`)."""
    per_s = settings.estimator.mhe.theta_drift / math.sqrt(60.0) / sigmas
    return per_s * settings.can.yaw_rate_bias_max_rps, per_s * settings.can.speed_scale_max


def refused_offset(fix: FixMeasurement, estimate: StateEstimate) -> tuple[float, float, float]:
    """The position covariance (east variance, north variance, their covariance; m^2) a refused fix adds to the
    estimates until a fix is used again: an error along the fix's offset from the ``estimate`` of its epoch whose 95 %
    half-width (:data:`~sumhe.estimator.uncertainty.K1` sigmas) is that offset, so the 95 % figures reach the fix.

    An estimator refuses a fix far from its estimate: the fix may be the outlier, or the estimate may be off (a
    restart onto a multipath episode, a drift the filter's covariance did not foresee, after which it refuses
    every good fix). The estimate alone cannot tell which: on the realistic profile's nine drives (seeds 1-3) and
    nine more (4-6), the MHE's estimates while it refused fixes were farther from the truth than the refused fix in 69 %
    of the cases, and only 45 % of their errors were within ``eph`` (median error 11.3 m against a median ``eph``
    of 7.2 m). So the error figures allow for the fix being right: ``eph`` reaches about as far as the fix."""
    east = fix.east_m - estimate.east_m
    north = fix.north_m - estimate.north_m
    return along(math.hypot(east, north) / K1, math.atan2(east, north))


def _tagged(e: StateEstimate, spread: Spread | None, sats: int | None, hdop: float | None) -> StateEstimate:
    """``dataclasses.replace(e, spread=spread, sats=sats, hdop=hdop)``, a few times faster (one per estimate)."""
    return StateEstimate(
        e.t, e.east_m, e.north_m, e.azimuth_rad, e.speed_mps, e.yaw_rate_rps, e.gps, e.mode, e.bound_east_m,
        e.bound_north_m, e.window, e.solve_ms, spread, sats, hdop
    )  # fmt: skip


def predicted_at(
    estimates: Sequence[StateEstimate], t: float, ahead_s: float = math.inf
) -> tuple[float, float, float] | None:
    """An estimator's prediction of a fix at ``t`` (s) from its estimates since its previous GNSS epoch (that epoch's
    included): their position (east, north; m) interpolated linearly to ``t``, or moved on from the newest with its
    speed and azimuth where ``t`` is later by at most ``ahead_s`` (the CAN data may lag the fix by more than the
    receiver's latency; the estimator passes ``sensors.can.max_gap_s``), and the trace of their own position
    covariance there (m^2). None before their times, more than ``ahead_s`` after them, or without a spread."""
    pts = sorted((e for e in estimates if e.spread is not None), key=lambda e: e.t)
    if not pts or not pts[0].t <= t <= pts[-1].t + ahead_s:
        return None
    if t >= pts[-1].t:
        last = pts[-1]
        assert last.spread is not None  # filtered above
        run = last.speed_mps * (t - last.t)
        trace = last.spread.var_east_m2 + last.spread.var_north_m2
        return last.east_m + run * math.sin(last.azimuth_rad), last.north_m + run * math.cos(last.azimuth_rad), trace
    i = next(k for k, e in enumerate(pts) if e.t >= t)
    a, b = pts[max(i - 1, 0)], pts[i]
    w = (t - a.t) / (b.t - a.t) if b.t > a.t else 1.0
    assert a.spread is not None and b.spread is not None  # filtered above

    def mix(u: float, v: float) -> float:
        return (1.0 - w) * u + w * v

    trace_a = a.spread.var_east_m2 + a.spread.var_north_m2
    trace_b = b.spread.var_east_m2 + b.spread.var_north_m2
    return mix(a.east_m, b.east_m), mix(a.north_m, b.north_m), mix(trace_a, trace_b)


def on_a_line(run: Sequence[tuple[float, NDArray[np.float64]]], tolerance: float) -> bool:
    """Whether vectors stamped with times (a streak of rejected fixes' offsets from an estimator's prediction) lie
    within ``tolerance`` (each component) of their least-squares straight line in time; two always do. A prediction
    dead-reckoned on a wrong speed or azimuth moves away from the fixes steadily, so its offsets agree on a line as
    constant ones do; a multipath jump's do not."""
    if len(run) < 3:
        return True
    t = np.array([ti for ti, _ in run])
    v = np.array([vi for _, vi in run])
    design = np.column_stack([np.ones_like(t), t - t[0]])
    coef, *_ = np.linalg.lstsq(design, v, rcond=None)
    return bool(np.max(np.abs(v - design @ coef)) <= tolerance)


def horizontal_sigma(spread: Spread | None) -> float | None:
    """The root mean square of the east and north sigmas (m), or None."""
    return None if spread is None else math.sqrt(max(0.5 * (spread.var_east_m2 + spread.var_north_m2), 0.0))


def to_estimate(state: StateEstimate, frame: LocalFrame, up_m: float = 0.0) -> Estimate:
    """A local-frame estimate as the sinks send it (with WGS84 latitude, longitude and height)."""
    lat, lon, alt = frame.point_to_geodetic(state.east_m, state.north_m, up_m)
    # positional: a third faster than keywords for its 18 fields (one per estimate)
    return Estimate(
        state.t, state.east_m, state.north_m, lat, lon, alt, state.azimuth_rad % (2.0 * math.pi), state.speed_mps,
        state.yaw_rate_rps, state.gps, state.mode, state.window, state.solve_ms, state.bound_east_m,
        state.bound_north_m, gpsd_errors(state.spread) if state.spread is not None else None, state.sats, state.hdop
    )  # fmt: skip
