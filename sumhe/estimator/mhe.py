"""The moving-horizon state-uniform estimator (issue 3): the service's default estimator, ``"mhe"``.

At every GNSS epoch (a fix, a "no fix", or an epoch GNSS missed) one step is appended to the window
(:mod:`sumhe.estimator.window`): its CAN speed and yaw rate (the samples of the step's half-intervals averaged),
the fix's position, course and speed over ground (Doppler: it pins the CAN speed scale, which the positions'
slow wander cannot) if the gate lets the fix in, and the step's start state, the previous newest state
moved on by the model with the newest CAN data. The window is re-solved (:mod:`sumhe.estimator.sqp`) warm-started
from the previous solution shifted by the steps the window slid; the newest state is the epoch's estimate.
Between epochs, each CAN speed sample gives an estimate at its own time: the newest solution moved on with the CAN
samples since, so the position sent is that of the newest CAN sample. ``docs/mhe.md`` describes the choices.

* Noise bounds are not estimated per epoch. The output bounds R are the per-step error allowances (as in
  :mod:`sumhe.estimator.grid`: ``r_cap_sigmas`` sigmas of the receiver's accuracy; for CAN, of the mean of the
  samples averaged), the state bounds Q the q caps (the vehicle's limits, :func:`mhe_q_caps`) scaled with each
  step's length: the estimate is the centre of the set of the prior box (11), as the batch estimator's
  ``objective = "caps"``. (On a 5 s window the MAP of (q, r) is noisy, and bounds near the derived
  floors make the boxes active: slower and less accurate, ``docs/mhe.md``.)
* Information leaving the window is kept twice. (1) The arrival box: when steps are dropped, the first state is
  held to a box around the previous solution's estimate of it, of half-widths ``alpha`` carried as an interval
  bound: ``alpha <- min(alpha, m_k)`` with ``m_k`` what the dropped step's outputs bound directly (a position by
  its allowance, the azimuth by the course's, speed and yaw rate by the CAN allowances and the CAN states' limits),
  then moved one step on, ``alpha <- |dT/dx| alpha + 2 Q_k`` (the set grows by one step of state noise, twice
  because the box is centred on the estimate, not on the set). (2) The arrival cost ``(z_0 - p)' W (z_0 - p)`` of
  the least-squares objective: the dropped steps' terms (their outputs, their state noise and the previous arrival
  cost), linearised at the solution, with the dropped states eliminated (a Schur complement: what an information
  filter carries). It keeps the correlations a box cannot, of the speed scale with the positions above all: the
  scale is seen over the whole drive, not just over one window. The CAN bias and scale may drift by
  ``mhe_theta_drift`` of their limits per square-root minute.
* Gate: a fix whose distance to the prediction exceeds its position allowance + ``mhe_gate_m`` +
  ``mhe_gate_drift`` x the distance driven since the last fix used (twice that distance while no azimuth has been
  measured since the start: the prediction may point anywhere) is rejected (``gps="rejected"``) and left out of
  the window, so one multipath jump cannot widen the bounds. The gate widens with the distance driven, so after
  a long outage the first good fixes are taken; fixes rejected for ``GATE_RESET_S`` (30 s) without a break restart
  the estimator at the newest fix.
* Failures: a failed or infeasible solve is retried with Q, R and the arrival box widened by ``widen_factor``
  (001 algorithm 3.3), at most ``mhe_max_retries`` times. If it still fails and the epoch brought a fix, the fix
  is an outlier the gate let in: it is rejected and the window solved again. Otherwise the epoch's estimate is
  the model prediction with ``mode="predict"``. An estimate is never skipped because of the solver.

Modes: ``"init"`` (first fix), ``"mhe"`` (solved), ``"mhe-widened"`` (solved after widening), ``"predict"``
(solver failed: model prediction), ``"can"`` (between epochs: the newest solution moved on with CAN data).
Only the single-antenna model ``su5`` is supported in the sample stream.
"""

from __future__ import annotations

import bisect
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.config import Config
from sumhe.errors import ConfigError
from sumhe.estimator.base import BadInputCounter, LocalFix, StateEstimate, bad_epoch_time
from sumhe.estimator.batch import model_for, state_box
from sumhe.estimator.bounds import q_caps
from sumhe.estimator.grid import (
    CAN_USED,
    GGA_RTK_FIXED,
    GGA_RTK_FLOAT,
    GPS_SPEED_RESOLUTION_MPS,
    gps_sigma_m,
    gps_speed,
)
from sumhe.estimator.sqp import SolveResult, WindowProblem, WindowSolver, make_solver, step_jacobians
from sumhe.estimator.window import Window, plan_window
from sumhe.messages import CanSample, GpsStatus
from sumhe.model.su import BIAS_STATE, GPS_SPEED_OUTPUT, SCALE_STATE, SuModel
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)

PERIOD_HISTORY = 16
MAX_PERIOD_S = 5.0
MAX_DATA_GAP_S = 10.0
"""No sample at all for this long restarts the estimator at the next valid fix."""
GATE_RESET_S = 30.0
"""Valid fixes rejected for this long without a break (longer than a multipath episode): the estimate is what is
wrong; restart at the newest fix."""
REACQUIRE_FIXES = 5
"""After an outage, this many rejected fixes in a row that agree with each other (their offsets from the
prediction differ by less than the gate's base radius) mean the prediction drifted, not the fixes: restart at the
newest fix (0.5 s at 10 Hz). Mid-drive, a consistent offset is more likely multipath: ``GATE_RESET_S`` applies."""
REACQUIRE_AFTER_M = 30.0
"""Distance driven without a fix used (m) from which a rejection streak counts as "after an outage"."""
PRIOR_POSITION_M = 1000.0
"""Half-width of the weak prior on the first position (m) at a start."""
CAN_KEEP_S = 2.0
"""CAN samples older than the newest step by more than this are forgotten."""
MIN_HALF_S = 0.005
"""A step's CAN outputs are the sample nearest to it while the samples reach less than this past it (s)."""
STARTUP_ITERATIONS = 3
"""SQP iterations per epoch until the window first reaches its normal length (the start point is rough)."""
EPS = 1e-9
"""Regularisation of the arrival cost's eliminations (directions without information)."""


def mhe_q_caps(model: SuModel, h: float, settings: EstimationSettings) -> NDArray[np.float64]:
    """The MHE's state-noise bounds for a step of ``h`` s: the q caps (vehicle limits,
    :func:`~sumhe.estimator.bounds.q_caps`), those of the integrated states (positions, azimuth; ``q_power`` 2)
    times ``mhe_trapezoid_q`` with the trapezoidal transition, whose one-step error is O(h^3), not Euler's O(h^2)."""
    caps = q_caps(model, h, settings)
    if settings.estimator.discretisation == "trapezoid":
        caps = np.where(np.array(model.q_power) == 2, settings.estimator.mhe.trapezoid_q * caps, caps)
    return caps


@dataclass
class _Samples:
    """Time-ordered CAN samples of one quantity (s, SI value), trimmed from the front."""

    t: list[float]
    v: list[float]

    def add(self, t: float, value: float) -> None:
        self.t.append(t)
        self.v.append(value)

    def trim(self, t_min: float) -> None:
        k = bisect.bisect_left(self.t, t_min)
        if k > 256 or (k and k == len(self.t)):
            del self.t[:k], self.v[:k]

    def mean(self, t0: float, t1: float) -> tuple[float, int] | None:
        """Mean of the samples in (t0, t1] and their number, None if there is none."""
        i, j = bisect.bisect_right(self.t, t0), bisect.bisect_right(self.t, t1)
        return (sum(self.v[i:j]) / (j - i), j - i) if j > i else None

    def at(self, t: float, max_age: float) -> float | None:
        """The newest sample at or before ``t`` if it is at most ``max_age`` s old, else the next one within it."""
        i = bisect.bisect_right(self.t, t)
        if i and t - self.t[i - 1] <= max_age:
            return self.v[i - 1]
        if i < len(self.t) and self.t[i] - t <= max_age:
            return self.v[i]
        return None

    @property
    def newest(self) -> float:
        return self.t[-1] if self.t else -math.inf


class MovingHorizonEstimator(BadInputCounter):
    """The moving-horizon SU estimator on the :class:`~sumhe.estimator.base.Estimator` protocol (module doc)."""

    name = "mhe"

    def __init__(self, settings: EstimationSettings | None = None) -> None:
        s = settings or EstimationSettings()
        if s.estimator.model != "su5":
            raise ConfigError(
                f"estimator.model: the moving-horizon estimator supports su5 only, got {s.estimator.model!r}"
            )
        self.settings = s
        self.model = model = model_for(s)
        self.policy = s.estimator.mhe
        self._m, self._md, self._n = model.n_states, model.n_dynamic, model.n_outputs
        self._ie, self._in = model.position
        self._iphi, self._iv, self._iw = model.index("phi"), model.index("v"), model.index("omega")
        self._ib = model.index(BIAS_STATE) if BIAS_STATE in model.states else None
        self._ik = model.index(SCALE_STATE) if SCALE_STATE in model.states else None
        self._jpos = model.gps_outputs[:2]
        self._jangle = model.angle_outputs[0]
        self._jsog = model.outputs.index(GPS_SPEED_OUTPUT) if GPS_SPEED_OUTPUT in model.outputs else None
        self._jspeed, self._jyaw = self._n - 2, self._n - 1
        lo, hi = state_box(model, 1, s)
        self._lo, self._hi = lo[0], hi[0]
        self._theta_range = (self._hi[self._md :] - self._lo[self._md :]) / 2.0
        self._window = Window(self.policy.max_steps + 1, self._m, self._n, gps_column=self._jpos[0])
        self._buckets = tuple(
            sorted(
                {*range(self.policy.steps, self.policy.max_steps, s.estimator.mhe.bucket_steps), self.policy.max_steps}
            )
        )
        self._solvers: dict[int, WindowSolver] = {}
        self._step_jac = step_jacobians(model)
        self._counts: Counter[str] = Counter()
        self.last_result: SolveResult | None = None
        self.reset()

    @classmethod
    def from_config(cls, config: Config) -> MovingHorizonEstimator:
        """The estimator of ``config.estimation`` (the registry's constructor), with the ``sqp`` solvers of every
        window size built now (half a second) rather than during the first long outage."""
        estimator = cls(config.estimation)
        if config.estimator.mhe.solver == "sqp":
            estimator.warm_up()
        return estimator

    # ---- the Estimator protocol ---------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget the window, the CAN samples and the stream's timing (counters are kept)."""
        self._started = False
        self._window.clear()
        self._speed = _Samples([], [])
        self._yaw = _Samples([], [])
        self._t_last = -math.inf
        self._last_epoch: float | None = None
        self._last_real_epoch: float | None = None
        self._intervals: deque[float] = deque(maxlen=PERIOD_HISTORY)
        self._delays: deque[float] = deque(maxlen=PERIOD_HISTORY)
        self._period = self.settings.gnss.period_s
        self._delay = 0.0
        self._Q = np.zeros((0, self._md))
        self._q_caps = mhe_q_caps(self.model, self._period, self.settings)
        self._alpha = np.full(self._md, np.inf)
        self._box_centre = np.zeros(self._m)
        self._prior = np.zeros(self._m)
        self._weight = np.zeros((self._m, self._m))
        self._theta0: NDArray[np.float64] | None = None
        self._prop: list[float] = []
        self._t_prop = -math.inf
        self._status: GpsStatus = "outage"
        self._since_fix_m = 0.0
        self._heading_known = False
        self._rejected_since: float | None = None
        self._reject_offsets: list[tuple[float, float]] = []
        self._reject_after_outage = False
        self._used_fixes = 0
        self._capacity: int | None = None
        self._push_t0 = time.perf_counter()

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        """Feed one sample (time-ordered); returns the estimates it produced (contract in
        :mod:`sumhe.estimator.base`). Never raises for bad data: it is counted and dropped."""
        self._push_t0 = time.perf_counter()
        if isinstance(sample, CanSample):
            return self._push_can(sample) if sample.quantity in CAN_USED else []
        if isinstance(sample, LocalFix):
            return self._push_fix(sample)
        self._count("bad_samples", "not a LocalFix or CanSample: %s", type(sample).__name__)
        return []

    def stats(self) -> Mapping[str, float | int | str]:
        """Counters (epochs, fixes used/rejected, outage epochs, solves, banded solves, widenings, fallbacks,
        dropped samples), the window length and the nominal period."""
        out: dict[str, float | int | str] = {
            "estimator": self.name,
            "solver": self.settings.estimator.mhe.solver,
            "window": len(self._window),
            "period_s": self.period_s,
        }
        out.update(self._counts)
        return out

    @property
    def period_s(self) -> float:
        """The nominal GNSS period (s): median of the recent intervals between epochs."""
        return self._period

    def smoothed(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The window now: step times (s) and the smoothed states (L x m, the model's state order), for replays."""
        return self._window.t.copy(), self._window.x.copy()

    def warm_up(self) -> None:
        """Build the solver of every window size now rather than at first use (milliseconds each for ``sqp``,
        up to seconds for the NLP solvers)."""
        for size in self._buckets:
            self._solver(size)

    # ---- stream handling ----------------------------------------------------------------------------------------

    def _push_can(self, sample: CanSample) -> list[StateEstimate]:
        q, value, t = sample.quantity, sample.value, sample.t
        if not (isinstance(t, float | int) and isinstance(value, float | int) and math.isfinite(t)):
            self._count("bad_samples", "CAN %s sample with a non-finite time or value", q)
            return []
        t -= self.settings.can.delay_s
        store = self._speed if q == "speed" else self._yaw
        if t < store.newest:
            self._count("dropped_backwards", "CAN %s sample %.3f s back in time dropped", q, store.newest - t)
            return []
        limit = self.settings.vehicle.max_speed_mps if q == "speed" else 2.0 * self.settings.vehicle.max_yaw_rate_rps
        if not (math.isfinite(value) and abs(value) <= limit):
            self._count("bad_samples", "CAN %s = %r beyond the vehicle limits dropped", q, value)
            return []
        self._check_gap(t)
        store.add(t, float(value))
        if not self._started:
            return []
        out = self._missed_epochs(t - self._delay)
        if q != "speed":
            return out
        if t > self._t_prop:
            self._prop = self._advance(self._prop, self._t_prop, t)
            self._t_prop = t
            out.append(self._estimate(self._prop, t, self._status, "can"))
        else:  # a sample older than the newest state (an epoch newer than the CAN data): the model run back
            x = self.model.transition(self._prop, self._prop, t - self._t_prop, math)
            out.append(self._estimate(x, t, self._status, "can"))
        return out

    def _push_fix(self, fix: LocalFix) -> list[StateEstimate]:
        t = fix.t
        bad = bad_epoch_time(t, self._last_epoch)
        if bad is not None:
            self._count(bad[0], bad[1], *bad[2])
            return []
        usable = self._usable(fix)
        if self._last_real_epoch is not None and 0.0 < t - self._last_real_epoch <= MAX_PERIOD_S:
            self._intervals.append(t - self._last_real_epoch)
            self._period = float(np.median(self._intervals))
        self._last_real_epoch = t
        newest_can = max(self._speed.newest, self._yaw.newest)
        if newest_can > t:
            self._delays.append(newest_can - t)
            self._delay = float(np.median(self._delays))
        self._check_gap(t)
        if not self._started:
            return [self._begin(fix)] if usable else []
        out = self._missed_epochs(t)
        out.append(self._epoch(t, fix if usable else None))
        return out

    def _check_gap(self, t: float) -> None:
        if self._started and t - self._t_last > MAX_DATA_GAP_S:
            self._count("restarts", "no data for %.1f s: restarting at the next fix", t - self._t_last)
            self._restart()
        self._t_last = max(self._t_last, t)

    def _restart(self) -> None:
        """Start over at the next valid fix, keeping the CAN samples, the stream's timing and the CAN states."""
        keep = (self._speed, self._yaw, self._last_real_epoch, self._intervals, self._period, self._t_last)
        theta = self._window.x[-1, self._md :].copy() if len(self._window) else None
        self.reset()
        self._speed, self._yaw, self._last_real_epoch, self._intervals, self._period, self._t_last = keep
        self._theta0 = theta

    def _missed_epochs(self, t_fix_clock: float) -> list[StateEstimate]:
        """Outage epochs for the epochs GNSS missed up to ``t_fix_clock`` (silence > 1.5 periods)."""
        out: list[StateEstimate] = []
        period = self.period_s
        while self._started and self._last_epoch is not None and t_fix_clock - self._last_epoch > 1.5 * period:
            self._counts["missed_epochs"] += 1
            out.append(self._epoch(self._last_epoch + period, None))
        return out

    # ---- epochs ---------------------------------------------------------------------------------------------------

    def _begin(self, fix: LocalFix) -> StateEstimate:
        """Start at a valid fix: position from it, azimuth from its course/heading (else 0), speed and yaw rate
        from CAN, the CAN states from before a restart or none (bias 0, scale 1)."""
        s, md = self.settings, self._md
        x = np.zeros(self._m)
        x[self._ie], x[self._in] = fix.east_m, fix.north_m
        speed, yaw = self._speed.at(fix.t, s.can.max_gap_s), self._yaw.at(fix.t, s.can.max_gap_s)
        angle = self._fix_angle(fix, speed)
        x[self._iphi] = angle[0] if angle is not None else 0.0
        x[self._iv] = speed if speed is not None else 0.0
        x[self._iw] = yaw if yaw is not None else 0.0
        if self._ik is not None:
            x[self._ik] = 1.0
        # a weak prior (no information yet): the position within a kilometre, the azimuth anywhere on the circle,
        # speed and yaw rate within their limits, the CAN states within their ranges; it keeps directions no
        # data fixes yet (the azimuth at standstill) where they are
        half = np.full(self._m, PRIOR_POSITION_M)
        half[self._iphi] = math.pi
        half[self._iv] = 0.5 * (self._hi[self._iv] - self._lo[self._iv])
        half[self._iw] = 0.5 * (self._hi[self._iw] - self._lo[self._iw])
        half[md:] = self._theta_range
        weight = np.diag(1.0 / np.square(half))
        if self._theta0 is not None:
            x[md:] = self._theta0
        self._box_centre, self._prior, self._weight = x.copy(), x.copy(), weight
        y, avail, allow = self._outputs(fix.t, s.gnss.period_s, fix)
        self._heading_known = bool(avail[self._jangle])
        self._window.append(fix.t, y, avail, allow, x)
        self._started = True
        self._last_epoch = fix.t
        self._used_fixes = 1
        self._status = "ok"
        self._counts["epochs"] += 1
        self._counts["gps_ok"] += 1
        self._set_prop(x, fix.t)
        return self._estimate(list(x), fix.t, "ok", "init")

    def _epoch(self, t: float, fix: LocalFix | None) -> StateEstimate:
        """One GNSS epoch at ``t`` (``fix`` None: no usable fix): append, plan, solve, report."""
        win = self._window
        self._last_epoch = t
        h_prev = t - float(win.t[-1])
        x_pred = np.array(self._advance(list(win.x[-1]), float(win.t[-1]), t))
        self._since_fix_m += abs(float(x_pred[self._iv])) * h_prev
        status: GpsStatus = "outage"
        if fix is not None:
            status = "ok" if self._gate(fix, x_pred) else "rejected"
            if status == "rejected" and self._rejected_since is not None and t - self._rejected_since > GATE_RESET_S:
                self._count("gate_resets", "fixes rejected for %.0f s: restarting at the newest fix", GATE_RESET_S)
                self._restart()
                return self._begin(fix)
            if status == "rejected" and self._reacquire(fix, x_pred):
                self._count("reacquired", "GNSS re-acquired after an outage: %d agreeing fixes", REACQUIRE_FIXES)
                self._restart()
                return self._begin(fix)
        y, avail, allow = self._outputs(t, h_prev, fix if status == "ok" else None)
        # the previous step's CAN outputs again, now that the samples of its second half-interval are in
        i = len(win) - 1
        t_before = float(win.t[i - 1]) if i else float(win.t[i]) - self.period_s
        self._can_outputs(
            win.t[i], 0.5 * (t_before + win.t[i]), win.t[i] + 0.5 * h_prev, win.y[i], win.avail[i], win.allow[i]
        )
        win.append(t, y, avail, allow, x_pred)
        self._counts["epochs"] += 1
        self._counts[{"ok": "gps_ok", "rejected": "gps_rejected", "outage": "outage_epochs"}[status]] += 1
        self._status = status
        plan = plan_window(win.gps, win.t, self.period_s, self.policy)
        if plan.drop:
            self._arrival(min(plan.drop, len(win) - 1))
        self._merge_offsets(win.apply(plan))
        x_new, mode = self._solve(None if plan.merge else plan.drop)
        if mode == "predict" and status == "ok":
            # the window cannot take the fix even with widened bounds: an outlier the gate let in; drop it
            self._count("rejected_by_solver", "fix at %.2f rejected: no trajectory of the window reaches it", t)
            win.avail[-1, list(self.model.gps_outputs)] = False
            status = self._status = "rejected"
            self._counts["gps_ok"] -= 1
            self._counts["gps_rejected"] += 1
            x_new, mode = self._solve(None)
        if mode == "predict":
            self._count(
                "fallbacks",
                "MHE solve failed %d times: the model prediction",
                self.settings.estimator.mhe.max_retries + 1,
            )
        self._gate_done(t, status)
        self._heading_known |= status == "ok" and bool(win.avail[-1, self._jangle])
        win.x[:] = x_new
        self._set_prop(x_new[-1], t)
        return self._estimate(list(x_new[-1]), t, status, mode)

    def _merge_offsets(self, merged: list[int]) -> None:
        """The offsets of the steps whose transitions now span merged steps: what the current trajectory moved
        beyond one trapezoidal step over the merged span (the CAN data of the steps merged away: a varying yaw
        rate is not linear over a long step), so the merge does not move the solution."""
        win, md = self._window, self._md
        for j in merged:
            pred = self.model.transition(win.x[j - 1], win.x[j], float(win.t[j] - win.t[j - 1]))
            win.offset[j, :md] = win.x[j, :md] - np.array(pred[:md])

    def _gate(self, fix: LocalFix, x_pred: NDArray[np.float64]) -> bool:
        """Whether ``fix`` passes the gate (module docstring)."""
        s = self.settings
        sig_e, sig_n = self._fix_sigma(fix)
        # the prediction may be off by a fraction of the distance driven since the last fix used, or by twice
        # that distance while the azimuth has never been measured (it may point anywhere)
        drift = s.estimator.mhe.gate_drift if self._heading_known else 2.0
        radius = s.estimator.r_cap_sigmas * max(sig_e, sig_n) + s.estimator.mhe.gate_m + drift * self._since_fix_m
        miss = math.hypot(fix.east_m - x_pred[self._ie], fix.north_m - x_pred[self._in])
        if miss <= radius or self._used_fixes < max(self.policy.steps_before, 2):
            return True
        log.debug("fix at %.2f rejected: %.1f m from the prediction (gate %.1f m)", fix.t, miss, radius)
        return False

    def _reacquire(self, fix: LocalFix, x_pred: NDArray[np.float64]) -> bool:
        """Whether a rejected fix completes a streak after an outage that says the prediction is what is wrong
        (:data:`REACQUIRE_FIXES`); records the fix's offset from the prediction."""
        if not self._reject_offsets:
            self._reject_after_outage = self._since_fix_m > REACQUIRE_AFTER_M
        self._reject_offsets.append((fix.east_m - float(x_pred[self._ie]), fix.north_m - float(x_pred[self._in])))
        if not self._reject_after_outage or len(self._reject_offsets) < REACQUIRE_FIXES:
            return False
        recent = np.array(self._reject_offsets[-REACQUIRE_FIXES:])
        spread = float(np.max(np.hypot(*(recent - recent.mean(axis=0)).T)))
        sig_e, sig_n = self._fix_sigma(fix)
        return spread <= self.settings.estimator.r_cap_sigmas * max(sig_e, sig_n) + self.settings.estimator.mhe.gate_m

    def _gate_done(self, t: float, status: GpsStatus) -> None:
        """The gate's bookkeeping once the epoch is solved: a fix used, or one more rejected."""
        if status == "ok":
            self._since_fix_m = 0.0
            self._rejected_since = None
            self._reject_offsets.clear()
            self._used_fixes += 1
        elif status == "rejected" and self._rejected_since is None:
            self._rejected_since = t

    def _fix_sigma(self, fix: LocalFix) -> tuple[float, float]:
        """1-sigma error (east, north) of a fix (m): the receiver's GST, else by quality/HDOP, else the default."""
        if fix.fix is not None:
            return gps_sigma_m(fix.fix, self.settings)
        s = self.settings
        sigma = fix.sigma_m
        if sigma is None:
            by_quality = {GGA_RTK_FIXED: s.gnss.sigma_rtk_m, GGA_RTK_FLOAT: s.gnss.sigma_float_m}
            sigma = by_quality.get(fix.quality, s.gnss.sigma_m)
        return sigma, sigma

    def _fix_angle(self, fix: LocalFix, speed: float | None) -> tuple[float, float] | None:
        """The azimuth a fix measures (rad) and its sigma: heading, else course above the minimum speed."""
        s = self.settings
        if s.gnss.use_heading and fix.heading_rad is not None and math.isfinite(fix.heading_rad):
            return fix.heading_rad, s.gnss.heading_sigma_rad
        v = fix.speed_mps if fix.speed_mps is not None and math.isfinite(fix.speed_mps) else speed
        moving = v is not None and v >= s.gnss.course_min_speed_mps
        if moving and fix.course_rad is not None and math.isfinite(fix.course_rad):
            return fix.course_rad, s.gnss.speed_sigma_mps / max(v, 1e-3)  # type: ignore[arg-type]
        return None

    def _outputs(
        self, t: float, h_prev: float, fix: LocalFix | None
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
        """Outputs, availability and error allowances of the step at ``t`` (as :mod:`sumhe.estimator.grid`):
        CAN speed and yaw rate averaged over the step's half-intervals, the fix's position and azimuth."""
        s, n = self.settings, self._n
        y, avail, allow = np.zeros(n), np.zeros(n, dtype=bool), np.ones(n)
        self._can_outputs(t, t - 0.5 * h_prev, t + 0.5 * self.period_s, y, avail, allow)
        if fix is None:
            return y, avail, allow
        k_sig = s.estimator.r_cap_sigmas
        for j, value, sigma in zip(self._jpos, (fix.east_m, fix.north_m), self._fix_sigma(fix), strict=True):
            y[j], avail[j], allow[j] = value, True, k_sig * max(sigma, s.gnss.resolution_m)
        can_speed = y[self._jspeed] if avail[self._jspeed] else None
        angle = self._fix_angle(fix, can_speed)
        if angle is not None:
            turn = 0.5 * self.period_s * abs(y[self._jyaw])
            y[self._jangle], avail[self._jangle], allow[self._jangle] = angle[0], True, k_sig * angle[1] + turn
        speed = gps_speed(fix.speed_mps, can_speed, s) if self._jsog is not None else None
        if speed is not None:
            sigma = max(s.gnss.speed_sigma_mps, GPS_SPEED_RESOLUTION_MPS)
            y[self._jsog], avail[self._jsog], allow[self._jsog] = speed, True, k_sig * sigma
        return y, avail, allow

    def _can_outputs(
        self, t: float, t0: float, t1: float, y: NDArray[np.float64], avail: NDArray[np.bool_], allow: NDArray
    ) -> None:
        """Fill in place the CAN outputs of the step at ``t`` whose half-intervals span (t0, t1]: the mean of the
        samples there, else the nearest within ``can_max_gap_s``; and their error allowances, half a resolution
        step plus ``r_cap_sigmas`` sigmas of the mean (the sensor's sigma over the root of the samples averaged).
        While the samples reach only part of the second half-interval, the interval is shrunk symmetrically
        around ``t`` (a mean over the first half alone would lag by a quarter step)."""
        s = self.settings
        for store, j, res, sigma in (
            (self._speed, self._jspeed, s.can.speed_quantum_mps, s.can.speed_sigma_mps),
            (self._yaw, self._jyaw, s.can.yaw_rate_quantum_rps, s.can.yaw_rate_sigma_rps),
        ):
            reach = min(t - t0, t1 - t, store.newest - t)
            mean = store.mean(t - reach, t + reach) if reach > MIN_HALF_S else None
            value, count = mean if mean is not None else (store.at(t, s.can.max_gap_s), 1)
            y[j], avail[j] = (value, True) if value is not None else (0.0, False)
            allow[j] = 0.5 * res + s.estimator.r_cap_sigmas * sigma / math.sqrt(count)
        if self._ik is None:
            allow[self._jspeed] += s.can.speed_scale_max * abs(y[self._jspeed])
        if self._ib is None:
            allow[self._jyaw] += s.can.yaw_rate_bias_max_rps

    # ---- the solve ------------------------------------------------------------------------------------------------

    def _solver(self, size: int) -> WindowSolver:
        capacity = self._buckets[bisect.bisect_left(self._buckets, size)]
        solver = self._solvers.get(capacity)
        if solver is None:
            s = self.settings
            t0 = time.perf_counter()
            max_iter = s.estimator.mhe.qp_max_iter if s.estimator.mhe.solver == "sqp" else s.estimator.mhe.nlp_max_iter
            tol = s.estimator.mhe.qp_tol if s.estimator.mhe.solver == "sqp" else 1e-6
            solver = make_solver(
                self.model, capacity, s.estimator.mhe.solver, max_iter, tol, s.estimator.mhe.sqp_iterations
            )
            self._solvers[capacity] = solver
            self._counts["solver_builds"] += 1
            build_ms = 1e3 * (time.perf_counter() - t0)
            log.info("MHE: %s solver for %d steps built in %.0f ms", s.estimator.mhe.solver, capacity, build_ms)
        return solver

    def _noise_bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """State bounds Q (L-1 x m_dynamic): the q caps (vehicle limits) at the nominal period, scaled with each
        step's length; output bounds R (L x n): the steps' error allowances (module docstring)."""
        win, period = self._window, self.period_s
        scale = (np.diff(win.t)[:, None] / period) ** np.array(self.model.q_power)[None, :]
        return self._q_caps[None, :] * scale, win.allow.copy()

    def _problem(self, capacity: int, Q: NDArray, R: NDArray, widen: float) -> WindowProblem:
        win, L = self._window, len(self._window)
        pad = capacity - L
        offset = np.vstack([win.offset[1:, : self._md], np.zeros((pad, self._md))])
        if pad == 0:
            x, h, y, avail = win.x, np.diff(win.t), win.y, win.avail
        else:
            x = np.vstack([win.x, np.repeat(win.x[-1:], pad, axis=0)])
            h = np.concatenate([np.diff(win.t), np.full(pad, self.period_s)])
            y = np.vstack([win.y, np.zeros((pad, self._n))])
            avail = np.vstack([win.avail, np.zeros((pad, self._n), dtype=bool)])
            Q = np.vstack([Q, np.ones((pad, self._md))])
            R = np.vstack([R, np.ones((pad, self._n))])
        return WindowProblem(
            n_steps=L,
            x=x,
            h=h,
            y=y,
            avail=avail,
            out_bound=R * widen,
            state_bound=Q * widen,
            lo=self._lo,
            hi=self._hi,
            box_centre=self._box_centre,
            box_half=np.concatenate([self._alpha * widen, np.full(self._m - self._md, np.inf)]),
            prior=self._prior,
            weight=self._weight,
            offset=offset,
        )

    def _solve(self, shift: int | None) -> tuple[NDArray[np.float64], str]:
        """Solve the window with retries (module docstring); the trajectory (L x m) and the mode."""
        win, s = self._window, self.settings
        L = len(win)
        capacity = self._buckets[bisect.bisect_left(self._buckets, L)]
        solver = self._solver(L)
        if capacity != self._capacity:
            shift = None
        self._capacity = capacity
        self._q_caps = mhe_q_caps(self.model, self.period_s, s)
        Q, R = self._noise_bounds()
        self._Q = Q
        iterations = (
            s.estimator.mhe.sqp_iterations
            if self.policy.steps <= L
            else max(s.estimator.mhe.sqp_iterations, STARTUP_ITERATIONS)
        )
        for attempt in range(s.estimator.mhe.max_retries + 1):
            problem = self._problem(capacity, Q, R, s.estimator.widen_factor**attempt)
            try:
                result = solver.solve(problem, shift if attempt == 0 else None, iterations)
            except (RuntimeError, ValueError, ArithmeticError) as e:
                self._count("solver_errors", "MHE solver raised %s", e)
                continue
            self.last_result = result
            self._counts["solves"] += 1
            self._counts["qp_iterations" if s.estimator.mhe.solver == "sqp" else "nlp_iterations"] += result.iterations
            if result.success:
                self._counts["banded_solves"] += result.status == "banded"
                if attempt:
                    self._counts["widened"] += 1
                return result.x[:L], "mhe-widened" if attempt else "mhe"
            self._count("failed_solves", "MHE solve failed (%s)", result.status)
        return win.x.copy(), "predict"

    # ---- the arrival box and cost -----------------------------------------------------------------------------

    def _arrival(self, drop: int) -> None:
        """Carry the arrival box and the arrival cost over the ``drop`` oldest steps leaving the window (module
        docstring), linearised at the current trajectory."""
        win, md, nt = self._window, self._md, self._m - self._md
        nx = (drop + 1) * md
        # the quadratic d' H d + 2 g' d over (x_0 .. x_drop dynamic states, CAN states) of the dropped terms
        H, g = np.zeros((nx + nt, nx + nt)), np.zeros(nx + nt)
        first = np.r_[0:md, nx : nx + nt]
        H[np.ix_(first, first)] = self._weight
        g[first] = self._weight @ (win.x[0] - self._prior)
        alpha = self._alpha
        for k in range(drop):
            q = self._Q[k] if k < len(self._Q) else self._q_caps
            w, dwp, dwn, e, dep = self._step_jac(win.x[k], win.x[k + 1], float(win.t[k + 1] - win.t[k]), win.y[k])
            w = w - win.offset[k + 1, :md]
            J = np.zeros((md, nx + nt))
            J[:, k * md : (k + 2) * md] = np.hstack([dwp[:, :md], dwn[:, :md]]) / q[:, None]
            J[:, nx:] = dwp[:, md:] / q[:, None]
            ok = win.avail[k]
            Je = np.zeros((int(ok.sum()), nx + nt))
            Je[:, k * md : (k + 1) * md] = dep[ok, :md] / win.allow[k][ok, None]
            Je[:, nx:] = dep[ok, md:] / win.allow[k][ok, None]
            H += J.T @ J + Je.T @ Je
            g += J.T @ (w / q) + Je.T @ (e[ok] / win.allow[k][ok])
            alpha = np.minimum(alpha, self._measured_bounds(k))
            # x_{k+1} = T(x_k, x_{k+1}) + w: dx_{k+1}/dx_k = (dw/dx_{k+1})^-1 (-dw/dx_k)
            F = np.abs(np.linalg.solve(dwn[:, :md], -dwp[:, :md]))
            unknown = ~np.isfinite(alpha)
            grown = F @ np.where(unknown, 0.0, alpha) + 2.0 * q
            alpha = np.where((F[:, unknown] > 0).any(axis=1), np.inf, grown)
        self._alpha = alpha
        self._box_centre = win.x[drop].copy()
        self._prior, self._weight = self._reduce(H, g, drop * md, win.x[drop], float(win.t[drop] - win.t[0]))

    def _reduce(
        self, H: NDArray, g: NDArray, na: int, x_new: NDArray[np.float64], dt: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Eliminate the first ``na`` variables (the dropped states) from the quadratic ``d' H d + 2 g' d``: the
        arrival cost's centre and weight on the new first state (its dynamic states, then the CAN states), with
        the CAN states' drift over ``dt`` s."""
        nt = self._m - self._md
        K = np.linalg.solve(H[:na, :na] + EPS * np.eye(na), np.column_stack([H[:na, na:], g[:na]]))
        Hr = H[na:, na:] - H[na:, :na] @ K[:, :-1]
        gr = g[na:] - H[na:, :na] @ K[:, -1]
        Hr = 0.5 * (Hr + Hr.T) + EPS * np.eye(len(gr))
        prior = x_new - np.linalg.solve(Hr, gr)
        if nt == 0:
            return prior, Hr
        # the CAN states drift: W <- (W^-1 + E D E')^-1 by Woodbury, D = drift variance over dt
        drift = np.square(self.settings.estimator.mhe.theta_drift * self._theta_range) * dt / 60.0
        E = Hr[:, -nt:]
        weight = Hr - E @ np.linalg.solve(Hr[-nt:, -nt:] + np.diag(1.0 / np.maximum(drift, 1e-30)), E.T)
        return prior, 0.5 * (weight + weight.T)

    def _measured_bounds(self, k: int) -> NDArray[np.float64]:
        """What the outputs of step ``k`` bound directly: half-widths per dynamic state (inf if nothing); speed
        and yaw rate through the CAN states' whole range (a box must not rely on their estimates)."""
        win = self._window
        out = np.full(self._md, np.inf)
        avail, allow, x = win.avail[k], win.allow[k], win.x[k]
        for j, i in ((self._jpos[0], self._ie), (self._jpos[1], self._in), (self._jangle, self._iphi)):
            if avail[j]:
                out[i] = allow[j]
        nt0 = self._md
        if avail[self._jspeed]:
            k_range = self._theta_range[self._ik - nt0] if self._ik is not None else 0.0
            k_low = (x[self._ik] - k_range) if self._ik is not None else 1.0
            out[self._iv] = (allow[self._jspeed] + abs(x[self._iv]) * k_range) / max(k_low, 1e-3)
        if self._jsog is not None and avail[self._jsog]:
            out[self._iv] = min(out[self._iv], allow[self._jsog])
        if avail[self._jyaw]:
            out[self._iw] = allow[self._jyaw] + (
                2.0 * self._theta_range[self._ib - nt0] if self._ib is not None else 0.0
            )
        return out

    # ---- propagation and estimates ------------------------------------------------------------------------------

    def _set_prop(self, x: NDArray[np.float64], t: float) -> None:
        """Restart the CAN-rate propagation at the newest solution and move it to the newest CAN speed sample."""
        t_to = self._speed.newest
        self._prop = self._advance(list(x), t, t_to) if t_to > t else list(x)
        self._t_prop = max(t, t_to)
        self._speed.trim(t - CAN_KEEP_S)
        self._yaw.trim(t - CAN_KEEP_S)

    def _advance(self, x: list[float], t0: float, t1: float) -> list[float]:
        """The state ``x`` at ``t0`` moved to ``t1`` (s) by the model's transition, with the CAN speed and yaw rate
        of the samples in between (trapezoid from sample to sample; speed divided by the scale, bias removed)."""
        if not t1 > t0:
            return x
        ts = self._speed.t
        i, j = bisect.bisect_right(ts, t0), bisect.bisect_right(ts, t1)
        times = [*ts[i:j], t1] if j == i or ts[j - 1] < t1 else ts[i:j]
        scale = x[self._ik] if self._ik is not None else 1.0
        bias = x[self._ib] if self._ib is not None else 0.0
        gap = self.settings.can.max_gap_s
        ta = t0
        for k, tb in enumerate(times):
            v = self._speed.v[i + k] if i + k < j else self._speed.at(tb, gap)
            mean = self._yaw.mean(ta, tb)
            w = mean[0] if mean is not None else self._yaw.at(tb, gap)
            xn = list(x)
            if v is not None:
                xn[self._iv] = v / scale if scale else v
            if w is not None:
                xn[self._iw] = w - bias
            x = self.model.transition(x, xn, tb - ta, math)
            x[self._iv], x[self._iw] = xn[self._iv], xn[self._iw]
            ta = tb
        return x

    def _estimate(self, x: list[float], t: float, status: GpsStatus, mode: str) -> StateEstimate:
        return StateEstimate(
            t=t,
            east_m=float(x[self._ie]),
            north_m=float(x[self._in]),
            azimuth_rad=float(x[self._iphi]) % (2.0 * math.pi),
            speed_mps=float(x[self._iv]),
            yaw_rate_rps=float(x[self._iw]),
            gps=status,
            mode=mode,
            window=len(self._window),
            solve_ms=1000.0 * (time.perf_counter() - self._push_t0),
        )
