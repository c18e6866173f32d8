"""The SQP real-time-iteration solver of the window problem (:mod:`sumhe.estimator.mhe.problem`).

``"sqp"``: real-time iteration. The constraints are linearised at the previous solution shifted by one step (the
new step predicted with the newest CAN data), giving one QP per epoch (or a few, by ``estimator.mhe.sqp_iterations``).
Its least-squares objective without the inequalities has block-banded normal equations, solved by a banded
Cholesky factorisation in O(N) (a Kalman smoother's cost); if that point is inside every box it solves the QP (the
problem is convex). Otherwise OSQP solves the QP: the noises are lifted into variables scaled by their bounds,
``w_k = Q_k v_k``, ``e_k = R_k u_k``, every row is divided by its bound, so that ``P`` is fixed but for the arrival
block, every bound is a box on a variable, and only ``A``'s values (the Jacobians from one compiled CasADi
function), ``P``'s arrival block, ``l``, ``u`` and ``q`` change: OSQP is set up once per bucket and re-solved with
``update``, warm-started with its duals shifted by the window's slide.
"""

from __future__ import annotations

import functools
import logging
import time

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import get_lapack_funcs

from sumhe.errors import SolverError
from sumhe.estimator import linalg
from sumhe.estimator.mhe.problem import SolveResult, WindowProblem, residual_functions
from sumhe.model.compiled import NumpyFunction
from sumhe.model.su import SuModel

log = logging.getLogger(__name__)

OSQP_OK = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)
STEP_TOL = 0.01
"""An SQP iteration that turns no azimuth by more than this (rad) ends the iterations: the model is nonlinear
through the azimuth (positions enter linearly, speed bilinearly with the scale), so the real-time iteration does
one QP per epoch unless a transient, e.g. the azimuth found when driving off, needs more."""
BOX_TOL = 1e-9
"""Slack allowed on the boxes when the banded (unconstrained) solution is checked against them."""
BLOCK_STEPS = 25
"""Steps per flat block of the window function's step functions (:func:`_over_steps`): long enough that the map's
call per block is a small part of a block's time, short enough to build in about a millisecond."""
REGULARISATION = 1e-6
"""Added to the normal matrix's diagonal: directions no data fixes (an azimuth at standstill) stay put."""
_PBTRF, _TBTRS = get_lapack_funcs(("pbtrf", "tbtrs"), (np.zeros(1),))
"""LAPACK's banded Cholesky factorisation and banded triangular solve, called directly (without
:func:`scipy.linalg.solveh_banded`'s per-call checks, a fifth of the banded step's time on a 50-step window)."""


def _free(mask: NDArray[np.bool_], lo: NDArray, hi: NDArray) -> tuple[NDArray, NDArray]:
    """``lo``, ``hi`` where ``mask``, (-inf, inf) elsewhere."""
    return np.where(mask, lo, -np.inf), np.where(mask, hi, np.inf)


Pattern = tuple[NDArray[np.int64], NDArray[np.int64]]
"""A sparse matrix's nonzeros: their rows and columns, in CasADi's (column-major) order."""
StepLinearisation = tuple[ca.Function, ca.Function, Pattern, Pattern]
"""One step's ``(xp, xn, theta, h) -> (w, dw.nz)`` and ``(x, theta, y) -> (e, de.nz)``, and the patterns of
``dw`` (in ``(xp, xn, theta)``) and ``de`` (in ``(x, theta)``)."""


@functools.lru_cache(maxsize=4)
def _step_linearisation(model: SuModel) -> StepLinearisation:
    """One step's residuals and the nonzeros of their Jacobians (:data:`StepLinearisation`), derived once per model
    and shared by every window size's solver (11 at start-up: 35 ms less to build; the same functions, so the same
    arithmetic)."""
    md, n, nt = model.n_dynamic, model.n_outputs, model.n_states - model.n_dynamic
    fw, fe = residual_functions(model)
    xp, xn, x, th = ca.SX.sym("xp", md), ca.SX.sym("xn", md), ca.SX.sym("x", md), ca.SX.sym("theta", nt)
    h, y = ca.SX.sym("h"), ca.SX.sym("y", n)
    w, e = fw(ca.vertcat(xp, th), ca.vertcat(xn, th), h), fe(ca.vertcat(x, th), y)
    jw, je = ca.jacobian(w, ca.vertcat(xp, xn, th)), ca.jacobian(e, ca.vertcat(x, th))
    step_w = ca.Function("mhe_w_lin", [xp, xn, th, h], [w, jw.nz[:]])
    step_e = ca.Function("mhe_e_lin", [x, th, y], [e, je.nz[:]])
    (rw, cw), (re, ce) = jw.sparsity().get_triplet(), je.sparsity().get_triplet()
    return step_w, step_e, (np.asarray(rw), np.asarray(cw)), (np.asarray(re), np.asarray(ce))


@functools.lru_cache(maxsize=16)
def _step_blocks(model: SuModel, steps: int) -> tuple[ca.Function, ca.Function]:
    """The one-step functions of :func:`_step_linearisation` mapped over ``steps`` steps and expanded into flat
    (SX) functions: one call runs the steps' operations without the map's call of the step function per step."""
    step_w, step_e, _, _ = _step_linearisation(model)
    return step_w.map(steps).expand(), step_e.map(steps).expand()


def _over_steps(model: SuModel, which: int, steps: int, args: list[ca.MX]) -> list[ca.MX]:
    """The outputs of one-step function ``which`` (0: the state noise's, 1: the outputs') of
    :func:`_step_linearisation` over ``steps`` steps, as its map would give them: per-step inputs are the columns of
    ``args``, a one-column input is every step's. Flat blocks of :data:`BLOCK_STEPS` steps mapped, then one flat
    block of the rest (:func:`_step_blocks`): the same operations per step as the map of the step function, bit for
    bit (tested), in about 0.7 of its time on an outage's long windows."""
    full, rest = divmod(steps, BLOCK_STEPS)
    parts = []
    for n_steps, first, last in ((BLOCK_STEPS, 0, full * BLOCK_STEPS), (rest, full * BLOCK_STEPS, steps)):
        if last > first:
            block = _step_blocks(model, n_steps)[which]
            block = block.map((last - first) // n_steps) if last - first > n_steps else block
            parts.append(block(*(a if a.size2() == 1 else a[:, first:last] for a in args)))
    return [ca.horzcat(*outs) for outs in zip(*parts, strict=True)]


def _linearisation(model: SuModel, C: int) -> tuple[ca.Function, NDArray[np.int64], NDArray[np.int64]]:
    """``(z, h, y) -> [r; J.nz]`` of a window of ``C`` steps: the residuals ``r`` (the state noises of the steps,
    then the output noises) and the nonzeros of their Jacobian ``J`` in the variables ``z`` (the dynamic states
    step by step, then the CAN states), column-major as CasADi stores a sparse matrix; and ``J``'s rows and columns.

    ``J`` is put together from the Jacobians of one step (:func:`_step_linearisation`), derived once: the same
    expressions, entry for entry, as differentiating the whole window (checked in the tests), for a sixth of the
    build time (11 window sizes are built at start-up)."""
    md, n, nt = model.n_dynamic, model.n_outputs, model.n_states - model.n_dynamic
    _, _, (rw, cw), (re, ce) = _step_linearisation(model)
    # the window's function calls flat blocks of the step functions (MX: a map node each, :func:`_over_steps`), not
    # copies of their expressions for the whole window (SX): the same arithmetic, bit for bit, built in a few ms at
    # any size instead of 12-26 ms (11 sizes at start-up)
    nx = C * md
    z = ca.MX.sym("z", nx + nt)
    Xd, TH = ca.reshape(z[:nx], md, C), z[nx:]
    H, Y = ca.MX.sym("h", 1, C - 1), ca.MX.sym("y", n, C)
    W, JW = _over_steps(model, 0, C - 1, [Xd[:, :-1], Xd[:, 1:], TH, H])
    E, JE = _over_steps(model, 1, C, [Xd, TH, Y])
    # each step's entries placed: its rows after the previous steps', its states' columns at its step (then the
    # next step's for a state noise), the CAN states' after all dynamic states
    kw, ke = np.arange(C - 1)[:, None], np.arange(C)[:, None]
    rows = np.concatenate([(kw * md + rw).ravel(), ((C - 1) * md + ke * n + re).ravel()])
    cols = np.concatenate(
        [
            np.where(cw < 2 * md, kw * md + cw, nx + cw - 2 * md).ravel(),
            np.where(ce < md, ke * md + ce, nx + ce - md).ravel(),
        ]
    )
    order = np.lexsort((rows, cols))
    nz = ca.vertcat(ca.vec(JW), ca.vec(JE))[order.tolist()]
    lin = ca.Function("mhe_lin", [z, H, Y], [ca.vertcat(ca.vec(W), ca.vec(E), nz)])
    return lin, rows[order].astype(np.int64), cols[order].astype(np.int64)


class SqpSolver:
    """Real-time iteration on a structure fixed per capacity (module docstring): banded solve, else OSQP."""

    name = "sqp"

    def __init__(
        self,
        model: SuModel,
        capacity: int,
        max_iter: int = 200,
        tol: float = 1e-5,
        iterations: int = 1,
        banded: bool = True,
        flat: bool = False,
    ) -> None:
        """``flat``: the window's residual-and-Jacobian function expanded into one flat (SX) function: the same
        operations on the same numbers, bit for bit, for 2 ms more to build and 0.7 MB more at 50 steps (all 11
        default sizes: 90 ms and 25 MB, so only the window's normal size is flat; the others call flat blocks of
        steps, :func:`_over_steps`). Its common subexpressions are merged (CasADi's ``cse``: each value computed
        once, from the same operands, so the same bits): 8202 instructions instead of 9679 at 50 steps; a call
        17.5 us alone at 50 steps (the blocks' 26 us, without ``cse`` 21 us), for 15 ms more to build."""
        if capacity < 2:
            raise ValueError(f"capacity: need at least 2 steps, got {capacity}")
        t0 = time.perf_counter()
        self.model, self.capacity, self.iterations, self.banded = model, capacity, iterations, banded
        m, md, n, C = model.n_states, model.n_dynamic, model.n_outputs, capacity
        self.m, self.md, self.n, self.nt = m, md, n, m - md
        self.nz = C * md + self.nt
        self.nw, self.ne = md * (C - 1), n * C
        self.nv = nv = self.nz + self.nw + self.ne
        lin, self._rows, self._cols = _linearisation(model, C)
        self._lin = NumpyFunction(lin.expand(lin.name(), {"cse": True}) if flat else lin)
        self._row_step = np.concatenate([np.repeat(np.arange(C - 1), md), np.repeat(np.arange(C), n)])
        self._z_step = np.concatenate([np.repeat(np.arange(C), md), np.zeros(self.nt, dtype=np.int64)])
        self._live_masks: dict[int, tuple[NDArray[np.bool_], NDArray[np.bool_]]] = {}
        # the first state's variables: x_0 (dynamic) then the CAN states, in the order of the model's states
        self._first = np.concatenate([np.arange(md), self.nz - self.nt + np.arange(self.nt)])
        # the azimuth states' variables, step by step
        self._angles = (np.arange(C)[:, None] * md + np.array(model.angle_states)[None, :]).ravel()
        self._setup_banded()
        self._osqp_settings = (max_iter, tol)
        self._osqp: osqp.OSQP | None = None
        """Set up by :meth:`warm_up`, else at the first QP the banded step cannot solve."""
        self._y_prev: NDArray[np.float64] | None = None
        log.debug("SQP MHE problem, %d steps: %d variables, built in %.1f ms", C, nv, 1e3 * (time.perf_counter() - t0))

    def _setup_banded(self) -> None:
        """Index maps from products of Jacobian entries of one row to the normal matrix: its band (states, upper
        band storage of :func:`scipy.linalg.solveh_banded`, Fortran order as LAPACK takes it), the state-CAN block
        and the CAN-CAN block (both triangles), as places in one array that one ``bincount`` fills."""
        rows, cols, nx, nt, md = self._rows, self._cols, self.capacity * self.md, self.nt, self.md
        # every pair (a, b) of entries of one row, rows in order, a then b in the row's order (a row's
        # np.meshgrid(idx, idx, indexing="ij")), kept where cols[a] <= cols[b]
        order = np.argsort(rows, kind="stable")
        per_row = np.bincount(rows, minlength=self.nw + self.ne)
        count, row_start = per_row[rows[order]], (np.cumsum(per_row) - per_row)[rows[order]]
        a = np.repeat(order, count)
        within = np.arange(len(a)) - np.repeat(np.cumsum(count) - count, count)
        b = order[np.repeat(row_start, count) + within]
        keep = cols[a] <= cols[b]
        # grouped (state-state, state-CAN, CAN-CAN: cols[a] <= cols[b] leaves no CAN-state pair), each group in
        # the order above, so that each entry's sum adds the same terms in the same order; the CAN-CAN pairs off
        # the diagonal once more, mirrored, after them: the lower triangle the same sums as the upper
        ci, cj = cols[a[keep]], cols[b[keep]]
        groups = ((ci < nx) & (cj < nx), (ci < nx) & (cj >= nx), (ci >= nx) & (cj >= nx))
        mirrored = np.flatnonzero(groups[2] & (ci != cj))
        grouped = np.concatenate([*(np.flatnonzero(g) for g in groups), mirrored])
        pa, pb = a[keep][grouped], b[keep][grouped]
        swapped = np.arange(len(pa)) >= len(pa) - len(mirrored)
        ci, cj = np.where(swapped, cols[pb], cols[pa]), np.where(swapped, cols[pa], cols[pb])
        n_xx, n_xt = int(groups[0].sum()), int(groups[1].sum())
        xx, xt, tt = slice(0, n_xx), slice(n_xx, n_xx + n_xt), slice(n_xx + n_xt, len(pa))
        self._bw = bw = int(np.max(cj[xx] - ci[xx], initial=0))
        if self._bw < self.md - 1:
            raise SolverError(f"MHE problem: band {self._bw} narrower than a state ({self.md})")
        self._pairs = (pa, pb)
        # places: the band (bw + 1 x nx, column-major), then the state-CAN block (nx x nt), then the CAN-CAN one
        n_band = (bw + 1) * nx
        self._normal_at = np.concatenate(
            [
                cj[xx] * (bw + 1) + bw + ci[xx] - cj[xx],
                n_band + ci[xt] * nt + cj[xt] - nx,
                n_band + nx * nt + (ci[tt] - nx) * nt + cj[tt] - nx,
            ]
        )
        self._normal_size = n_band + nx * nt + nt * nt
        # the arrival weight on the first state, at its places: its dynamic states' upper triangle in the band,
        # their rows against the CAN states in the state-CAN block, the CAN-CAN block (regularised) whole
        m = md + nt
        wi, wj = np.triu_indices(md)
        ti, tj = np.divmod(np.arange(nt * nt), nt)
        xi, xt = np.divmod(np.arange(md * nt), nt)
        self._w_at = np.concatenate(
            [wj * (bw + 1) + bw - wj + wi, n_band + xi * nt + xt, n_band + nx * nt + ti * nt + tj]
        )
        self._w_from = np.concatenate([wi * m + wj, xi * m + md + xt, (md + ti) * m + md + tj])
        self._w_regularisation = np.zeros((m, m))
        self._w_regularisation[md:, md:] = REGULARISATION * np.eye(nt)

    def _setup_osqp(self) -> osqp.OSQP:
        """OSQP on the lifted QP: A = [J / B, -I; I] (rows divided by their bound B, lifted noises v = w / Q,
        u = e / R), P = 2 I on the lifted noises plus the arrival block on the first state."""
        max_iter, tol = self._osqp_settings
        nv, nr, nz = self.nv, self.nw + self.ne, self.nz
        a_rows = np.concatenate([self._rows, np.arange(nr), nr + np.arange(nv)])
        a_cols = np.concatenate([self._cols, nz + np.arange(nr), np.arange(nv)])
        self._perm = np.lexsort((a_rows, a_cols))
        indptr = np.searchsorted(a_cols[self._perm], np.arange(nv + 1))
        A = sp.csc_matrix((np.ones(len(self._perm)), a_rows[self._perm], indptr), shape=(nr + nv, nv))
        self._a_values = np.concatenate([np.zeros(len(self._rows)), -np.ones(nr), np.ones(nv)])
        # P pattern: the diagonal and the upper triangle of the first state's block
        fi, fj = np.meshgrid(self._first, self._first, indexing="ij")
        upper = fi < fj
        p_rows = np.concatenate([np.arange(nv), fi[upper]])
        p_cols = np.concatenate([np.arange(nv), fj[upper]])
        self._p_perm = np.lexsort((p_rows, p_cols))
        self._p_block = (np.flatnonzero(upper.reshape(-1)), self._first)
        p_ind = np.searchsorted(p_cols[self._p_perm], np.arange(nv + 1))
        self._p_base = np.concatenate([np.zeros(nz), np.full(nr, 2.0), np.zeros(int(upper.sum()))])
        P = sp.csc_matrix((self._p_base[self._p_perm] + (p_rows == p_cols)[self._p_perm], p_rows[self._p_perm], p_ind))
        # blocks of OSQP's rows (offset, width per step, steps) for shifting the duals
        C, md, n, nt = self.capacity, self.md, self.n, self.nt
        self._blocks = [(0, md, C - 1), (self.nw, n, C), (nr, md, C), (nr + C * md, nt, 1)]
        self._blocks += [(nr + nz, md, C - 1), (nr + nz + self.nw, n, C)]
        solver = osqp.OSQP()
        solver.setup(
            P,
            np.zeros(nv),
            A,
            np.full(nr + nv, -np.inf),
            np.full(nr + nv, np.inf),
            verbose=False,
            eps_abs=tol,
            eps_rel=tol,
            eps_prim_inf=1e-6,
            eps_dual_inf=1e-6,
            max_iter=max_iter,
            polishing=False,
            check_termination=5,
            warm_starting=True,
        )
        return solver

    def warm_up(self) -> None:
        """Set up OSQP now rather than at the first QP the banded step cannot solve: its workspace (up to 3 MB at
        300 steps, 30 MB over the default buckets) would otherwise be allocated mid-drive, in a long outage or a
        run of rejected fixes that grows the window through the buckets. Outputs are the same either way: every
        solve sets all of the QP's values."""
        if self._osqp is None:
            self._osqp = self._setup_osqp()

    def _banded_step(
        self, js: NDArray, rs: NDArray, weight: NDArray, W: NDArray, delta: NDArray, L: int
    ) -> NDArray[np.float64] | None:
        """The minimiser of ``sum weight (J dz / B + r / B)^2 + (dz_0 - delta)' W (dz_0 - delta)`` over the first
        ``L`` steps and the CAN states (None if the normal matrix is singular); ``js = J / B``, ``rs = r / B``,
        ``dz_0`` the first state's variables."""
        md, nt, nx, bw = self.md, self.nt, self.capacity * self.md, self._bw
        pa, pb = self._pairs
        # weight[rows[pa]] * js[pa] * js[pb], the row's weight taken once per entry rather than once per pair
        weighted = weight.take(self._rows) * js
        normal = np.bincount(self._normal_at, weighted.take(pa) * js.take(pb), minlength=self._normal_size)
        # the arrival cost on the first state: normal[w_at] is never -0.0 (a bincount's sums start at +0.0), so
        # adding W's entries (-0.0 or not) and the regularisation at once gives the bits of adding them block by block
        normal[self._w_at] += (W + self._w_regularisation).take(self._w_from)
        n_band = (bw + 1) * nx
        band = normal[:n_band].reshape(bw + 1, nx, order="F")
        Nxt = normal[n_band : n_band + nx * nt].reshape(nx, nt)
        Ntt = normal[n_band + nx * nt :].reshape(nt, nt)
        b = -np.bincount(self._cols, weighted * rs.take(self._rows), minlength=self.nz)
        b[self._first] += W @ delta
        n_live = L * md
        band = band[:, :n_live]
        band[bw] += REGULARISATION
        rhs = np.empty((n_live, 1 + nt), order="F")
        rhs[:, 0], rhs[:, 1:] = b[:n_live], Nxt[:n_live]
        try:
            # N = U'U; with Y = U'^-1 [b, Nxt] the CAN states' Schur complement is Ntt - Y_N' Y_N and the states
            # follow from one more solve: 7 triangular solves instead of a full solve's 12 (LAPACK's pbsv on 6
            # right-hand sides), the band's solve 38 -> 27 us on a 50-step window
            U, info = _PBTRF(band, overwrite_ab=True)
            if info > 0:
                raise np.linalg.LinAlgError(f"{info}th leading minor not positive definite")
            Y, _ = _TBTRS(U, rhs, trans="T", overwrite_b=True)
            yb, YN = Y[:, 0], Y[:, 1:]
            dtheta = linalg.solve(Ntt - YN.T @ YN, b[nx:] - YN.T @ yb)
            dx, _ = _TBTRS(U, (yb - YN @ dtheta)[:, None], overwrite_b=True)
        except np.linalg.LinAlgError:
            return None
        dz = np.zeros(self.nz)
        dz[:n_live] = dx[:, 0]
        dz[nx:] = dtheta
        return dz

    def _live(self, L: int) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """The rows of a window of ``L`` steps (the state noises of its steps but the last, the outputs of all) and
        its variables (its steps' dynamic states, the CAN states), as masks made once per ``L``."""
        masks = self._live_masks.get(L)
        if masks is None:
            rows = np.concatenate([self._row_step[: self.nw] < L - 1, self._row_step[self.nw :] < L])
            masks = self._live_masks[L] = (rows, self._z_step < L)
        return masks

    def _shifted_duals(self, shift: int | None) -> NDArray[np.float64]:
        y = np.zeros(self.nw + self.ne + self.nv)
        if shift is None or self._y_prev is None:
            return y
        for offset, width, steps in self._blocks:
            if steps == 1:
                y[offset : offset + width] = self._y_prev[offset : offset + width]
            elif shift < steps:
                keep = (steps - shift) * width
                y[offset : offset + keep] = self._y_prev[offset + shift * width : offset + steps * width]
        return y

    def solve(self, problem: WindowProblem, shift: int | None, iterations: int | None = None) -> SolveResult:
        """Run the SQP iterations (``iterations`` QPs at most, default the solver's) from ``problem.x``; OSQP is
        warm-started with its previous duals shifted by ``shift`` steps (None: cold)."""
        md, nz, L = self.md, self.nz, problem.n_steps
        x = problem.x.copy()
        bound = np.concatenate([problem.state_bound.reshape(-1), problem.out_bound.reshape(-1)])
        rows_live, z_live = self._live(L)
        active = rows_live.copy()
        active[self.nw :] &= problem.avail.reshape(-1)
        weight = active.astype(float)
        W = problem.weight
        lo0, hi0 = problem.first_box()
        box_lo, box_hi = self._z_box(lo0, problem.lo), self._z_box(hi0, problem.hi)
        # the live variables' boxes with the banded solution's slack (:data:`BOX_TOL`)
        inside_lo, inside_hi = (box_lo - BOX_TOL)[z_live], (box_hi + BOX_TOL)[z_live]
        status, cost, success = "not solved", np.inf, False
        iters = qp_solves = 0
        t_eval = t_asm = t_solve = 0.0
        for it in range(iterations or self.iterations):
            t0 = time.perf_counter()
            zbar = np.concatenate([x[:, :md].reshape(-1), x[0, md:]])
            lin = self._lin(zbar, problem.h, problem.y.T)
            res, jac = lin[: self.nw + self.ne], lin[self.nw + self.ne :]
            res[: self.nw] -= problem.offset.reshape(-1)
            t1 = time.perf_counter()
            js, rs = jac / bound.take(self._rows), res / bound
            delta = problem.prior - x[0]
            dz = self._banded_step(js, rs, weight, W, delta, L) if self.banded else None
            if dz is not None:
                after = (np.bincount(self._rows, js * dz.take(self._cols), minlength=len(rs)) + rs)[active]
                z = (zbar + dz)[z_live]
                if (np.abs(after) <= 1.0 + BOX_TOL).all() and ((z >= inside_lo) & (z <= inside_hi)).all():
                    t_eval, t_asm = t_eval + t1 - t0, t_asm + time.perf_counter() - t1
                    qp_solves += 1
                    self._y_prev = None  # no duals: the next OSQP solve starts from zero ones
                    status, success, cost = "banded", True, float((after**2).sum())
                    self._apply(x, dz, L)
                    if self._turned(dz, L) < STEP_TOL:
                        break
                    continue
            if self._osqp is None:
                self._osqp = self._setup_osqp()
            row_lo, row_hi = _free(active, -rs, -rs)
            z_lo, z_hi = _free(z_live, box_lo - zbar, box_hi - zbar)
            v_lo, v_hi = _free(active, -np.ones(len(rs)), np.ones(len(rs)))
            p_values = self._p_base.copy()
            p_values[self._first] = 2.0 * np.diag(W)
            p_values[nz + len(rs) :] = 2.0 * W.reshape(-1)[self._p_block[0]]
            q = np.zeros(self.nv)
            q[self._first] = -2.0 * W @ delta
            a_values = self._a_values.copy()
            a_values[: len(js)] = js
            v0 = np.concatenate([np.zeros(nz), np.where(active, rs, 0.0)])
            t2 = time.perf_counter()
            self._osqp.update(
                q=q,
                l=np.concatenate([row_lo, z_lo, v_lo]),
                u=np.concatenate([row_hi, z_hi, v_hi]),
                Px=p_values[self._p_perm],
                Ax=a_values[self._perm],
            )
            self._osqp.warm_start(x=v0, y=self._shifted_duals(shift if it == 0 else 0))
            out = self._osqp.solve(raise_error=False)
            t3 = time.perf_counter()
            t_eval, t_asm, t_solve = t_eval + t1 - t0, t_asm + t2 - t1, t_solve + t3 - t2
            qp_solves += 1
            iters += int(out.info.iter)
            st = osqp.SolverStatus(out.info.status_val)
            status = st.name
            if st not in OSQP_OK or out.x is None or not np.all(np.isfinite(out.x)):
                success = False
                self._y_prev = None
                break
            success = True
            self._y_prev = np.asarray(out.y, dtype=float).copy()
            dz = out.x[:nz]
            self._apply(x, dz, L)
            cost = float(np.sum(out.x[nz:][active] ** 2))
            if self._turned(dz, L) < STEP_TOL:
                break
        return SolveResult(x, success, status, iters, qp_solves, cost, t_eval, t_asm, t_solve)

    def _z_box(self, first: NDArray[np.float64], each: NDArray[np.float64]) -> NDArray[np.float64]:
        """A bound on every variable: ``first`` (m) on the first state's (its CAN states too), ``each`` (m) on the
        later steps' dynamic states."""
        md, nx = self.md, self.capacity * self.md
        box = np.empty(self.nz)
        box[:md], box[nx:] = first[:md], first[md:]
        box[md:nx].reshape(-1, md)[:] = each[:md]
        return box

    def _turned(self, dz: NDArray[np.float64], L: int) -> float:
        """The largest change of an azimuth state over the first ``L`` steps (rad)."""
        angles = dz[self._angles[: L * len(self.model.angle_states)]]
        return float(np.maximum.reduce(np.abs(angles), initial=0.0))  # ndarray.max's reduction, without its wrapper

    def _apply(self, x: NDArray[np.float64], dz: NDArray[np.float64], L: int) -> None:
        md = self.md
        x[:L, :md] += dz[: L * md].reshape(L, md)
        x[:, md:] += dz[self.nz - self.nt :]
