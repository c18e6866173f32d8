"""The window problem as a stage-wise NLP (:mod:`sumhe.estimator.mhe.problem`), solved by IPOPT or fatrop.

``"ipopt"``, ``"fatrop"``: the same problem as an NLP in the stage-wise form of an optimal control problem (states
``x_k``, controls ``v_k = w_k / Q_k``, dynamics ``x_{k+1} = F(x_k, Q_k v_k)``, the CAN states copied per stage),
solved to convergence each epoch, warm-started with the shifted primal and dual solution; fatrop exploits the stage
structure (``structure_detection = "auto"``). The implicit trapezoidal transition becomes explicit by substitution:
``T`` depends on ``x_{k+1}`` only through speed and yaw rate, whose own rows do not depend on ``x_{k+1}``, so
``F(x, w) = T(x, T(x, x) + w) + w`` is exact (with the offset, ``F(x, w + d)``).
"""

from __future__ import annotations

import logging
import time

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from sumhe.estimator.mhe.problem import SolveResult, WindowProblem, residual_functions
from sumhe.model.su import SuModel

log = logging.getLogger(__name__)

NLP_OK = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


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
        R, Q, D = ca.SX.sym("r", n, C), ca.SX.sym("q", md, C - 1), ca.SX.sym("d", md, C - 1)
        prior, Wsqrt = ca.SX.sym("p", m), ca.SX.sym("w", m, m)
        X = [ca.SX.sym(f"x{k}", m) for k in range(C)]
        V = [ca.SX.sym(f"v{k}", md) for k in range(C - 1)]
        z, g, f = [], [], ca.sumsqr(Wsqrt @ (X[0] - prior))
        equality: list[bool] = []
        for k in range(C):
            z.append(X[k])
            if k < C - 1:
                z.append(V[k])
                g.append(X[k + 1] - step(X[k], Q[:, k] * V[k] + D[:, k], H[k]))
                equality += [True] * m
                f += ca.sumsqr(V[k])
            e = A[:, k] * fe(X[k], Y[:, k]) / R[:, k]
            g.append(e)
            equality += [False] * n
            f += ca.sumsqr(e)
        p = ca.vertcat(H, ca.vec(Y), ca.vec(A), ca.vec(R), ca.vec(Q), ca.vec(D), prior, ca.vec(Wsqrt))
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
        noises = ca.horzcat(*[fw(X[k], X[k + 1], H[k]) for k in range(C - 1)])
        self._res = ca.Function("mhe_res", [ca.horzcat(*X), H], [noises])
        self._last: tuple[NDArray, NDArray] | None = None
        log.debug("%s MHE problem for %d steps built in %.1f ms", solver, C, 1e3 * (time.perf_counter() - t0))

    @staticmethod
    def _shift(vec: NDArray[np.float64], width: int, shift: int) -> NDArray[np.float64]:
        out = np.zeros(len(vec))
        keep = len(vec) - shift * width
        if keep > 0:
            out[:keep] = vec[shift * width :]
        return out

    def warm_up(self) -> None:
        """Nothing to do: the NLP solver is built whole by the constructor."""

    def solve(self, problem: WindowProblem, shift: int | None, iterations: int | None = None) -> SolveResult:
        """Solve the NLP from ``problem.x`` to convergence (``iterations`` is ignored); multipliers of the previous
        solve shifted by ``shift`` steps (None: cold)."""
        m, md, C, L = self.m, self.md, self.capacity, problem.n_steps
        t0 = time.perf_counter()
        live_w = np.arange(C - 1)[:, None] < L - 1
        Q = np.where(live_w, problem.state_bound, 1.0)
        avail = problem.avail & (np.arange(C)[:, None] < L)
        w = self._res(problem.x.T, problem.h).full().T - problem.offset
        v = np.where(live_w, w / Q, 0.0)
        z0 = np.concatenate([np.concatenate([problem.x[:-1], v], axis=1).reshape(-1), problem.x[-1]])
        lo0, hi0 = problem.first_box()
        lbx, ubx = np.full(len(z0), -np.inf), np.full(len(z0), np.inf)
        for k in range(L):
            s = k * self._stage
            lbx[s : s + m] = lo0 if k == 0 else problem.lo
            ubx[s : s + m] = hi0 if k == 0 else problem.hi
            if k < L - 1:
                lbx[s + m : s + m + md], ubx[s + m : s + m + md] = -1.0, 1.0
        eigval, eigvec = np.linalg.eigh(0.5 * (problem.weight + problem.weight.T))
        w_sqrt = (eigvec * np.sqrt(np.maximum(eigval, 0.0))) @ eigvec.T
        p = np.concatenate(
            [
                problem.h,
                problem.y.reshape(-1),
                avail.astype(float).reshape(-1),
                problem.out_bound.reshape(-1),
                Q.reshape(-1),
                problem.offset.reshape(-1),
                problem.prior,
                w_sqrt.reshape(-1, order="F"),
            ]
        )
        args: dict[str, object] = {"x0": z0, "p": p, "lbx": lbx, "ubx": ubx, "lbg": self._lbg, "ubg": self._ubg}
        if shift is not None and self._last is not None:
            lam_x, lam_g = self._last
            args["lam_x0"] = self._shift(lam_x, self._stage, shift)
            args["lam_g0"] = self._shift(lam_g, self._rows, shift)
        t1 = time.perf_counter()
        sol = self._nlp(**args)
        t2 = time.perf_counter()
        stats = self._nlp.stats()
        status = str(stats.get("return_status", "unknown"))
        success = bool(stats.get("success", False)) or status in NLP_OK
        zs = sol["x"].full().reshape(-1)
        success = success and bool(np.all(np.isfinite(zs)))
        self._last = (sol["lam_x"].full().reshape(-1), sol["lam_g"].full().reshape(-1)) if success else None
        x = problem.x.copy()
        if success:
            x[:-1] = zs[: (C - 1) * self._stage].reshape(C - 1, self._stage)[:, :m]
            x[-1] = zs[(C - 1) * self._stage :]
            x[:, md:] = x[0, md:]
        iterations_done = int(stats.get("iter_count", -1))
        return SolveResult(x, success, status, iterations_done, 0, float(sol["f"]), 0.0, t1 - t0, t2 - t1)
