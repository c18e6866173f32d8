"""The moving-horizon state-uniform estimator (issue 3): the service's default estimator, ``"mhe"``, a conductor
of its parts.

At every GNSS epoch the front-end hands over (a fix, a "no fix", or an epoch GNSS missed), one step is appended to
the window (:mod:`.window`): its CAN speed and yaw rate and, if the gate (:mod:`.gate`) lets the fix in, the fix's
position, azimuth and speed over ground (Doppler: it pins the CAN speed scale, which the positions' slow wander
cannot), each with its error allowance (:mod:`.outputs`), and the step's start state, the previous newest state
moved on by the model with the CAN data (:mod:`.propagate`). Steps leaving the window leave their information in the
arrival box and cost (:mod:`.arrival`). The window is re-solved (:mod:`.solve`: buckets, retries; the solvers of
:mod:`.sqp` and :mod:`.nlp` on the problem of :mod:`.problem`) warm-started from the previous solution shifted by
the steps the window slid; the newest state is the epoch's estimate. Between epochs, each CAN speed sample gives an
estimate at its own time: the newest solution moved on with the CAN samples since. A fix that came after its epoch
was declared missed (``Epoch.fills``: the receiver's latency grew) goes into that epoch's step, and the window is
solved again (:meth:`MovingHorizonEstimator._fill`). ``docs/mhe.md`` describes the choices.

Failures: if the solve still fails after its retries and the epoch brought a fix, the fix is an outlier the gate
let in: it is rejected and the window solved again. Otherwise the epoch's estimate is the model prediction with
``mode="predict"``. An estimate is never skipped because of the solver. When the gate says the estimate is what is
wrong (fixes rejected too long, or a consistent streak after an outage), the estimator restarts at the newest fix,
keeping its CAN bias and scale.

Modes: ``"init"`` (first fix), ``"mhe"`` (solved), ``"mhe-widened"`` (solved after widening), ``"predict"``
(solver failed: model prediction), ``"can"`` (between epochs: the newest solution moved on with CAN data),
``"degraded"`` (``defer_solves`` set by a service that fell behind: the epoch appended to the window unsolved, its
estimate the model prediction; the next epoch solved solves them all), ``"aside"`` (``solve_aside`` set by the
live service: the epoch's window is solved in a thread of its own, its estimate the model prediction; the CAN
samples that come meanwhile are answered from it, and the solution, once done, is propagated over them).
Only the single-antenna model ``su5`` is supported in the sample stream.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from numpy.typing import NDArray

from sumhe.config import Config
from sumhe.errors import ConfigError
from sumhe.estimator.base import StateEstimate, StreamEstimator, sensor_drift
from sumhe.estimator.batch import model_for, nominal_parameters
from sumhe.estimator.mhe.arrival import (
    Arrival,
    arrival_update,
    measured,
    prior_arrival,
    theta_drift_variance,
    theta_information,
)
from sumhe.estimator.mhe.envelope import OutputEnvelope
from sumhe.estimator.mhe.gate import GATE_RESET_S, REACQUIRE_FIXES, FixGate
from sumhe.estimator.mhe.newest import NewestError
from sumhe.estimator.mhe.outputs import can_outputs, fix_outputs, step_outputs
from sumhe.estimator.mhe.preintegration import part_bound, step_motion
from sumhe.estimator.mhe.problem import SolveResult, step_jacobians
from sumhe.estimator.mhe.propagate import Propagation, advance
from sumhe.estimator.mhe.solve import WindowSolve
from sumhe.estimator.mhe.window import Window, plan_window
from sumhe.frontend.measurements import can_allowance, unmodelled_can_errors
from sumhe.frontend.standstill import StopWatch, bias_at_rest
from sumhe.frontend.stream import OUTPUT_QUANTITY, SAME_EPOCH, CanTick, Epoch, FixMeasurement
from sumhe.messages import GpsStatus
from sumhe.model.su import SuModel, output_residuals
from sumhe.settings import EstimationSettings

PRIOR_POSITION_M = 1000.0
"""Half-width of the weak prior on the first position (m) at a start."""
STATUS_COUNTERS: dict[str, str] = {"ok": "gps_ok", "rejected": "gps_rejected", "outage": "outage_epochs"}

HOLD_FRACTION = 1e-3
"""While the newest step has no fix, the CAN scale states are held where the last window solved with one left
them, within this fraction of their half-ranges (:meth:`MovingHorizonEstimator._solve`)."""


def fix_moved(model: SuModel, fix: FixMeasurement, x: NDArray[np.float64], t: float) -> FixMeasurement:
    """``fix`` moved to ``t`` (s) along the state ``x`` (its speed and azimuth: a few tens of ms at most)."""
    dt = t - fix.t
    v, phi = float(x[model.i_v]), float(x[model.i_phi])
    east, north = fix.east_m + v * dt * math.sin(phi), fix.north_m + v * dt * math.cos(phi)
    return dataclasses.replace(fix, t=t, east_m=east, north_m=north)


class MovingHorizonEstimator(StreamEstimator):
    """The moving-horizon SU estimator (module docstring) on :class:`~sumhe.estimator.base.StreamEstimator`."""

    name = "mhe"

    def __init__(self, settings: EstimationSettings | None = None) -> None:
        s = settings or EstimationSettings()
        if s.estimator.model != "su5":
            raise ConfigError(
                f"estimator.model: the moving-horizon estimator supports su5 only, got {s.estimator.model!r}"
            )
        super().__init__(s)
        # the drift floor of the growth (StreamEstimator._drift_m2) at the MHE's own reading of theta_drift, a bound
        # of r_cap_sigmas sigmas (.newest): read as one sigma, its t^5 set the late shape of the growth in place of
        # the MHE's own (above it at 76 % of the estimates 45-60 s into the realistic profile's outages; eph 17.8
        # times the median error there, 8.5 times with this floor, 3.42 and 3.40 times over all outages)
        self._drift = sensor_drift(s, s.estimator.r_cap_sigmas)
        self.model = model = model_for(s)
        self.policy = s.estimator.mhe
        self.window = Window(self.policy.max_steps + 1, model.n_states, model.n_outputs, model.j_position[0])
        self.solve = WindowSolve(model, s, self.tally)
        self.gate = FixGate(s)
        self.propagation = Propagation(model, s.can.max_gap_s)
        self.defer_solves = False
        """Set by a service that fell behind: epochs are appended to the window without a solve (mode
        ``"degraded"``) until it is cleared; the next epoch solved then solves the whole window."""
        self.solve_aside = False
        """Set by the live service: an epoch's solve runs in a thread of its own while the CAN samples after it are
        answered (:meth:`_collect`)."""
        self._aside: ThreadPoolExecutor | None = None
        self._pending: tuple[float, GpsStatus, Future[tuple[NDArray[np.float64], str]]] | None = None
        self._unsolved = False
        self._step_jac = step_jacobians(model)
        self._q_power = np.array(model.q_power, dtype=float)
        """The powers of the state bounds' growth with a step's length, as floats: an int array is cast at every
        CAN-rate estimate's bounds (0.84 -> 0.62 us with floats; the same bits)."""
        md = model.n_dynamic
        self._theta_range = (self.solve.hi[md:] - self.solve.lo[md:]) / 2.0
        self._scale_states = [i for i in (model.i_scale, model.i_gain) if i is not None]
        self._hold_bounds = [HOLD_FRACTION * float(self._theta_range[i - md]) for i in self._scale_states]
        drift = theta_drift_variance(self.policy.theta_drift, self._theta_range, 1.0)  # per second
        self.newest = NewestError(model, self._step_jac, s.estimator.r_cap_sigmas, drift)
        c, k_sig = s.can, s.estimator.r_cap_sigmas
        extra = unmodelled_can_errors(1.0, c, model.i_scale is not None, model.i_bias is not None)
        self._can_sample_allow = (
            (can_allowance(c.speed_quantum_mps, c.speed_sigma_mps, k_sig), float(extra[0])),
            can_allowance(c.yaw_rate_quantum_rps, c.yaw_rate_sigma_rps, k_sig) + extra[1],
        )
        """One CAN sample's allowances (:func:`~sumhe.estimator.mhe.outputs.can_outputs`'s): the speed's (m/s)
        and what a model without the speed scale adds per m/s, the yaw rate's (rad/s, with the bias a model
        without it adds): a CAN-rate estimate's outputs (:meth:`_part_bounds`)."""
        self.envelope = self._new_envelope()
        self.reset_state()

    @classmethod
    def from_config(cls, config: Config) -> MovingHorizonEstimator:
        """The estimator of ``config.estimation`` (the registry's constructor), with the ``sqp`` solvers of every
        window size and their OSQP workspaces built now (under a second; 30 MB) rather than during the first long
        outage or run of rejected fixes: memory stays flat over a day of data."""
        estimator = cls(config.estimation)
        if config.estimator.mhe.solver == "sqp":
            estimator.warm_up()
        return estimator

    # ---- the StreamEstimator's methods ------------------------------------------------------------------------

    def _new_envelope(self) -> OutputEnvelope:
        p = self.policy
        return OutputEnvelope(self.model.n_outputs, p.bound_history, p.bound_margin, p.bound_max_factor)

    def reset(self) -> None:
        """Forget everything, the output bounds learned from the data too (a restart within a drive keeps them: the
        same sensors; a reset may be the next drive, as a fleet worker reuses its estimator)."""
        super().reset()
        self.envelope = self._new_envelope()

    def reset_state(self) -> None:
        """Forget the window, the arrival, the gate's streaks and the CAN states (counters are kept)."""
        if self._pending is not None:
            self._pending[2].result()  # the solve reads the window: let it end
            self._pending = None
            self.settled(None)
        self.window.clear()
        self.solve.reset()
        self.newest.reset()
        self.gate.start(heading_known=False)
        self._arrival: Arrival | None = None
        self._unsolved = False
        self._theta0: NDArray[np.float64] | None = None
        self._theta_info: NDArray[np.float64] | None = None
        self._scales: list[float] | None = None
        """The CAN scale states (speed scale, yaw-rate gain) of the last window solved with a fix at its newest step."""
        self._stops = StopWatch()
        self._status: GpsStatus = "outage"

    def on_epoch(self, epoch: Epoch) -> StateEstimate | None:
        self._collect(wait=True)
        if epoch.start:
            assert epoch.fix is not None  # the front-end starts at a usable fix
            if epoch.fresh:  # the output bounds were learned from CAN data that changed meaning
                self.envelope = self._new_envelope()
            self._restart(keep_can_states=not epoch.fresh)
            return self._begin(epoch.fix)
        if epoch.fills:
            assert epoch.fix is not None  # the front-end fills a missed epoch with a usable fix
            return self._fill(epoch.fix)
        return self._epoch(epoch.t, epoch.fix)

    def on_can(self, tick: CanTick) -> StateEstimate | None:
        if self._pending is not None:
            self._collect(wait=False)
        if not tick.output or not len(self.window):
            return None
        can = self.frontend.can
        # a speed tick moves the CAN-rate state on; a yaw-rate tick between sparse speed samples is answered from it
        # without moving it (the steps stay from speed sample to speed sample)
        move = self.propagation.to if tick.quantity == OUTPUT_QUANTITY else self.propagation.ahead
        x = move(tick.t, can)
        return self._estimate(x, tick.t, self._status, "can")

    def stats(self) -> Mapping[str, float | int | str]:
        """Counters (epochs, fixes used/rejected, outage epochs, solves, banded solves, widenings, fallbacks,
        dropped samples), the window length and the nominal period."""
        return {**super().stats(), "solver": self.policy.solver, "window": len(self.window)}

    # ---- for replays and benchmarks ---------------------------------------------------------------------------

    @property
    def last_result(self) -> SolveResult | None:
        """The last solver answer."""
        return self.solve.last_result

    def smoothed(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The window now: step times (s) and the smoothed states (L x m, the model's state order), for replays."""
        return self.window.t.copy(), self.window.x.copy()

    def warm_up(self) -> None:
        """Build the solver of every window size now rather than at first use (10-60 ms each for ``sqp``, with its
        OSQP workspace; up to seconds for the NLP solvers)."""
        self.solve.warm_up()

    # ---- epochs -----------------------------------------------------------------------------------------------

    def _restart(self, keep_can_states: bool = True) -> None:
        """Forget the window to start over at a fix, keeping the CAN and installation states of the last one and what
        the arrival cost held on them unless told not to (the CAN data changed meaning: ``Epoch.fresh``); the fix is
        not matched against the prediction given up: ``started_over``. With their values alone under the start's
        weak prior, a restart let them wander again: on a realistic simulated highway drive (seed 11) the azimuth
        offset went from 0.07 to -1.7 deg in 4 s after one, the azimuth with it, and the fixes were not followed for
        70 s (the estimate up to 47 m off)."""
        self.started_over = True
        md = self.model.n_dynamic
        theta = self.window.x[-1, md:].copy() if len(self.window) and keep_can_states else None
        info = None
        if theta is not None and self._arrival is not None:  # the arrival's states are the window's first
            since = float(self.window.t[-1] - self.window.t[0])
            drift = theta_drift_variance(self.policy.theta_drift, self._theta_range, since)
            info = theta_information(self._arrival.weight, md, drift)
        stops = self._stops
        self.reset_state()
        self._theta0, self._theta_info = theta, info
        if theta is not None:
            self._stops = stops

    def _start_over(self, fix: FixMeasurement, x_pred: np.ndarray) -> StateEstimate:
        """Give the prediction ``x_pred`` up and start again at ``fix`` (:meth:`_restart`, :meth:`_begin`); the
        gate keeps the jump from the one to the other, which the fixes after it may undo (:meth:`FixGate.start`)."""
        i_e, i_n = self.model.position
        self._restart()
        return self._begin(fix, (fix.t, np.array([fix.east_m - x_pred[i_e], fix.north_m - x_pred[i_n]])))

    def _begin(self, fix: FixMeasurement, jump: tuple[float, np.ndarray] | None = None) -> StateEstimate:
        """Start at a usable fix: position from it, azimuth from its course/heading (else 0), speed and yaw rate
        from CAN, the sensor and installation states from before a restart or their nominal values, under a weak
        prior (plus, after a restart, what was known of those states); ``jump``: a restart's, for the gate."""
        model, s, t = self.model, self.settings, fix.t
        md, can = model.n_dynamic, self.frontend.can
        x = np.zeros(model.n_states)
        i_e, i_n = model.position
        x[i_e], x[i_n] = fix.east_m, fix.north_m
        speed, yaw = can["speed"].at(t, s.can.max_gap_s), can["yaw_rate"].at(t, s.can.max_gap_s)
        x[model.i_phi] = fix.azimuth_rad if fix.azimuth_rad is not None else 0.0
        x[model.i_v] = speed if speed is not None else 0.0
        x[model.i_omega] = yaw if yaw is not None else 0.0
        x[md:] = self._theta0 if self._theta0 is not None else nominal_parameters(model, s)
        # a weak prior (no information yet): the position within a kilometre, the azimuth anywhere on the circle,
        # speed and yaw rate within their limits, the CAN states within their ranges; it keeps directions no
        # data fixes yet (the azimuth at standstill) where they are
        lo, hi = self.solve.lo, self.solve.hi
        half = np.full(model.n_states, PRIOR_POSITION_M)
        half[model.i_phi] = math.pi
        half[model.i_v] = 0.5 * (hi[model.i_v] - lo[model.i_v])
        half[model.i_omega] = 0.5 * (hi[model.i_omega] - lo[model.i_omega])
        half[md:] = self._theta_range
        self._arrival = prior_arrival(x, half, md, self._theta_info)
        y, avail, allow = step_outputs(model, can, t, s.gnss.period_s, self.period_s, fix, s, x)
        self.gate.start(bool(avail[model.j_azimuth]), jump)
        self.window.append(t, y, avail, allow, x)
        limits = np.full(md, np.inf)
        limits[model.i_phi] = math.pi
        limits[model.i_v] = hi[model.i_v] - lo[model.i_v]
        limits[model.i_omega] = hi[model.i_omega] - lo[model.i_omega]
        self.newest.start(self.window, half, limits, self.envelope.factor, self._theta_range)
        self._status = "ok"
        self.tally.counts["gps_ok"] += 1
        self.propagation.restart(x.tolist(), t, can)
        return self._estimate(x.tolist(), t, "ok", "init")

    def _epoch(self, t: float, fix: FixMeasurement | None) -> StateEstimate:
        """One GNSS epoch at ``t`` (``fix`` None: no usable fix): gate, append, plan, solve, report."""
        win, model, s, can = self.window, self.model, self.settings, self.frontend.can
        h_prev = t - float(win.t[-1])
        self._watch_stop(float(win.t[-1]), t)
        x_pred = np.array(advance(model, win.x[-1].tolist(), float(win.t[-1]), t, can, s.can.max_gap_s))
        self.gate.drove(abs(float(x_pred[model.i_v])) * h_prev)
        i_e, i_n = model.position
        status: GpsStatus = "outage"
        if fix is not None:
            status = "ok" if self.gate.passes(fix, x_pred[i_e], x_pred[i_n]) else "rejected"
            if self.gate.locked_out(t):  # rejected by the gate or the solver, or taken by a solution that stays away
                self.tally.count(
                    "gate_resets", "fixes not followed for %.0f s: restarting at the newest fix", GATE_RESET_S
                )
                return self._start_over(fix, x_pred)
            if status == "rejected" and self.gate.reacquire(fix, x_pred[i_e], x_pred[i_n]):
                self.tally.count(
                    "reacquired", "GNSS re-acquired: %d rejected fixes agreeing against the prediction", REACQUIRE_FIXES
                )
                return self._start_over(fix, x_pred)
        used = self._timed(fix) if fix is not None and status == "ok" else None
        y, avail, allow = step_outputs(model, can, t, h_prev, self.period_s, used, s, x_pred)
        # the previous step's CAN outputs again, now that the samples of its second half-interval are in
        i = len(win) - 1
        t_before = float(win.t[i - 1]) if i else float(win.t[i]) - self.period_s
        previous = (win.y[i], win.avail[i], win.allow[i])
        can_outputs(model, can, float(win.t[i]), 0.5 * (t_before + win.t[i]), win.t[i] + 0.5 * h_prev, s, previous)
        win.append(t, y, avail, allow, x_pred)
        for j in range(max(len(win) - 2, 1), len(win)):
            self._step_motion(j)
        self.tally.counts[STATUS_COUNTERS[status]] += 1
        self._status = status
        plan = plan_window(win.gps, win.t, self.period_s, self.policy)
        if plan.drop:
            assert self._arrival is not None  # set at the start
            drop = min(plan.drop, len(win) - 1)
            self._arrival = arrival_update(
                model,
                win,
                drop,
                self._arrival,
                self.solve.Q,
                self.solve.q_caps,
                self._step_jac,
                self._theta_range,
                self.policy.theta_drift,
                self.envelope.factor,
            )
            if not self._unsolved:
                self._learn_bounds(win.x[:drop], slice(0, drop))
        self._merge_offsets(win.apply(plan))
        if self.defer_solves:
            self.tally.counts["deferred_epochs"] += 1
            self._unsolved = True
            self.gate.done(t, status, status == "ok" and bool(win.avail[-1, model.j_azimuth]))
            return self._estimate(win.x[-1].tolist(), t, status, "degraded")
        shift = None if plan.merge or self._unsolved else plan.drop
        self._unsolved = False
        if self.solve_aside:
            if self._aside is None:
                self._aside = ThreadPoolExecutor(1, thread_name_prefix="mhe-solve")
            self._pending = (t, status, self._aside.submit(self._solve, shift))
            self.unsettled = True
            self.propagation.restart(win.x[-1].tolist(), t, can)
            return self._estimate(win.x[-1].tolist(), t, status, "aside")
        x_new, mode = self._solve(shift)
        return self._solved(t, status, x_new, mode)

    def settle(self) -> None:
        """Wait for the epoch solved aside (``solve_aside``), if any, and apply its solution."""
        self._collect(wait=True)

    def _collect(self, wait: bool) -> None:
        """Apply the solution of the epoch solved aside (``solve_aside``) once it is done, or wait for it
        (``wait``: the window is about to change); the newest state is then propagated anew over the CAN samples
        since (:meth:`Propagation.restart`)."""
        if self._pending is None or not (wait or self._pending[2].done()):
            return
        t, status, future = self._pending
        self._pending = None
        x_new, mode = future.result()
        self.settled(self._solved(t, status, x_new, mode))

    def _solved(self, t: float, status: GpsStatus, x_new: NDArray[np.float64], mode: str) -> StateEstimate:
        """The epoch at ``t`` whose window was solved to ``x_new`` (``mode``): a fix the solver cannot take
        rejected, bounds learned, the gate told, the newest state and its propagation restarted; its estimate."""
        win, model, can = self.window, self.model, self.frontend.can
        if mode == "predict" and status == "ok":
            # the window cannot take the fix even with widened bounds: an outlier the gate let in; drop it
            self.tally.count("rejected_by_solver", "fix at %.2f rejected: no trajectory of the window reaches it", t)
            win.avail[-1, list(model.gps_outputs)] = False
            status = self._status = "rejected"
            self.tally.counts["gps_ok"] -= 1
            self.tally.counts["gps_rejected"] += 1
            x_new, mode = self._solve(None)
        if mode == "predict":
            self.tally.count(
                "fallbacks", "MHE solve failed %d times: the model prediction", self.policy.max_retries + 1
            )
        elif mode == "mhe-widened":
            # the data broke a bound: learn it now, from the residuals of the solution that fits them
            self._learn_bounds(x_new, slice(0, len(win)))
        miss = (0.0, 0.0)
        if status == "ok":
            e = output_residuals(model, x_new[-1:], win.y[-1:])[0]
            miss = (float(e[model.j_position[0]]), float(e[model.j_position[1]]))
        self.gate.done(t, status, status == "ok" and bool(win.avail[-1, model.j_azimuth]), miss)
        win.x[:] = x_new
        self.newest.epoch(win, self.solve.Q, self.envelope.factor, self._theta_range)
        self.propagation.restart(x_new[-1].tolist(), t, can)
        return self._estimate(x_new[-1].tolist(), t, status, mode)

    def _fill(self, fix: FixMeasurement) -> StateEstimate | None:
        """A fix that came after its epoch was declared missed (``Epoch.fills``), put in that epoch's step as a
        late fix: moved to the step's time along the step's state, through the gate, the window solved again (or
        left unsolved under ``defer_solves``) and the newest state propagated anew over the CAN samples since; the
        estimate of the step. None, counted ``fixes_after_missed``, where the step has left the window (or was
        merged away), has a fix, or the gate or the solver turns the fix away."""
        win, model = self.window, self.model
        near = np.flatnonzero(np.abs(win.t - fix.t) <= SAME_EPOCH * self.period_s)
        j = int(near[-1]) if near.size and not win.gps[near[-1]] else -1
        why = "its step is no longer in the window"
        if j >= 0:
            x = win.x[j]
            fix = fix_moved(model, fix, x, float(win.t[j]))
            if not self.gate.passes(fix, *x[list(model.position)]):
                why, j = "rejected by the gate", -1
        if j < 0:
            self.tally.count("fixes_after_missed", "GNSS fix of a missed epoch dropped: %s", why)
            return None
        saved = (win.y[j].copy(), win.avail[j].copy(), win.allow[j].copy())
        out = (saved[0].copy(), saved[1].copy(), saved[2].copy())
        fix_outputs(model, self._timed(fix), self.period_s, self.settings, out, x)
        win.y[j], win.avail[j], win.allow[j] = out
        mode = "degraded"
        if not self.defer_solves:
            x_new, mode = self._solve(None)
            if mode == "predict":
                win.y[j], win.avail[j], win.allow[j] = saved
                self.tally.count("fixes_after_missed", "GNSS fix of a missed epoch dropped: %s", "the solve failed")
                return None
            win.x[:] = x_new
            self.newest.epoch(win, self.solve.Q, self.envelope.factor, self._theta_range)
            self.propagation.restart(x_new[-1].tolist(), float(win.t[-1]), self.frontend.can)
        self._unsolved = self.defer_solves
        if j == len(win) - 1:
            self._status = "ok"
            self.gate.done(fix.t, "ok", bool(win.avail[j, model.j_azimuth]))
        self.tally.counts["missed_epochs_filled"] += 1
        return self._estimate(win.x[j].tolist(), fix.t, "ok", mode)

    def _timed(self, fix: FixMeasurement) -> FixMeasurement:
        """``fix`` with its speed over ground's sigma grown by the error of its uncertain time while the car
        accelerates (:meth:`~sumhe.frontend.stream.FrontEnd.timed_speed_sigma_mps`, as the Kalman family weighs
        it)."""
        if fix.speed_mps is None:
            return fix
        return dataclasses.replace(fix, speed_sigma_mps=self.frontend.timed_speed_sigma_mps(fix))

    def _watch_stop(self, t0: float, t1: float) -> None:
        """Collect the CAN yaw rates of a standstill over the step (``t0``, ``t1``]; when the car drives off, tell
        the arrival cost once what the stop measured of the bias (:mod:`sumhe.frontend.standstill`)."""
        s = self.settings
        stop = self._stops.step(self.frontend.can, t0, t1, 0.5 * s.can.speed_quantum_mps, s.can.max_gap_s)
        if stop is None or self.model.i_bias is None:
            return
        assert self._arrival is not None  # set at the start
        bias = bias_at_rest(stop, s.can, s.estimator.r_cap_sigmas, self.policy.rest_bias_rps)
        if bias is None:
            self.tally.count(
                "stops_unused",
                "a standstill's %d yaw rates spread by %.3f deg/s: not taken as the bias",
                stop.n,
                math.degrees(stop.spread),
                level=logging.INFO,
            )
            return
        self._arrival = measured(self._arrival, self.model.i_bias, *bias)
        self.tally.counts["stops_used"] += 1

    def _learn_bounds(self, x: NDArray[np.float64], steps: slice) -> None:
        """Show the envelope (:mod:`.envelope`) the residual-to-allowance ratios of the window's ``steps`` at the
        trajectory ``x`` (theirs)."""
        if self.policy.learn_bounds:
            win = self.window
            ratio = np.abs(output_residuals(self.model, x, win.y[steps])) / win.allow[steps]
            self.envelope.observe(np.where(win.avail[steps], ratio, np.nan))

    def _solve(self, shift: int | None) -> tuple[NDArray[np.float64], str]:
        """Solve the window. While its newest step has no fix, the CAN scale states (speed scale, yaw-rate gain)
        are held where the last window solved with one left them: steps without a fix carry no information on
        them, but their state-noise terms shrink as the scales grow (a larger gain makes the yaw rate behind the
        same CAN samples smaller, its changes cheaper), so through a long outage's turns the solution drifted with
        the turns (a realistic simulated offroad drive, seed 11: the gain 0.996 -> 1.15 in 25 s of a 55 s outage,
        the truth's 0.967, the azimuth 48 deg off; the Kalman peers' gain does not move without a measurement)."""
        assert self._arrival is not None  # set at the start
        win, arrival = self.window, self._arrival
        if self._scales is not None and not win.gps[-1]:
            for i, value, bound in zip(self._scale_states, self._scales, self._hold_bounds, strict=True):
                arrival = measured(arrival, i, value, bound)
        x_new, mode = self.solve.solve(win, arrival, self.period_s, shift, self.envelope.factor)
        if win.gps[-1] and mode != "predict":
            self._scales = x_new[-1, self._scale_states].tolist()
        return x_new, mode

    def _step_motion(self, j: int) -> None:
        """The offset and CAN noise bound of the transition into step ``j`` from the CAN data between it and the
        step before, the yaw rate between the two steps' own CAN outputs (:mod:`.preintegration`; none across a gap
        in the CAN data)."""
        win, model, yaw = self.window, self.model, self.model.j_can_yaw_rate
        # in plain floats: 0.8 us, where a numpy array of them took 4 us (two calls an epoch)
        ends = [[math.nan, float(win.y[i, yaw]) if win.avail[i, yaw] else math.nan] for i in (j - 1, j)]
        motion = step_motion(
            model, self.frontend.can, float(win.t[j - 1]), float(win.t[j]), win.x[j - 1], win.x[j], self.settings, ends
        )
        offset, bound = motion if motion is not None else (0.0, np.nan)
        win.offset[j] = offset
        win.q_step[j, : self.model.n_dynamic] = bound

    def _merge_offsets(self, merged: list[int]) -> None:
        """The offsets of the steps whose transitions now span merged steps: what the current trajectory moved
        beyond one trapezoidal step over the merged span (the CAN data of the steps merged away: a varying yaw
        rate is not linear over a long step), so the merge does not move the solution."""
        win, md = self.window, self.model.n_dynamic
        for j in merged:
            pred = self.model.transition(win.x[j - 1], win.x[j], float(win.t[j] - win.t[j - 1]))
            win.offset[j, :md] = win.x[j, :md] - np.array(pred[:md])

    def _part_bounds(self, x: list[float], t: float, h: float) -> tuple[NDArray[np.float64], list[float]]:
        """The bounds a CAN-rate estimate ``x`` at ``t``, ``h`` s after the newest step, is carried with, as the
        epoch's step is (:mod:`.newest`): the state bounds of that part of a step (the CAN data's where it bounds a
        state, :func:`~sumhe.estimator.mhe.preintegration.part_bound`, else the vehicle's limits over ``h``), and
        the bounds of the CAN speed and yaw rate (m/s, rad/s) measured at ``x`` (one sample's allowance, with what
        a model without the speed scale or yaw-rate bias adds, times the envelope's factor, as the window's
        outputs; ``inf``, none, across a gap in the CAN data)."""
        model = self.model
        caps = self.solve.q_caps * (h / self.period_s) ** self._q_power
        speed = abs(x[model.i_v])
        mean_speed = 0.5 * (abs(float(self.window.x[-1, model.i_v])) + speed)
        bound = part_bound(model, self.frontend.can, float(self.window.t[-1]), t, mean_speed, self.settings)
        if bound is None:
            return caps, [math.inf, math.inf]
        (speed_allow, per_mps), yaw_allow = self._can_sample_allow
        factor = self.envelope.factor
        speed_bound = (speed_allow + per_mps * speed) * float(factor[model.j_can_speed])
        return np.fmin(bound, caps), [speed_bound, yaw_allow * float(factor[model.j_can_yaw_rate])]

    def _estimate(self, x: list[float], t: float, status: GpsStatus, mode: str) -> StateEstimate:
        """The estimate of the state ``x`` at ``t`` (the newest step's, or the newest solution moved on by CAN), with
        the newest state's bound box and covariance carried to it (:mod:`.newest`)."""
        model, win = self.model, self.window
        h = t - float(win.t[-1])
        (bound_east, bound_north), spread = self.newest.at(x, h, *self._part_bounds(x, t, max(h, 0.0)))
        i_e, i_n = model.position
        return StateEstimate(
            t, float(x[i_e]), float(x[i_n]), float(x[model.i_phi]) % (2.0 * math.pi), float(x[model.i_v]),
            float(x[model.i_omega]), status, mode, bound_east, bound_north, len(win), self.elapsed_ms(), spread
        )  # fmt: skip
