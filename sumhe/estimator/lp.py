"""The simplified linear SU model (000 (21)-(22)) solved as the linear program of 001 (15)-(19) with OSQP.

State: the antenna positions only; input: the velocity ``v_t (sin phi_t, cos phi_t)`` from CAN speed and an
azimuth ``phi_t`` that is measured where GNSS has one (the antenna pair's xi for su7; the receiver's
heading/course, else the direction of the step to the next fix, for su5) and dead-reckoned with the CAN yaw
rate elsewhere, ``phi_t = phi_{t-1} - h omega_{t-1}`` (backwards before the first measured one). With the
``trapezoid`` discretisation the step's mean yaw rate, speed and azimuth replace the values at t-1.

The LP, over ``z = [p_0 .. p_{N-1}, q, r]``::

    min  sum q_i + sum r_j                              (001 (15): the linearised MAP objective)
    s.t. |p_t - p_{t-1} - h_t u_{t-1}| <= q S_t          (state rows, 001 (18) A11/A12)
         |y_k - p_k| <= r C_k     for available fixes   (output rows A21/A22; missing fixes: no rows)
         0 <= q <= qbar, 0 <= r <= rbar                 (001 (19))

OSQP solves QPs; an LP is a QP with ``P = 0``, on which its ADMM converges slowly and, as every trajectory of
an optimal face is optimal, to an arbitrary one. We add ``P = eps * D'D``, ``eps = lp_regularisation``,
where ``D z`` are the state residuals ``p_t - p_{t-1} - h u``: among (nearly) optimal points OSQP then
returns the one with the smallest squared process noise (the smoothest), and the LP value moves by a
negligible ``O(eps)``. If the LP fails (OSQP reports primal infeasibility, or does not converge within
``LP_MAX_ITER``, which happens next to the infeasibility boundary), algorithm 3.3 of 001 applies: ``qbar`` and
``rbar`` are widened by ``widen_factor`` and the LP is solved again, at most ``max_widenings`` times.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp
from numpy.typing import NDArray

from sumhe.errors import SolverError
from sumhe.estimator.bounds import NoiseBounds, fill_gaps
from sumhe.estimator.grid import Grid
from sumhe.model.su import SuModel
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)

SOLVED = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)
LP_TOL = 1e-5
LP_MAX_ITER = 20000
LP_MAX_ITER_PRIM_RES = 1e-3
"""An iterate at the iteration limit is still a usable start point when its constraint violation is below
this (m): the NLP starts from it and does not need it to be optimal."""


@dataclass(frozen=True)
class LpSolution:
    """The linear SU estimate: positions (N x 2 per antenna), q, r, the azimuth and speed inputs used."""

    p: NDArray[np.float64]
    q: NDArray[np.float64]
    r: NDArray[np.float64]
    phi: NDArray[np.float64]
    speed: NDArray[np.float64]
    yaw_rate: NDArray[np.float64]
    status: str
    retries: int
    iterations: int
    time_s: float


def azimuth_inputs(grid: Grid, model: SuModel, yaw_rate: NDArray, trapezoid: bool) -> NDArray[np.float64]:
    """phi-hat of (21), unwrapped (rad): measured where GNSS gives one, dead-reckoned with the yaw rate else
    (Euler as in (21), or with the step's mean yaw rate when ``trapezoid``).

    For su5 without heading/course at a fix, the direction to the next fix is used when that step is longer
    than five times the two fixes' error allowances.
    """
    N = grid.n_steps
    j = model.angle_outputs[0]
    known = grid.avail[:, j].copy()
    phi = np.where(known, grid.y[:, j], 0.0)
    if model.antennas == 1:
        d = np.diff(grid.y[:, :2], axis=0)
        dist = np.hypot(d[:, 0], d[:, 1])
        ok = grid.avail[:-1, 0] & grid.avail[1:, 0] & (dist > 5 * (grid.allow[:-1, 0] + grid.allow[1:, 0]))
        use = ok & ~known[:-1]
        phi[:-1][use] = np.arctan2(d[use, 0], d[use, 1])
        known[:-1] |= use
    turn = grid.h * (0.5 * (yaw_rate[:-1] + yaw_rate[1:]) if trapezoid else yaw_rate[:-1])
    if not known.any():
        return np.concatenate([[0.0], -np.cumsum(turn)])
    first = int(np.argmax(known))
    for k in range(first - 1, -1, -1):
        phi[k] = phi[k + 1] + turn[k]
    for k in range(first + 1, N):
        prev = phi[k - 1] - turn[k - 1]
        phi[k] = prev + np.angle(np.exp(1j * (phi[k] - prev))) if known[k] else prev
    return phi


def can_inputs(grid: Grid) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """CAN speed and yaw rate on every step, gaps interpolated (speed from GNSS displacement if CAN has none)."""
    if np.isfinite(grid.can_speed).any():
        speed = fill_gaps(grid.can_speed, grid.t)
    else:
        gps = grid.gps
        tg, pg = grid.t[gps], grid.y[gps, :2]
        vg = np.hypot(*np.diff(pg, axis=0).T) / np.diff(tg)
        speed = fill_gaps(np.interp(grid.t, 0.5 * (tg[1:] + tg[:-1]), vg), grid.t)
    return speed, fill_gaps(grid.can_yaw_rate, grid.t)


def interpolated_start(grid: Grid, model: SuModel, settings: EstimationSettings) -> LpSolution:
    """The fallback start point when the LP fails: fixes interpolated linearly in time (held at the ends),
    with the LP's azimuth, speed and yaw-rate inputs; ``status = "interpolated"``, q and r NaN."""
    n_pos = 2 * model.antennas
    speed, yaw_rate = can_inputs(grid)
    phi = azimuth_inputs(grid, model, yaw_rate, settings.estimator.discretisation == "trapezoid")
    p = np.column_stack([fill_gaps(np.where(grid.avail[:, i], grid.y[:, i], np.nan), grid.t) for i in range(n_pos)])
    nan = np.full(n_pos, np.nan)
    return LpSolution(p, nan, nan, phi, speed, yaw_rate, "interpolated", 0, 0, 0.0)


def displacements(
    model: SuModel, h: NDArray[np.float64], phi: NDArray, speed: NDArray, yaw_rate: NDArray
) -> NDArray[np.float64]:
    """``h u_{t-1}`` of (21) for every step (N-1 x antenna positions, m): the model's own transition of the
    positions driven by the inputs (azimuth phi-hat, CAN speed and yaw rate; bias 0, scale 1)."""
    x = np.zeros((len(phi), model.n_states))
    x[:, model.i_phi], x[:, model.i_v], x[:, model.i_omega] = phi, speed, yaw_rate
    if model.i_scale is not None:
        x[:, model.i_scale] = 1.0
    n_pos = 2 * model.antennas
    return np.array(model.transition(x[:-1].T, x[1:].T, h)[:n_pos]).T


def _lp_matrices(
    grid: Grid, bounds: NoiseBounds, n_pos: int, move: NDArray[np.float64]
) -> tuple[sp.csc_matrix, NDArray, NDArray, sp.csc_matrix, NDArray]:
    """A, l, u rows for the state and output constraints (without the q/r boxes), D and D's target."""
    N = grid.n_steps
    nx = N * n_pos
    nz = nx + 2 * n_pos
    iq, ir = nx, nx + n_pos
    steps = np.arange(1, N)
    rows_a, cols_a, vals_a, lo, hi = [], [], [], [], []
    row = 0
    d_rows, d_cols, d_vals = [], [], []
    target = np.zeros((N - 1) * n_pos)
    for i in range(n_pos):
        s = bounds.q_scale[:, i]
        for t in steps:
            cur, prev = t * n_pos + i, (t - 1) * n_pos + i
            hu = move[t - 1, i]
            k = (t - 1) * n_pos + i
            d_rows += [k, k]
            d_cols += [cur, prev]
            d_vals += [1.0, -1.0]
            target[k] = hu
            for sign, (lo_v, hi_v) in ((-1.0, (-np.inf, hu)), (1.0, (hu, np.inf))):
                rows_a += [row, row, row]
                cols_a += [cur, prev, iq + i]
                vals_a += [1.0, -1.0, sign * s[t - 1]]
                lo.append(lo_v)
                hi.append(hi_v)
                row += 1
        avail = np.flatnonzero(grid.avail[:, i])
        for k in avail:
            y = grid.y[k, i]
            c = bounds.r_scale[k, i]
            for sign, (lo_v, hi_v) in ((-1.0, (-np.inf, y)), (1.0, (y, np.inf))):
                rows_a += [row, row]
                cols_a += [k * n_pos + i, ir + i]
                vals_a += [1.0, sign * c]
                lo.append(lo_v)
                hi.append(hi_v)
                row += 1
    A = sp.csc_matrix((vals_a, (rows_a, cols_a)), shape=(row, nz))
    D = sp.csc_matrix((d_vals, (d_rows, d_cols)), shape=((N - 1) * n_pos, nz))
    return A, np.array(lo), np.array(hi), D, target


def solve_lp(
    grid: Grid, model: SuModel, bounds: NoiseBounds, settings: EstimationSettings, origin: NDArray[np.float64]
) -> LpSolution:
    """Solve the linear SU program with OSQP, retrying with widened ``qbar``, ``rbar`` while infeasible.

    ``origin`` (east, north, m) is subtracted from the positions for the solve (conditioning) and added back.
    Raises SolverError if OSQP fails otherwise or the retries are exhausted.
    """
    t_start = time.perf_counter()
    n_pos = 2 * model.antennas
    speed, yaw_rate = can_inputs(grid)
    trapezoid = settings.estimator.discretisation == "trapezoid"
    phi = azimuth_inputs(grid, model, yaw_rate, trapezoid)
    move = displacements(model, grid.h, phi, speed, yaw_rate)
    shift = np.tile(origin, model.antennas)
    centred = Grid(
        t=grid.t,
        y=np.where(grid.avail, grid.y - np.r_[shift, np.zeros(model.n_outputs - n_pos)], grid.y),
        avail=grid.avail,
        allow=grid.allow,
        can_speed=grid.can_speed,
        can_yaw_rate=grid.can_yaw_rate,
        frame=grid.frame,
    )
    A, lo, hi, D, target = _lp_matrices(centred, bounds, n_pos, move)
    nz = A.shape[1]
    nx = nz - 2 * n_pos
    eps = settings.estimator.batch.lp_regularisation
    P = sp.triu(eps * (D.T @ D), format="csc")
    c = np.zeros(nz)
    c[nx:] = 1.0
    c -= eps * (D.T @ target)
    box = sp.csc_matrix((np.ones(2 * n_pos), (np.arange(2 * n_pos), np.arange(nx, nz))), shape=(2 * n_pos, nz))
    A_all = sp.vstack([A, box], format="csc")
    qbar, rbar = bounds.q_hi[:n_pos].copy(), bounds.r_hi[:n_pos].copy()
    iterations = 0
    for attempt in range(settings.estimator.batch.max_widenings + 1):
        solver = osqp.OSQP()
        solver.setup(
            P,
            c,
            A_all,
            np.r_[lo, np.zeros(2 * n_pos)],
            np.r_[hi, qbar, rbar],
            verbose=False,
            eps_abs=LP_TOL,
            eps_rel=LP_TOL,
            max_iter=LP_MAX_ITER,
            polishing=True,
        )
        res = solver.solve(raise_error=False)
        iterations += int(res.info.iter)
        status = osqp.SolverStatus(res.info.status_val)
        usable = status == osqp.SolverStatus.OSQP_MAX_ITER_REACHED and res.info.prim_res <= LP_MAX_ITER_PRIM_RES
        if status in SOLVED or usable:
            z = res.x
            p = z[:nx].reshape(-1, n_pos) + shift
            log.debug("LP solved after %d retries, %d iterations", attempt, iterations)
            return LpSolution(
                p=p,
                q=z[nx : nx + n_pos],
                r=z[nx + n_pos :],
                phi=phi,
                speed=speed,
                yaw_rate=yaw_rate,
                status=status.name,
                retries=attempt,
                iterations=iterations,
                time_s=time.perf_counter() - t_start,
            )
        log.info(
            "LP %s (attempt %d): widening qbar, rbar by %g", status.name, attempt + 1, settings.estimator.widen_factor
        )
        qbar *= settings.estimator.widen_factor
        rbar *= settings.estimator.widen_factor
    raise SolverError(
        f"linear SU program failed ({status.name}) after {settings.estimator.batch.max_widenings} widenings"
    )
