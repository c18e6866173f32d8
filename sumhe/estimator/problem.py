"""The MAP nonlinear program (16) of paper 000 in CasADi, built once per model and window size.

Decision variables ``z = [x_0 .. x_{N-1}, theta, q, r]``: the dynamic states step-major, the window-constant
states (CAN yaw-rate bias, speed scale: the parameters Theta of 000 (2)), then the noise bounds. Everything
that changes from window to window is a symbolic parameter, so one built NLP is re-solved with new data,
new availability and new bounds (the moving-horizon estimator relies on this; see ``SuNlp.params``):

* data ``Y`` and availability ``A`` (n x N): an output row ``|A (Y - h(x))| <= r * C`` with ``A = 0`` is
  ``0 <= r * C``, always true, which is the indicator ``I_t`` of (20): a missing output drops its constraint;
* per-epoch output scales ``C`` (n x N), per-step state scales ``S`` (m x N-1) and step lengths ``H`` (N-1);
* objective weights: ``K/T`` per output (``Kw``), normalisers ``qn``, ``rn`` and the mixing weights
  ``(w_log, w_lin, w_lsq)`` of the three objectives, and ``c_ext`` on the newest position;
* the antenna distance ``d`` of (23) (su7; its tolerance alpha is the row bound).

Objective: ``w_log * (sum ln q_i + sum Kw_j ln r_j)``  (paper (15))
``+ w_lin * (sum q_i / qn_i + sum Kw_j r_j / rn_j)``  (the normalised linear objective, 001 (15))
``+ w_lsq * (sum (w_ti / (q_i S_ti))^2 + sum A_kj (e_kj / (r_j C_kj))^2)``  (centre of the feasible set)
``+ c_ext . p_{N-1}``  (extent of the newest position). Residuals by :func:`~sumhe.model.su.state_noise` and
:func:`~sumhe.model.su.output_noise` (output angles wrapped, the azimuth state continuous).
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from sumhe.model.su import SuModel, antenna_distance_residual, output_noise, state_noise, su_model

log = logging.getLogger(__name__)

INF = np.inf
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
FEASIBLE_ENOUGH = ("Search_Direction_Becomes_Too_Small",)
"""IPOPT stops like this at a point it cannot improve within machine precision; such a point is a success
when it satisfies the constraints to ``MAX_VIOLATION``."""
MAX_VIOLATION = 1e-6


@dataclass(frozen=True)
class NlpSolution:
    """One IPOPT solve: the variables split into states (N x m), q (m) and r (n), and solver statistics."""

    x: NDArray[np.float64]
    q: NDArray[np.float64]
    r: NDArray[np.float64]
    f: float
    status: str
    success: bool
    iterations: int
    time_s: float


class SuNlp:
    """The MAP NLP for one SU model and ``n_steps`` steps; build with :func:`build_nlp` (cached)."""

    def __init__(self, model: SuModel, n_steps: int, max_iter: int, tol: float) -> None:
        if n_steps < 2:
            raise ValueError(f"n_steps: need at least 2 steps, got {n_steps}")
        self.model = model
        self.n_steps = n_steps
        m, md, n, N = model.n_states, model.n_dynamic, model.n_outputs, n_steps
        Xd, theta = ca.SX.sym("x", md, N), ca.SX.sym("theta", m - md)
        X = ca.vertcat(Xd, ca.repmat(theta, 1, N))
        q_rel, r_rel = ca.SX.sym("q_rel", md), ca.SX.sym("r_rel", n)
        Y, A, C = ca.SX.sym("y", n, N), ca.SX.sym("a", n, N), ca.SX.sym("c", n, N)
        S, H = ca.SX.sym("s", md, N - 1), ca.SX.sym("h", 1, N - 1)
        Kw, qn, rn = ca.SX.sym("kw", n), ca.SX.sym("qn", md), ca.SX.sym("rn", n)
        q, r = q_rel * qn, r_rel * rn
        wts, cext, d = ca.SX.sym("w", 3), ca.SX.sym("cext", 2), ca.SX.sym("d", 1)

        g_state, lsq_state = self._state_rows(X, q, S, H)
        g_out, lsq_out = self._output_rows(X, r, Y, A, C)
        rows = [g_state, g_out]
        lbg = [
            np.tile(np.r_[-INF * np.ones(md), np.zeros(md)], N - 1),
            np.tile(np.r_[-INF * np.ones(n), np.zeros(n)], N),
        ]
        ubg = [np.tile(np.r_[np.zeros(md), INF * np.ones(md)], N - 1), np.tile(np.r_[np.zeros(n), INF * np.ones(n)], N)]
        self.n_antenna_rows = N if model.antennas == 2 else 0
        if model.antennas == 2:
            rows.append(ca.vertcat(*[antenna_distance_residual(X[:, k]) - d**2 for k in range(N)]))
        self._g_fixed = (np.concatenate(lbg), np.concatenate(ubg))

        f_log = ca.sum1(ca.log(q_rel)) + ca.dot(Kw, ca.log(r_rel))
        f_lin = ca.sum1(q_rel) + ca.dot(Kw, r_rel)
        ie, inn = model.position
        f = wts[0] * f_log + wts[1] * f_lin + wts[2] * (lsq_state + lsq_out)
        f += cext[0] * X[ie, N - 1] + cext[1] * X[inn, N - 1]
        z = ca.vertcat(ca.vec(Xd), theta, q_rel, r_rel)
        p = ca.vertcat(ca.vec(Y), ca.vec(A), ca.vec(C), ca.vec(S), ca.vec(H), Kw, qn, rn, wts, cext, d)
        self.n_params = int(p.shape[0])
        self._qn_at = 3 * n * N + md * (N - 1) + (N - 1) + n
        opts = {
            "print_time": False,
            "error_on_fail": False,
            # IPOPT backtracks from a NaN (a log of a q it relaxed below 0); the status reports real trouble
            "show_eval_warnings": False,
            "ipopt": {
                "print_level": 0,
                "sb": "yes",
                "max_iter": max_iter,
                "tol": tol,
                "acceptable_tol": max(tol * 100, 1e-6),
                "mu_strategy": "adaptive",
            },
        }
        t0 = time.perf_counter()
        self._solver = ca.nlpsol("su_map", "ipopt", {"x": z, "p": p, "f": f, "g": ca.vertcat(*rows)}, opts)
        log.debug("built SU NLP %s N=%d (%d vars) in %.2f s", model.name, N, z.shape[0], time.perf_counter() - t0)

    def _state_rows(self, X: ca.SX, q: ca.SX, S: ca.SX, H: ca.SX) -> tuple[ca.SX, ca.SX]:
        """``x_t - g(x_{t-1}) -/+ q S_t`` for every step (2 rows per dynamic state) and the squared normalised
        residuals. The constant states (bias, scale) are one variable each and have no rows."""
        m, md = self.model.n_states, self.model.n_dynamic
        xp, xn, h, s = ca.SX.sym("xp", m), ca.SX.sym("xn", m), ca.SX.sym("h"), ca.SX.sym("s", md)
        qq = ca.SX.sym("q", md)
        res = ca.vertcat(*state_noise(self.model, xp, xn, h, ca))
        bound = qq * s
        step = ca.Function(
            "state_step", [xp, xn, h, qq, s], [ca.vertcat(res - bound, res + bound), ca.sumsqr(res / bound)]
        )
        rows, lsq = step.map(self.n_steps - 1)(X[:, :-1], X[:, 1:], H, ca.repmat(q, 1, self.n_steps - 1), S)
        return ca.vec(rows), ca.sum2(lsq)

    def _output_rows(self, X: ca.SX, r: ca.SX, Y: ca.SX, A: ca.SX, C: ca.SX) -> tuple[ca.SX, ca.SX]:
        """``A (y_k - h(x_k)) -/+ r C_k`` for every step (2n rows each) and the squared normalised residuals."""
        m, n = self.model.n_states, self.model.n_outputs
        x, y, a, c, rr = ca.SX.sym("x", m), ca.SX.sym("y", n), ca.SX.sym("a", n), ca.SX.sym("c", n), ca.SX.sym("r", n)
        e = a * ca.vertcat(*output_noise(self.model, x, y, ca))
        bound = rr * c
        out = ca.Function("output", [x, y, a, rr, c], [ca.vertcat(e - bound, e + bound), ca.sumsqr(e / bound)])
        rows, lsq = out.map(self.n_steps)(X, Y, A, ca.repmat(r, 1, self.n_steps), C)
        return ca.vec(rows), ca.sum2(lsq)

    def params(
        self,
        y: NDArray[np.float64],
        avail: NDArray[np.bool_],
        r_scale: NDArray[np.float64],
        q_scale: NDArray[np.float64],
        h: NDArray[np.float64],
        kw: NDArray[np.float64],
        qn: NDArray[np.float64],
        rn: NDArray[np.float64],
        weights: tuple[float, float, float],
        c_ext: tuple[float, float] = (0.0, 0.0),
        antenna_distance: float = 1.0,
    ) -> NDArray[np.float64]:
        """The parameter vector. Arrays are step-major as in :class:`~sumhe.estimator.grid.Grid`:
        ``y``, ``avail``, ``r_scale`` (N x n), ``q_scale`` (N-1 x m_dynamic), ``h`` (N-1,) s."""
        y = np.where(avail, y, 0.0)
        parts = [y, avail.astype(float), r_scale, q_scale]
        flat = [np.asarray(a, dtype=float).reshape(-1) for a in parts]
        out = np.concatenate([*flat, h, kw, qn, rn, weights, c_ext, [antenna_distance]])
        if out.shape != (self.n_params,):
            raise ValueError(f"params: expected {self.n_params} values, got {out.shape[0]} (wrong window size?)")
        return out

    def solve(
        self,
        x0: NDArray[np.float64],
        q0: NDArray[np.float64],
        r0: NDArray[np.float64],
        p: NDArray[np.float64],
        lbx: NDArray[np.float64],
        ubx: NDArray[np.float64],
        q_bounds: tuple[NDArray[np.float64], NDArray[np.float64]],
        r_bounds: tuple[NDArray[np.float64], NDArray[np.float64]],
        antenna_tolerance: float = 0.0,
    ) -> NlpSolution:
        """Solve from the start ``x0`` (N x m), ``q0``, ``r0``; ``lbx``/``ubx`` are state bounds (N x m); the
        constant states take their start and bounds from the first row.

        q and r (start, bounds, solution) are in physical units; the NLP works on them divided by the
        normalisers ``qn``, ``rn`` of ``p`` (their caps), which keeps the variables O(1).
        """
        m, md, n, N = self.model.n_states, self.model.n_dynamic, self.model.n_outputs, self.n_steps
        qn, rn = p[self._qn_at : self._qn_at + md], p[self._qn_at + md : self._qn_at + md + n]
        lbg, ubg = self._g_fixed
        if self.n_antenna_rows:
            lbg = np.r_[lbg, -antenna_tolerance * np.ones(N)]
            ubg = np.r_[ubg, antenna_tolerance * np.ones(N)]
        t0 = time.perf_counter()
        sol = self._solver(
            x0=np.r_[x0[:, :md].reshape(-1), x0[0, md:], q0 / qn, r0 / rn],
            p=p,
            lbx=np.r_[lbx[:, :md].reshape(-1), lbx[0, md:], q_bounds[0] / qn, r_bounds[0] / rn],
            ubx=np.r_[ubx[:, :md].reshape(-1), ubx[0, md:], q_bounds[1] / qn, r_bounds[1] / rn],
            lbg=lbg,
            ubg=ubg,
        )
        elapsed = time.perf_counter() - t0
        stats = self._solver.stats()
        z = np.asarray(sol["x"]).reshape(-1)
        status = str(stats.get("return_status", "unknown"))
        g = np.asarray(sol["g"]).reshape(-1)
        violation = float(np.max(np.r_[lbg - g, g - ubg, 0.0]))
        success = status in SUCCESS or (status in FEASIBLE_ENOUGH and violation <= MAX_VIOLATION)
        nx = N * md + m - md
        x = np.hstack([z[: N * md].reshape(N, md), np.tile(z[N * md : nx], (N, 1))])
        return NlpSolution(
            x=x,
            q=z[nx : nx + md] * qn,
            r=z[nx + md :] * rn,
            f=float(sol["f"]),
            status=status,
            success=success,
            iterations=int(stats.get("iter_count", -1)),
            time_s=elapsed,
        )


@functools.lru_cache(maxsize=16)
def build_nlp(
    model_name: str,
    yaw_rate_bias: bool,
    speed_scale: bool,
    discretisation: str,
    lever_m: float,
    gps_speed: bool,
    n_steps: int,
    max_iter: int,
    tol: float,
) -> SuNlp:
    """The NLP for a model (the arguments of :func:`~sumhe.model.su.su_model`) and window size, built on first
    use and cached (never rebuilt per window)."""
    model = su_model(model_name, yaw_rate_bias, speed_scale, discretisation, lever_m, gps_speed)
    return SuNlp(model, n_steps, max_iter, tol)
