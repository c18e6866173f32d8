"""The batch state-uniform (SU) estimator: MAP (000 (15)-(17)) made well-posed, and its LP start point.

Pipeline for one window of samples (a time-ordered list of :class:`~sumhe.messages.GnssFix` and
:class:`~sumhe.messages.CanSample`):

1. :func:`~sumhe.estimator.grid.build_grid`: GNSS epochs as steps, outage gaps filled, CAN on the grid,
   per-epoch error allowances. :func:`~sumhe.estimator.bounds.noise_bounds`: floors and caps of q and r.
   The model (:mod:`sumhe.model.su`): su5 or su7 (000 (19)-(20)), optionally with the CAN yaw-rate bias and
   speed scale as window-constant parameters (Theta of 000 (2)), discretised by the trapezoidal twin of
   (19) (``discretisation``) and, for su7, with antenna 2 swinging about antenna 1 in turns
   (``antenna_lever``).
2. Start point (000 sec. 4.2): the linear SU program (21)-(22) with OSQP and 001's retry rule
   (:mod:`sumhe.estimator.lp`); if even the widened LP fails, the fixes interpolated in time.
   :func:`estimate_lp` returns the LP as an estimator of its own.
3. Stage 1, the MAP of (q, r) over the feasible set S of (14) with the box prior (11) from the derived
   floors and caps, by ``settings.estimator.batch.objective``:
   ``"log"``: the paper's (15), ``sum ln q_i + sum (K_j/T) ln r_j`` (K_j: outputs of kind j present);
   ``"linear"``: ``sum q_i/qcap_i + sum (K_j/T) r_j/rcap_j`` (001's linearised MAP, normalised);
   ``"caps"``: no stage 1, q and r are their caps (a pure set-membership estimate; the centre always runs).
4. Stage 2, the reported point (``settings.estimator.batch.centre``). The objective depends on q and r only, so every
   trajectory in S(q, r) is a MAP estimate; ``"lsq"`` reports the centre of S(q', r'), with q and r fixed
   at the stage-1 values widened by ``centre_margin`` (``q' = (1 + margin) q``), as the point minimising
   ``sum (w_ti / q'_i)^2 + sum (e_kj / r'_j)^2``: the constrained least-squares smoother whose weights are
   the variances ``q^2/3``, ``r^2/3`` of the uniform noises. ``"none"`` reports the stage-1 point.
5. On request, the extent of the newest position over S(q', r'): min and max of its east and north
   (four more solves with a linear objective; a local optimum, exact when S is convex near the solution).

One :class:`~sumhe.estimator.problem.SuNlp` per model and window size serves every stage (objective
weights and bounds are parameters; fixed q, r are variables with equal bounds). When IPOPT finds a stage
infeasible, the caps of q and r are widened by ``widen_factor`` and the stages rerun (algorithm 3.3 of 001, at most
``max_widenings`` times); before the first solve they are widened as often as it takes to hold the start point
(:meth:`_Window.widenings_to_hold`), so that IPOPT starts feasible. If IPOPT fails otherwise, the result carries
the last good point (stage 1, else the start point) with ``success=False`` and the IPOPT status. See
``docs/formulation.md`` for every choice against the paper and its measured effect on the protocol
(:mod:`sumhe.bench.protocol`).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.errors import SolverError
from sumhe.estimator.bounds import NoiseBounds, noise_bounds, widen_caps
from sumhe.estimator.grid import Grid, build_grid
from sumhe.estimator.lp import LpSolution, interpolated_start, solve_lp
from sumhe.estimator.problem import NlpSolution, SuNlp, build_nlp
from sumhe.geo import LocalFrame
from sumhe.messages import Sample
from sumhe.model.su import (
    AZIMUTH_OFFSET_STATE,
    BIAS_STATE,
    GAIN_STATE,
    LEVER_STATE,
    SCALE_STATE,
    SuModel,
    antenna_distance_residual,
    output_residuals,
    state_residuals,
    su_model,
)
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)

WEIGHTS = {"log": (1.0, 0.0, 0.0), "linear": (0.0, 1.0, 0.0)}
CENTRE_WEIGHTS = (0.0, 0.0, 1.0)
INFEASIBLE = ("Infeasible_Problem_Detected", "Restoration_Failed")
NO_WEIGHTS = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SuResult:
    """A batch SU estimate on the window's step grid.

    ``states`` (N x m) in the local ``frame`` (positions m, phi rad clockwise from north, v m/s, omega rad/s
    anticlockwise, bias rad/s, scale 1). ``q`` (at the reference step ``bounds.h_ref``) and ``r`` are the
    estimated noise bounds in the units of their state/output (NaN where the method does not estimate one).
    ``extent`` is (east_min, east_max, north_min, north_max) of the newest position, m, when requested.
    Times in s: ``solve_time_s`` is the whole call, ``ipopt_time_s`` the NLP solves, ``lp_time_s`` the LP.
    """

    t: NDArray[np.float64]
    states: NDArray[np.float64]
    state_names: tuple[str, ...]
    q: NDArray[np.float64]
    r: NDArray[np.float64]
    output_names: tuple[str, ...]
    method: str
    status: str
    success: bool
    solve_time_s: float
    ipopt_time_s: float
    lp_time_s: float
    iterations: int
    lp_retries: int
    widenings: int
    gps: NDArray[np.bool_]
    frame: LocalFrame
    bounds: NoiseBounds
    extent: tuple[float, float, float, float] | None = None

    def state(self, name: str) -> NDArray[np.float64]:
        """One state over the window by name (e.g. ``"px"``, ``"phi"``, ``"yaw_rate_bias"``)."""
        return self.states[:, self.state_names.index(name)]

    @property
    def east(self) -> NDArray[np.float64]:
        """East of the (first) antenna, m."""
        return self.states[:, 0]

    @property
    def north(self) -> NDArray[np.float64]:
        """North of the (first) antenna, m."""
        return self.states[:, 1]


ModelArgs = tuple[str, bool, bool, str, float, bool, bool, bool, bool, float, float]


def model_args(settings: EstimationSettings, streaming: bool = True) -> ModelArgs:
    """The arguments of :func:`~sumhe.model.su.su_model` the settings select (``model``, ``yaw_rate_bias``,
    ``speed_scale``, ``discretisation``, the lever arm, ``gps_speed``, and for su5 the yaw-rate gain, azimuth
    offset and antenna lever-arm states and the antenna's lever arm): hashable, a cache key too.

    The yaw-rate gain, the azimuth offset and the forward lever arm are states only for the streaming estimators
    (``streaming``), which carry them over the whole drive in their arrival cost and hold them to their nominal
    values by a prior: within one batch window a steady turn cannot tell the gain from the bias, nor a straight
    road the lever arm from a shift of the whole trajectory, and without a prior they would run to their bounds
    (the batch windows take the lever arm as configured)."""
    e, su5 = settings.estimator, settings.estimator.model == "su5"
    streaming_su5 = su5 and streaming
    forward_state = e.antenna_offset and streaming_su5
    return (
        e.model,
        e.yaw_rate_bias,
        e.speed_scale,
        e.discretisation,
        lever_m(settings),
        settings.gnss.use_speed,
        e.yaw_rate_gain and streaming_su5,
        e.azimuth_offset and streaming_su5,
        forward_state,
        settings.vehicle.antenna_forward_m if su5 and not forward_state else 0.0,
        settings.vehicle.antenna_left_m if su5 else 0.0,
    )


def model_for(settings: EstimationSettings, streaming: bool = True) -> SuModel:
    """The SU model the settings select (:func:`model_args`)."""
    return su_model(*model_args(settings, streaming))


def lever_m(settings: EstimationSettings) -> float:
    """The antenna-2 lever arm of su7 (m): the antenna distance, or 0 for the paper's rigid translation."""
    return settings.vehicle.antenna_distance_m if settings.vehicle.antenna_lever else 0.0


def state_box(model: SuModel, n_steps: int, settings: EstimationSettings) -> tuple[NDArray, NDArray]:
    """Bounds (11) on every x_t (N x m): speed, yaw rate, the limits of the sensor and installation states;
    positions, phi free."""
    lo = np.full(model.n_states, -np.inf)
    hi = np.full(model.n_states, np.inf)
    can, vehicle = settings.can, settings.vehicle
    forward, reach = vehicle.antenna_forward_m, vehicle.antenna_forward_range_m
    limits = {
        "v": (-vehicle.max_reverse_speed_mps, vehicle.max_speed_mps),
        "omega": (-vehicle.max_yaw_rate_rps, vehicle.max_yaw_rate_rps),
        BIAS_STATE: (-can.yaw_rate_bias_max_rps, can.yaw_rate_bias_max_rps),
        SCALE_STATE: (1.0 - can.speed_scale_max, 1.0 + can.speed_scale_max),
        GAIN_STATE: (1.0 - can.yaw_rate_gain_max, 1.0 + can.yaw_rate_gain_max),
        AZIMUTH_OFFSET_STATE: (-settings.gnss.azimuth_offset_max_rad, settings.gnss.azimuth_offset_max_rad),
        LEVER_STATE: (forward - reach, forward + reach),
    }
    for name, (a, b) in limits.items():
        if name in model.states:
            lo[model.index(name)], hi[model.index(name)] = a, b
    return np.tile(lo, (n_steps, 1)), np.tile(hi, (n_steps, 1))


def start_states(
    lp: LpSolution, model: SuModel, origin: NDArray[np.float64], settings: EstimationSettings
) -> NDArray[np.float64]:
    """The NLP start X0 (000 sec. 4.2) from the LP: positions, its azimuth input, CAN speed and yaw rate."""
    N = len(lp.phi)
    x = np.zeros((N, model.n_states))
    n_pos = 2 * model.antennas
    x[:, :n_pos] = lp.p - np.tile(origin, model.antennas)
    x[:, model.i_phi], x[:, model.i_v], x[:, model.i_omega] = lp.phi, lp.speed, lp.yaw_rate
    x[:, model.n_dynamic :] = nominal_parameters(model, settings)
    return x


def nominal_parameters(model: SuModel, settings: EstimationSettings) -> NDArray[np.float64]:
    """The parameters Theta (the states after the dynamic ones) of a car and sensors as configured: no bias, unit
    speed scale and yaw-rate gain, no azimuth offset, the antenna where ``[vehicle]`` says."""
    nominal = {
        SCALE_STATE: 1.0,
        GAIN_STATE: 1.0,
        LEVER_STATE: settings.vehicle.antenna_forward_m,
    }
    return np.array([nominal.get(name, 0.0) for name in model.states[model.n_dynamic :]])


def _centred(grid: Grid, model: SuModel, origin: NDArray[np.float64]) -> NDArray[np.float64]:
    shift = np.zeros(model.n_outputs)
    shift[: 2 * model.antennas] = np.tile(origin, model.antennas)
    return np.where(grid.avail, grid.y - shift, 0.0)


def _start_needs(
    model: SuModel, grid: Grid, bounds: NoiseBounds, x: NDArray, y: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """q, r that make the start point ``x`` feasible."""
    w = np.abs(state_residuals(model, x, grid.h)) / bounds.q_scale
    e = np.where(grid.avail, np.abs(output_residuals(model, x, y)) / bounds.r_scale, 0.0)
    return w.max(axis=0), e.max(axis=0)


def _start_noise(
    model: SuModel, grid: Grid, bounds: NoiseBounds, x: NDArray, y: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """q, r that make the start point feasible, clipped into their boxes."""
    q, r = _start_needs(model, grid, bounds, x, y)
    return np.clip(q, bounds.q_lo, bounds.q_hi), np.clip(r, bounds.r_lo, bounds.r_hi)


class _Window:
    """One window's NLP inputs; ``solve`` runs one stage (objective weights, fixed or free q and r)."""

    def __init__(self, nlp: SuNlp, model: SuModel, grid: Grid, bounds: NoiseBounds, settings: EstimationSettings):
        self.nlp, self.model, self.grid, self.bounds, self.settings = nlp, model, grid, bounds, settings
        self.origin = np.mean(grid.y[grid.gps, :2], axis=0)
        self.y = _centred(grid, model, self.origin)
        self.lbx, self.ubx = state_box(model, grid.n_steps, settings)
        self.kw = grid.avail.sum(axis=0) / (grid.n_steps - 1)
        self.ipopt_time = 0.0
        self.iterations = 0

    def solve(
        self,
        x0: NDArray,
        q: tuple[NDArray, NDArray, NDArray],
        r: tuple[NDArray, NDArray, NDArray],
        weights: tuple[float, float, float],
        c_ext: tuple[float, float] = (0.0, 0.0),
    ) -> NlpSolution:
        """One IPOPT solve; ``q`` and ``r`` are (start, lower, upper)."""
        g, b, s = self.grid, self.bounds, self.settings
        p = self.nlp.params(
            self.y,
            g.avail,
            b.r_scale,
            b.q_scale,
            g.h,
            self.kw,
            b.q_hi,
            b.r_hi,
            weights,
            c_ext,
            s.vehicle.antenna_distance_m,
        )
        x0 = np.clip(x0, self.lbx, self.ubx)
        sol = self.nlp.solve(x0, q[0], r[0], p, self.lbx, self.ubx, q[1:], r[1:], s.vehicle.antenna_tolerance_m2)
        self.ipopt_time += sol.time_s
        self.iterations += sol.iterations
        if not sol.success:
            log.warning("SU NLP stage %s: IPOPT %s after %d iterations", weights, sol.status, sol.iterations)
        return sol

    def widenings_to_hold(self, x0: NDArray[np.float64], factor: float) -> int:
        """How many widenings by ``factor`` make the caps of q and r hold the start point ``x0`` (clipped into the
        state box), from where IPOPT starts feasible. Started outside the caps, IPOPT ran the dual infeasibility of
        some windows of realistic drives up to 1e14 within a dozen iterations, then spent minutes in MUMPS on each
        before it declared the problem infeasible (or, widened once, solved it)."""
        q, r = _start_needs(self.model, self.grid, self.bounds, np.clip(x0, self.lbx, self.ubx), self.y)
        ratio = max(float(np.max(q / self.bounds.q_hi)), float(np.max(r / self.bounds.r_hi)))
        return math.ceil(math.log(ratio) / math.log(factor)) if 1.0 < ratio < math.inf else 0


def estimate_batch(
    samples: Sequence[Sample],
    settings: EstimationSettings | None = None,
    *,
    frame: LocalFrame | None = None,
    extent: bool = False,
) -> SuResult:
    """Batch SU estimate of a window of samples (see the module docstring for the stages).

    ``frame`` is the local frame of the result (default: at the first valid fix); ``extent`` asks for the
    extent of the newest position. Raises EstimatorInputError for unusable input; a failed solve is not an
    exception but a result with ``success=False`` (and the LP start, or the interpolated fixes, as states).
    """
    t_start = time.perf_counter()
    settings = settings or EstimationSettings()
    model = model_for(settings, streaming=False)
    grid = build_grid(samples, model, settings, frame)
    bounds = noise_bounds(model, grid, settings, lever_m(settings))
    nlp = build_nlp(
        *model_args(settings, streaming=False),
        grid.n_steps,
        settings.estimator.batch.ipopt_max_iter,
        settings.estimator.batch.ipopt_tol,
    )
    win = _Window(nlp, model, grid, bounds, settings)
    try:
        lp = solve_lp(grid, model, bounds, settings, win.origin)
    except SolverError as e:
        log.warning("%s; the NLP starts from the interpolated fixes", e)
        lp = interpolated_start(grid, model, settings)
    x0 = start_states(lp, model, win.origin, settings)
    most, factor = settings.estimator.batch.max_widenings, settings.estimator.widen_factor
    first = min(most, win.widenings_to_hold(x0, factor))
    if first:
        log.info("SU NLP: the start point needs the caps of q and r widened by %g", factor**first)
        win.bounds = widen_caps(win.bounds, factor**first)
    for widenings in range(first, most + 1):
        stages = _stages(win, x0)
        if stages.success or stages.status not in INFEASIBLE or widenings == most:
            break
        log.info("SU NLP %s: widening the caps of q and r by %g", stages.status, factor)
        win.bounds = widen_caps(win.bounds, factor)
    x, q, r, q2, r2 = stages.x, stages.q, stages.r, stages.q_centre, stages.r_centre
    status, success = stages.status, stages.success
    box = _extent(win, x, q2, r2) if extent and success else None
    x = x.copy()
    x[:, : 2 * model.antennas] += np.tile(win.origin, model.antennas)
    return SuResult(
        t=grid.t,
        states=x,
        state_names=model.states,
        q=q,
        r=r,
        output_names=model.outputs,
        method="nlp",
        status=status,
        success=success,
        solve_time_s=time.perf_counter() - t_start,
        ipopt_time_s=win.ipopt_time,
        lp_time_s=lp.time_s,
        iterations=win.iterations,
        lp_retries=lp.retries,
        widenings=widenings,
        gps=grid.gps,
        frame=grid.frame,
        bounds=win.bounds,
        extent=box,
    )


@dataclass(frozen=True)
class _Stages:
    """What the stages of one attempt produced: the reported states, the MAP (q, r), the (q, r) of the
    centre stage, and the status of the last solve that ran."""

    x: NDArray[np.float64]
    q: NDArray[np.float64]
    r: NDArray[np.float64]
    q_centre: NDArray[np.float64]
    r_centre: NDArray[np.float64]
    status: str
    success: bool


def _stages(win: _Window, x0: NDArray[np.float64]) -> _Stages:
    """Stage 1 (MAP of q, r, unless ``objective = "caps"``) and stage 2 (the centre) from the start ``x0``.

    A failed stage reports the last good point: stage 1's, else the start point."""
    s, b = win.settings, win.bounds
    x, status, success = x0, "Solve_Succeeded", True
    if s.estimator.batch.objective == "caps":
        q, r = b.q_hi, b.r_hi
        q2, r2 = q, r
    else:
        q0, r0 = _start_noise(win.model, win.grid, b, x0, win.y)
        sol = win.solve(x0, (q0, b.q_lo, b.q_hi), (r0, b.r_lo, b.r_hi), WEIGHTS[s.estimator.batch.objective])
        if not sol.success:
            return _Stages(x0, q0, r0, q0, r0, sol.status, False)
        x, q, r = sol.x, sol.q, sol.r
        q2, r2 = q * (1.0 + s.estimator.batch.centre_margin), r * (1.0 + s.estimator.batch.centre_margin)
    if s.estimator.batch.centre == "lsq" or s.estimator.batch.objective == "caps":
        sol = win.solve(x, (q2, q2, q2), (r2, r2, r2), CENTRE_WEIGHTS)
        status, success = sol.status, sol.success
        if sol.success:
            x = sol.x
    return _Stages(x, q, r, q2, r2, status, success)


def _extent(win: _Window, x: NDArray, q: NDArray, r: NDArray) -> tuple[float, float, float, float] | None:
    """(east_min, east_max, north_min, north_max) of the newest position over S(q, r), in the frame (m)."""
    out = []
    for c_ext, sign in (((1.0, 0.0), 1.0), ((-1.0, 0.0), -1.0), ((0.0, 1.0), 1.0), ((0.0, -1.0), -1.0)):
        sol = win.solve(x, (q, q, q), (r, r, r), NO_WEIGHTS, c_ext)
        if not sol.success:
            return None
        axis = 0 if c_ext[0] else 1
        out.append(sign * sol.f + win.origin[axis])
    return out[0], out[1], out[2], out[3]


def estimate_lp(
    samples: Sequence[Sample],
    settings: EstimationSettings | None = None,
    *,
    frame: LocalFrame | None = None,
) -> SuResult:
    """The linear SU estimate alone (000 (21)-(22) as 001's LP): positions from the LP, azimuth from its
    input phi-hat, speed and yaw rate from CAN; q and r only for the position states and outputs."""
    t_start = time.perf_counter()
    settings = settings or EstimationSettings()
    model = model_for(settings, streaming=False)
    grid = build_grid(samples, model, settings, frame)
    bounds = noise_bounds(model, grid, settings, lever_m(settings))
    origin = np.mean(grid.y[grid.gps, :2], axis=0)
    lp = solve_lp(grid, model, bounds, settings, origin)
    x = start_states(lp, model, np.zeros(2), settings)
    n_pos = 2 * model.antennas
    q = np.full(model.n_states, np.nan)
    r = np.full(model.n_outputs, np.nan)
    q[:n_pos], r[:n_pos] = lp.q, lp.r
    return SuResult(
        t=grid.t,
        states=x,
        state_names=model.states,
        q=q,
        r=r,
        output_names=model.outputs,
        method="lp",
        status=lp.status,
        success=True,
        solve_time_s=time.perf_counter() - t_start,
        ipopt_time_s=0.0,
        lp_time_s=lp.time_s,
        iterations=lp.iterations,
        lp_retries=lp.retries,
        widenings=0,
        gps=grid.gps,
        frame=grid.frame,
        bounds=bounds,
    )


def antenna_distance_error(result: SuResult, distance_m: float) -> NDArray[np.float64]:
    """``|dist^2 - d^2|`` (m^2) per step of an su7 result: the left side of (23)."""
    return np.abs(antenna_distance_residual(result.states.T) - distance_m**2)
