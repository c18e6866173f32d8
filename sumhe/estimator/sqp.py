"""The moving-horizon SU problem of one window, and its three solvers: SQP-RTI with OSQP, IPOPT and fatrop.

The problem is the batch estimator's centre stage (:mod:`sumhe.estimator.batch`, stage 2) on a window of ``L``
steps, with the noise bounds fixed and the first state held to an arrival box (``docs/mhe.md``)::

    min   sum_k |w_k / Q_k|^2 + sum_k |a_k e_k / R_k|^2 + |(x_0 - c) / alpha|^2
    s.t.  w_k = x_{k+1} - T(x_k, x_{k+1}, h_k),  |w_k| <= Q_k                 (state noise, k < L - 1)
          e_k = y_k - h(x_k),                   |a_k e_k| <= R_k               (output noise; a_k: availability)
          lo <= x_k <= hi,  |x_0 - c| <= alpha                                  (state box (11), arrival box)

``T`` is the model's transition (:mod:`sumhe.model.su`), ``Q_k = q' S_k`` and ``R_k = r' C_k`` the state and
output noise bounds of each step (half-widths of the uniform noises, so the weights are their variances up to the
common factor 3), ``c``, ``alpha`` the arrival box. The CAN bias and scale states are one variable per window.

Everything that changes from epoch to epoch (data, availability, bounds, step lengths, arrival box) is a number
handed to a solver built once per window capacity ``C`` (a bucket of sizes): steps ``L .. C-1`` are padding whose
rows are free. The three solvers:

* :class:`SqpSolver` (``"sqp"``): real-time iteration. The constraints are linearised at the previous solution
  shifted by one step (the new step predicted with the newest CAN data), giving one QP per epoch (or a few, by
  ``mhe_sqp_iterations``), solved by OSQP. The noises are lifted into variables scaled by their bounds,
  ``w_k = Q_k v_k``, ``e_k = R_k u_k``, so that ``P`` is a constant diagonal, every bound is a box on a
  variable, and only ``A``'s values (the Jacobians from one compiled CasADi function, and the bounds), ``l``,
  ``u`` and ``q`` change: OSQP is set up once per bucket and re-solved with ``update(q, l, u, Ax)``, warm-started
  with the shifted primal and dual solution;
* :class:`NlpSolver` (``"ipopt"``, ``"fatrop"``): the same problem as an NLP in the stage-wise form of an optimal
  control problem (states ``x_k``, controls ``v_k = w_k / Q_k``, dynamics ``x_{k+1} = F(x_k, Q_k v_k)``, the CAN
  states copied per stage), solved to convergence each epoch, warm-started with the shifted primal and dual
  solution; fatrop exploits the stage structure (``structure_detection = "auto"``). The implicit trapezoidal
  transition becomes explicit by substitution: ``T`` depends on ``x_{k+1}`` only through speed and yaw rate,
  whose own rows do not depend on ``x_{k+1}``, so ``F(x, w) = T(x, T(x, x) + w) + w`` is exact.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Protocol

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sp
from scipy.linalg import solveh_banded
from numpy.typing import NDArray

from sumhe.errors import SolverError
from sumhe.model.su import SuModel, wrap_angle

log = logging.getLogger(__name__)

OSQP_OK = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)
OSQP_INFEASIBLE = (osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE, osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE)
NLP_OK = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
STEP_TOL = 1e-4
"""An SQP iteration whose largest state change is below this (m, rad, m/s, rad/s) ends the iterations."""
BOX_TOL = 1e-9
"""Slack allowed on the boxes when the banded (unconstrained) solution is checked against them."""
REGULARISATION = 1e-9
"""Added to the normal matrix's diagonal: directions no data fixes (an azimuth at standstill) stay put."""


@dataclass(frozen=True)
class WindowProblem:
    """One window on a solver of capacity ``C``: ``n_steps`` real steps, rows beyond them are padding.

    ``x`` (C x m): the start point and linearisation point (CAN bias/scale columns constant); ``h`` (C-1) step
    lengths (s); ``y``, ``avail``, ``out_bound`` (C x n): outputs, availability and bounds R; ``state_bound``
    (C-1 x m_dynamic): bounds Q; ``lo``, ``hi`` (m): the state box; ``centre``, ``half`` (m): the arrival box of
    the first state (``inf`` half-widths: no information).
    """

    n_steps: int
    x: NDArray[np.float64]
    h: NDArray[np.float64]
    y: NDArray[np.float64]
    avail: NDArray[np.bool_]
    out_bound: NDArray[np.float64]
    state_bound: NDArray[np.float64]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]
    centre: NDArray[np.float64]
    half: NDArray[np.float64]

    @property
    def capacity(self) -> int:
        return int(self.x.shape[0])


@dataclass(frozen=True)
class SolveResult:
    """A solver's answer: the trajectory ``x`` (C x m), whether it is usable, the solver's status, its
    iterations (ADMM iterations summed over the QPs, or NLP iterations), the QPs solved, the objective, and
    the time (s) spent evaluating the model and its Jacobians, assembling the QP and in the solver."""

    x: NDArray[np.float64]
    success: bool
    status: str
    iterations: int
    qp_solves: int
    cost: float
    eval_s: float = 0.0
    assemble_s: float = 0.0
    solve_s: float = 0.0
    theta_info: NDArray[np.float64] | None = None

    @property
    def infeasible(self) -> bool:
        return "infeasible" in self.status.lower()


class WindowSolver(Protocol):
    """A solver of the window problem for one capacity; ``shift`` is how many steps the window slid since the
    previous solve (the warm start is shifted by it), None for a cold start."""

    name: str
    capacity: int

    def solve(self, problem: WindowProblem, shift: int | None, iterations: int | None = None) -> SolveResult: ...


def residual_functions(model: SuModel) -> tuple[ca.Function, ca.Function]:
    """CasADi functions of one step: state noise ``w(x_prev, x_next, h)`` (m_dynamic) and output noise
    ``e(x, y)`` (n). Output angles are wrapped with atan2(sin, cos) as in :mod:`sumhe.estimator.problem`; the
    azimuth state is kept continuous along the window (never wrapped), so its noise is not: a wrapped state
    noise would let the azimuth jump by 2 pi from step to step, away from its arrival box."""
    m, md, n = model.n_states, model.n_dynamic, model.n_outputs
    xp, xn, h = ca.SX.sym("xp", m), ca.SX.sym("xn", m), ca.SX.sym("h")
    w = xn[:md] - ca.vertcat(*model.transition(xp, xn, h, ca)[:md])
    x, y = ca.SX.sym("x", m), ca.SX.sym("y", n)
    e = y - ca.vertcat(*model.output(x, ca))
    e = ca.vertcat(*[wrap_angle(e[j], ca) if j in model.angle_outputs else e[j] for j in range(n)])
    return ca.Function("w", [xp, xn, h], [w]), ca.Function("e", [x, y], [e])


def _free(mask: NDArray[np.bool_], lo: NDArray, hi: NDArray) -> tuple[NDArray, NDArray]:
    """``lo``, ``hi`` where ``mask``, (-inf, inf) elsewhere."""
    return np.where(mask, lo, -np.inf), np.where(mask, hi, np.inf)


def _arrival_weights(half: NDArray[np.float64]) -> NDArray[np.float64]:
    """1 / alpha^2 of the arrival term (0 where the box is infinite)."""
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(half) & (half > 0), 1.0 / np.square(half), 0.0)


class SqpSolver:
    """Real-time iteration on a structure fixed per capacity (module docstring).

    Each QP is first solved without its inequalities: the normal equations of the least-squares objective are
    block-banded (state ``k`` meets only states ``k - 1`` and ``k + 1``, plus the window's CAN bias and scale),
    so a banded Cholesky factorisation solves them in O(N), a Kalman smoother's cost. If that point lies inside
    every box it is the QP's solution (the problem is convex); otherwise OSQP solves the QP (``banded=False``:
    always OSQP).
    """

    name = "sqp"

    def __init__(
        self,
        model: SuModel,
        capacity: int,
        max_iter: int = 200,
        tol: float = 1e-5,
        iterations: int = 1,
        banded: bool = True,
    ) -> None:
        if capacity < 2:
            raise ValueError(f"capacity: need at least 2 steps, got {capacity}")
        t0 = time.perf_counter()
        self.model, self.capacity, self.iterations, self.banded = model, capacity, iterations, banded
        m, md, n, C = model.n_states, model.n_dynamic, model.n_outputs, capacity
        self.m, self.md, self.n, self.nt = m, md, n, m - md
        self.nz = C * md + self.nt
        self.nw, self.ne = md * (C - 1), n * C
        self.nv = nv = self.nz + self.nw + self.ne
        nr = self.nw + self.ne
        fw, fe = residual_functions(model)
        Xd, th = ca.SX.sym("x", md, C), ca.SX.sym("theta", self.nt)
        H, Y = ca.SX.sym("h", 1, C - 1), ca.SX.sym("y", n, C)
        X = ca.vertcat(Xd, ca.repmat(th, 1, C))
        res = ca.vertcat(ca.vec(fw.map(C - 1)(X[:, :-1], X[:, 1:], H)), ca.vec(fe.map(C)(X, Y)))
        z = ca.vertcat(ca.vec(Xd), th)
        J = ca.jacobian(res, z)
        self._lin = ca.Function("mhe_lin", [z, H, Y], [res, J.nz[:]])
        rows, cols = (np.asarray(a, dtype=np.int64) for a in J.sparsity().get_triplet())
        self._rows, self._cols = rows, cols
        self._row_step = np.concatenate([np.repeat(np.arange(C - 1), md), np.repeat(np.arange(C), n)])
        self._z_step = np.concatenate([np.repeat(np.arange(C), md), np.zeros(self.nt, dtype=np.int64)])
        self._setup_banded()
        # OSQP: A = [J / B, -I; I] (rows divided by their bound B = Q or R; lifted noises v = w / Q, u = e / R)
        a_rows = np.concatenate([rows, np.arange(nr), nr + np.arange(nv)])
        a_cols = np.concatenate([cols, self.nz + np.arange(nr), np.arange(nv)])
        self._perm = np.lexsort((a_rows, a_cols))
        indptr = np.searchsorted(a_cols[self._perm], np.arange(nv + 1))
        A = sp.csc_matrix((np.ones(len(self._perm)), a_rows[self._perm], indptr), shape=(nr + nv, nv))
        self._a_values = np.concatenate([np.zeros(len(rows)), -np.ones(nr), np.ones(nv)])
        self._p_diag = np.concatenate([np.zeros(self.nz), np.full(nr, 2.0)])
        P = sp.csc_matrix((self._p_diag.copy(), np.arange(nv), np.arange(nv + 1)), shape=(nv, nv))
        # blocks of OSQP's rows (offset, width per step, steps) for shifting the duals
        self._blocks = [(0, md, C - 1), (self.nw, n, C), (nr, md, C), (nr + C * md, self.nt, 1)]
        self._blocks += [(nr + self.nz, md, C - 1), (nr + self.nz + self.nw, n, C)]
        self._osqp = osqp.OSQP()
        self._osqp.setup(
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
        self._y_prev: NDArray[np.float64] | None = None
        self._theta_info: NDArray[np.float64] | None = None
        self.banded_solves = 0
        log.debug("SQP MHE problem, %d steps: %d variables, built in %.1f ms", C, nv, 1e3 * (time.perf_counter() - t0))

    def _setup_banded(self) -> None:
        """Index maps from products of Jacobian entries of one row to the normal matrix: its band (states, upper
        band storage of :func:`scipy.linalg.solveh_banded`), the state-CAN block and the CAN-CAN block."""
        rows, cols, nx, nt = self._rows, self._cols, self.capacity * self.md, self.nt
        order = np.argsort(rows, kind="stable")
        starts = np.searchsorted(rows[order], np.arange(self.nw + self.ne + 1))
        first, second = [], []
        for i in range(self.nw + self.ne):
            idx = order[starts[i] : starts[i + 1]]
            a, b = np.meshgrid(idx, idx, indexing="ij")
            keep = cols[a] <= cols[b]
            first.append(a[keep])
            second.append(b[keep])
        pa, pb = np.concatenate(first), np.concatenate(second)
        ci, cj = cols[pa], cols[pb]
        xx, xt, tt = (ci < nx) & (cj < nx), (ci < nx) & (cj >= nx), (ci >= nx) & (cj >= nx)
        self._bw = int(np.max(cj[xx] - ci[xx], initial=0))
        self._pairs = (pa, pb)
        self._xx = (xx, (self._bw + ci[xx] - cj[xx]) * nx + cj[xx])
        self._xt = (xt, ci[xt] * nt + (cj[xt] - nx))
        self._tt = (tt, (ci[tt] - nx) * nt + (cj[tt] - nx))

    def _banded_step(
        self, js: NDArray, rs: NDArray, weight: NDArray, d: NDArray, delta: NDArray, L: int
    ) -> NDArray[np.float64] | None:
        """The minimiser of ``sum weight (J dz / B + r / B)^2 + sum d (dz - delta)^2`` over the first ``L`` steps
        and the CAN states (None if the normal matrix is singular); ``js = J / B`` entries, ``rs = r / B``."""
        md, nt, nx, bw = self.md, self.nt, self.capacity * self.md, self._bw
        pa, pb = self._pairs
        prod = weight[self._rows[pa]] * js[pa] * js[pb]
        xx, xx_at = self._xx
        band = np.bincount(xx_at, prod[xx], minlength=(bw + 1) * nx).reshape(bw + 1, nx)
        xt, xt_at = self._xt
        Nxt = np.bincount(xt_at, prod[xt], minlength=nx * nt).reshape(nx, nt)
        tt, tt_at = self._tt
        Ntt = np.bincount(tt_at, prod[tt], minlength=nt * nt).reshape(nt, nt)
        Ntt = np.triu(Ntt) + np.triu(Ntt, 1).T
        grad = np.bincount(self._cols, js * (weight * rs)[self._rows], minlength=self.nz)
        b = d * delta - grad
        n_live = L * md
        band = band[:, :n_live]
        band[bw] += d[:n_live] + REGULARISATION
        Ntt += np.diag(d[nx:] + REGULARISATION)
        try:
            sol = solveh_banded(band, np.column_stack([b[:n_live], Nxt[:n_live]]), check_finite=False)
            schur = Ntt - Nxt[:n_live].T @ sol[:, 1:]
            dtheta = np.linalg.solve(schur, b[nx:] - Nxt[:n_live].T @ sol[:, 0])
        except np.linalg.LinAlgError:
            return None
        self._theta_info = np.diag(schur) - d[nx:] - REGULARISATION
        dz = np.zeros(self.nz)
        dz[:n_live] = sol[:, 0] - sol[:, 1:] @ dtheta
        dz[nx:] = dtheta
        return dz

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
        md, nt, nz, C, L = self.md, self.nt, self.nz, self.capacity, problem.n_steps
        x = problem.x.copy()
        bound = np.concatenate([problem.state_bound.reshape(-1), problem.out_bound.reshape(-1)])
        active = np.concatenate([self._row_step[: self.nw] < L - 1, problem.avail.reshape(-1)])
        active[self.nw :] &= self._row_step[self.nw :] < L
        weight = active.astype(float)
        wa = _arrival_weights(problem.half)
        d = np.zeros(nz)
        d[:md], d[nz - nt :] = wa[:md], wa[md:]
        lo = np.maximum(problem.lo, problem.centre - problem.half)
        hi = np.minimum(problem.hi, problem.centre + problem.half)
        box_lo = np.concatenate([lo[:md], np.tile(problem.lo[:md], C - 1), lo[md:]])
        box_hi = np.concatenate([hi[:md], np.tile(problem.hi[:md], C - 1), hi[md:]])
        z_live = self._z_step < L
        status, cost, success = "not solved", np.inf, False
        self._theta_info = None
        iters = qp_solves = 0
        t_eval = t_asm = t_solve = 0.0
        for it in range(iterations or self.iterations):
            t0 = time.perf_counter()
            zbar = np.concatenate([x[:, :md].reshape(-1), x[0, md:]])
            res, jac = self._lin(zbar, problem.h, problem.y.T)
            res, jac = res.full().reshape(-1), jac.full().reshape(-1)
            t1 = time.perf_counter()
            js, rs = jac / bound[self._rows], res / bound
            delta = np.zeros(nz)
            delta[:md] = (problem.centre - x[0])[:md]
            delta[nz - nt :] = (problem.centre - x[0])[md:]
            delta = np.where(d > 0, delta, 0.0)
            dz = self._banded_step(js, rs, weight, d, delta, L) if self.banded else None
            if dz is not None:
                after = np.bincount(self._rows, js * dz[self._cols], minlength=len(rs)) + rs
                inside = np.all(np.abs(after[active]) <= 1.0 + BOX_TOL)
                moved = (zbar + dz)[z_live]
                if inside and np.all(moved >= box_lo[z_live] - BOX_TOL) and np.all(moved <= box_hi[z_live] + BOX_TOL):
                    t2 = time.perf_counter()
                    t_asm += t2 - t1
                    t_eval += t1 - t0
                    self.banded_solves += 1
                    self._y_prev = np.zeros(self.nw + self.ne + self.nv)
                    status, success, cost = "banded", True, float(np.sum(after[active] ** 2))
                    self._apply(x, dz, L)
                    if np.max(np.abs(dz[: L * md]), initial=0.0) < STEP_TOL:
                        break
                    continue
            row_lo, row_hi = _free(active, -rs, -rs)
            z_lo, z_hi = _free(z_live, box_lo - zbar, box_hi - zbar)
            v_lo, v_hi = _free(active, -np.ones(len(rs)), np.ones(len(rs)))
            p_diag = self._p_diag.copy()
            p_diag[:nz] = 2.0 * d
            a_values = self._a_values.copy()
            a_values[: len(js)] = js
            v0 = np.concatenate([np.zeros(nz), np.where(active, rs, 0.0)])
            t2 = time.perf_counter()
            self._osqp.update(
                q=np.concatenate([-2.0 * d * delta, np.zeros(len(rs))]),
                l=np.concatenate([row_lo, z_lo, v_lo]),
                u=np.concatenate([row_hi, z_hi, v_hi]),
                Px=p_diag,
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
            lifted = out.x[nz:]
            cost = float(np.sum(lifted[active] ** 2))
            if np.max(np.abs(dz[: L * md]), initial=0.0) < STEP_TOL:
                break
        info = self._theta_info if status == "banded" else None
        return SolveResult(x, success, status, iters, qp_solves, cost, t_eval, t_asm, t_solve, info)

    def _apply(self, x: NDArray[np.float64], dz: NDArray[np.float64], L: int) -> None:
        md = self.md
        x[:L, :md] += dz[: L * md].reshape(L, md)
        x[:, md:] += dz[self.nz - self.nt :]


class NlpSolver:
    """The window problem as a stage-wise NLP solved to convergence by IPOPT or fatrop (module docstring)."""

    def __init__(self, model: SuModel, capacity: int, solver: str = "ipopt", max_iter: int = 100, tol: float = 1e-6):
        if solver not in ("ipopt", "fatrop"):
            raise ValueError(f"solver: ipopt or fatrop, got {solver!r}")
        if capacity < 2:
            raise ValueError(f"capacity: need at least 2 steps, got {capacity}")
        t0 = time.perf_counter()
        self.name, self.model, self.capacity = solver, model, capacity
        m, md, n, C = model.n_states, model.n_dynamic, model.n_outputs, capacity
        self.m, self.md, self.n = m, md, n
        fw, fe = residual_functions(model)
        xs, ws, h = ca.SX.sym("x", m), ca.SX.sym("w", md), ca.SX.sym("h")
        noise = ca.vertcat(ws, ca.SX.zeros(m - md))
        guess = ca.vertcat(*model.transition(xs, xs, h, ca)) + noise
        step = ca.Function("F", [xs, ws, h], [ca.vertcat(*model.transition(xs, guess, h, ca)) + noise])
        H, Y, A = ca.SX.sym("h", C - 1), ca.SX.sym("y", n, C), ca.SX.sym("a", n, C)
        R, Q = ca.SX.sym("r", n, C), ca.SX.sym("q", md, C - 1)
        c, wa = ca.SX.sym("c", m), ca.SX.sym("wa", m)
        X = [ca.SX.sym(f"x{k}", m) for k in range(C)]
        V = [ca.SX.sym(f"v{k}", md) for k in range(C - 1)]
        z, g, f = [], [], ca.sumsqr(wa * (X[0] - c))
        equality: list[bool] = []
        for k in range(C):
            z.append(X[k])
            if k < C - 1:
                z.append(V[k])
                g.append(X[k + 1] - step(X[k], Q[:, k] * V[k], H[k]))
                equality += [True] * m
                f += ca.sumsqr(V[k])
            e = A[:, k] * fe(X[k], Y[:, k]) / R[:, k]
            g.append(e)
            equality += [False] * n
            f += ca.sumsqr(e)
        p = ca.vertcat(H, ca.vec(Y), ca.vec(A), ca.vec(R), ca.vec(Q), c, wa)
        nlp = {"x": ca.vertcat(*z), "p": p, "f": f, "g": ca.vertcat(*g)}
        opts: dict[str, object] = {"print_time": False, "error_on_fail": False}
        if solver == "ipopt":
            opts["ipopt"] = {
                "print_level": 0,
                "sb": "yes",
                "max_iter": max_iter,
                "tol": tol,
                "warm_start_init_point": "yes",
                "warm_start_bound_push": 1e-6,
                "warm_start_mult_bound_push": 1e-6,
                "mu_init": 1e-3,
            }
        else:
            opts.update(structure_detection="auto", equality=equality, expand=True)
            opts["fatrop"] = {"print_level": 0, "max_iter": max_iter, "tol": tol}
        self._nlp = ca.nlpsol(f"mhe_{solver}", solver, nlp, opts)
        self._stage = m + md
        self._rows = m + n
        self._lbg = np.where(np.array(equality), 0.0, -1.0)
        self._ubg = np.where(np.array(equality), 0.0, 1.0)
        self._res = ca.Function(
            "mhe_res",
            [ca.vertcat(*X), H],
            [ca.vertcat(*[fw(X[k], X[k + 1], H[k]) for k in range(C - 1)])],
        )
        self._last: tuple[NDArray, NDArray, NDArray] | None = None
        log.debug("%s MHE problem for %d steps built in %.1f ms", solver, C, 1e3 * (time.perf_counter() - t0))

    def _shift(self, vec: NDArray[np.float64], width: int, shift: int, total: int) -> NDArray[np.float64]:
        out = np.zeros(total)
        keep = total - shift * width
        if keep > 0:
            out[:keep] = vec[shift * width : shift * width + keep]
        return out

    def solve(self, problem: WindowProblem, shift: int | None, iterations: int | None = None) -> SolveResult:
        """Solve the NLP from ``problem.x`` to convergence (``iterations`` is ignored); multipliers of the previous
        solve shifted by ``shift`` steps (None: cold)."""
        m, md, n, C, L = self.m, self.md, self.n, self.capacity, problem.n_steps
        t0 = time.perf_counter()
        Q = np.where(np.arange(C - 1)[:, None] < L - 1, problem.state_bound, 1.0)
        avail = problem.avail & (np.arange(C)[:, None] < L)
        w = self._res(problem.x.reshape(-1), problem.h).full().reshape(C - 1, md)
        v = np.where(np.arange(C - 1)[:, None] < L - 1, w / Q, 0.0)
        z0 = np.concatenate([np.concatenate([problem.x[k], v[k]]) if k < C - 1 else problem.x[k] for k in range(C)])
        lo = np.maximum(problem.lo, problem.centre - problem.half)
        hi = np.minimum(problem.hi, problem.centre + problem.half)
        lbx, ubx = np.full(len(z0), -np.inf), np.full(len(z0), np.inf)
        for k in range(L):
            s = k * self._stage
            lbx[s : s + m] = lo if k == 0 else problem.lo
            ubx[s : s + m] = hi if k == 0 else problem.hi
            if k < L - 1:
                lbx[s + m : s + m + md], ubx[s + m : s + m + md] = -1.0, 1.0
        p = np.concatenate([
            problem.h,
            problem.y.reshape(-1),
            avail.astype(float).reshape(-1),
            problem.out_bound.reshape(-1),
            Q.reshape(-1),
            problem.centre,
            np.sqrt(_arrival_weights(problem.half)),
        ])
        args: dict[str, object] = {"x0": z0, "p": p, "lbx": lbx, "ubx": ubx, "lbg": self._lbg, "ubg": self._ubg}
        if shift is not None and self._last is not None:
            _, lam_x, lam_g = self._last
            args["lam_x0"] = self._shift(lam_x, self._stage, shift, len(z0))
            args["lam_g0"] = self._shift(lam_g, self._rows, shift, len(self._lbg))
        t1 = time.perf_counter()
        sol = self._nlp(**args)
        t2 = time.perf_counter()
        stats = self._nlp.stats()
        status = str(stats.get("return_status", "unknown"))
        success = bool(stats.get("success", False)) or status in NLP_OK
        zs = sol["x"].full().reshape(-1)
        if not np.all(np.isfinite(zs)):
            success = False
        self._last = (zs, sol["lam_x"].full().reshape(-1), sol["lam_g"].full().reshape(-1)) if success else None
        x = problem.x.copy()
        if success:
            for k in range(C):
                x[k] = zs[k * self._stage : k * self._stage + m]
            x[:, md:] = x[0, md:]
        return SolveResult(
            x, success, status, int(stats.get("iter_count", -1)), 0, float(sol["f"]), 0.0, t1 - t0, t2 - t1
        )


def make_solver(model: SuModel, capacity: int, name: str, max_iter: int, tol: float, iterations: int) -> WindowSolver:
    """The window solver ``name`` (``"sqp"``, ``"ipopt"``, ``"fatrop"``) for ``capacity`` steps."""
    try:
        if name == "sqp":
            return SqpSolver(model, capacity, max_iter, tol, iterations)
        return NlpSolver(model, capacity, name, max_iter, tol)
    except RuntimeError as e:
        raise SolverError(f"cannot build the {name} MHE solver for {capacity} steps: {e}") from e
