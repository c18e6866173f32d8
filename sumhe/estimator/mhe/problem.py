"""The moving-horizon SU problem of one window: its data (:class:`WindowProblem`), a solver's answer and interface,
and the step residuals and Jacobians every solver and the arrival cost share.

The problem is the batch estimator's centre stage (:mod:`sumhe.estimator.batch`, stage 2) on a window of ``L``
steps, with the noise bounds fixed, and the first state held to an arrival box and an arrival cost
(``docs/mhe.md``)::

    min   sum_k |w_k / Q_k|^2 + sum_k |a_k e_k / R_k|^2 + (z_0 - p)' W (z_0 - p)
    s.t.  w_k = x_{k+1} - T(x_k, x_{k+1}, h_k) - d_k,  |w_k| <= Q_k           (state noise, k < L - 1)
          e_k = y_k - h(x_k),                   |a_k e_k| <= R_k               (output noise; a_k: availability)
          lo <= x_k <= hi,  |x_0 - c| <= alpha                                  (state box (11), arrival box)

``T`` is the model's transition (:mod:`sumhe.model.su`), ``Q_k = q' S_k`` and ``R_k = r' C_k`` the state and
output noise bounds of each step (half-widths of the uniform noises, so the weights are their variances up to the
common factor 3); ``z_0`` is the first state (the CAN bias and scale included, one variable each per window),
``p``, ``W`` the arrival cost, ``c``, ``alpha`` the arrival box. ``d_k`` is a known offset of the transition,
zero but for a step merged from several (:mod:`sumhe.estimator.mhe.window`): there it is what the merged steps' own
transitions added beyond one long trapezoidal step (the CAN data of the steps merged away), so that a merge
changes the problem, not its solution.

Everything that changes from epoch to epoch (data, availability, bounds, step lengths, arrival) is a number handed
to a solver built once per window capacity ``C`` (a bucket of sizes): steps ``L .. C-1`` are padding whose rows
are free. The solvers: :class:`~sumhe.estimator.mhe.sqp.SqpSolver` (``"sqp"``, real-time iteration with a banded
least-squares step and OSQP) and :class:`~sumhe.estimator.mhe.nlp.NlpSolver` (``"ipopt"``, ``"fatrop"``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from sumhe.model.compiled import NumpyFunction
from sumhe.model.su import SuModel, output_noise, state_noise
from sumhe.records import quick_init


@quick_init
@dataclass(frozen=True, slots=True)
class WindowProblem:
    """One window on a solver of capacity ``C``: ``n_steps`` real steps, rows beyond them are padding.

    ``x`` (C x m): the start point and linearisation point (CAN bias/scale columns constant); ``h`` (C-1) step
    lengths (s); ``y``, ``avail``, ``out_bound`` (C x n): outputs, availability and bounds R; ``state_bound``
    (C-1 x m_dynamic): bounds Q; ``lo``, ``hi`` (m): the state box; ``box_centre``, ``box_half`` (m): the arrival
    box of the first state (``inf`` half-widths: none); ``prior``, ``weight`` (m, m x m): the arrival cost;
    ``offset`` (C-1 x m_dynamic): the transitions' offsets d_k.
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
    box_centre: NDArray[np.float64]
    box_half: NDArray[np.float64]
    prior: NDArray[np.float64]
    weight: NDArray[np.float64]
    offset: NDArray[np.float64]

    @property
    def capacity(self) -> int:
        return int(self.x.shape[0])

    def first_box(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Bounds of the first state: the state box intersected with the arrival box."""
        return (
            np.maximum(self.lo, self.box_centre - self.box_half),
            np.minimum(self.hi, self.box_centre + self.box_half),
        )


@quick_init
@dataclass(frozen=True, slots=True)
class SolveResult:
    """A solver's answer: the trajectory ``x`` (C x m), whether it is usable, the solver's status (``"banded"``
    when the banded solve was the answer), its iterations (OSQP's ADMM iterations summed over the QPs, or the NLP
    iterations), the QPs solved (SQP iterations, banded or OSQP), the objective, and the time (s) spent
    evaluating the model and its Jacobians, assembling and in the solver."""

    x: NDArray[np.float64]
    success: bool
    status: str
    iterations: int
    qp_solves: int
    cost: float
    eval_s: float = 0.0
    assemble_s: float = 0.0
    solve_s: float = 0.0


class WindowSolver(Protocol):
    """A solver of the window problem for one capacity; ``shift`` is how many steps the window slid since the
    previous solve (the warm start is shifted by it), None for a cold start."""

    name: str
    capacity: int

    def solve(self, problem: WindowProblem, shift: int | None, iterations: int | None = None) -> SolveResult: ...

    def warm_up(self) -> None:
        """Build now whatever the solver would otherwise build at its first use."""


def residual_functions(model: SuModel) -> tuple[ca.Function, ca.Function]:
    """CasADi functions of one step: state noise ``w(x_prev, x_next, h)`` (m_dynamic) and output noise
    ``e(x, y)`` (n), by the model's one residual rule (:func:`~sumhe.model.su.state_noise`,
    :func:`~sumhe.model.su.output_noise`)."""
    m, n = model.n_states, model.n_outputs
    xp, xn, h = ca.SX.sym("xp", m), ca.SX.sym("xn", m), ca.SX.sym("h")
    x, y = ca.SX.sym("x", m), ca.SX.sym("y", n)
    w = ca.vertcat(*state_noise(model, xp, xn, h, ca))
    e = ca.vertcat(*output_noise(model, x, y, ca))
    return ca.Function("w", [xp, xn, h], [w]), ca.Function("e", [x, y], [e])


def step_jacobians(
    model: SuModel,
) -> Callable[[NDArray, NDArray, float, NDArray], tuple[NDArray, NDArray, NDArray, NDArray, NDArray]]:
    """``(xp, xn, h, y) -> (w, dw/dxp, dw/dxn, e(xp), de/dxp)`` as numpy arrays: one step's noises and their
    Jacobians (the arrival cost's update); one CasADi call with one dense output, split here."""
    fw, fe = residual_functions(model)
    m, md, n = model.n_states, model.n_dynamic, model.n_outputs
    xp, xn, h, y = ca.SX.sym("xp", m), ca.SX.sym("xn", m), ca.SX.sym("h"), ca.SX.sym("y", n)
    w, e = fw(xp, xn, h), fe(xp, y)
    parts = [w, ca.jacobian(w, xp), ca.jacobian(w, xn), e, ca.jacobian(e, xp)]
    shapes = [(md,), (md, m), (md, m), (n,), (n, m)]
    f = NumpyFunction(ca.Function("step_jac", [xp, xn, h, y], [ca.vertcat(*[ca.vec(ca.densify(q)) for q in parts])]))
    ends = np.cumsum([int(np.prod(sh)) for sh in shapes]).tolist()
    (a, b, c, d), sw, se = ends[:4], (m, md), (m, n)

    def evaluate(xp_: NDArray, xn_: NDArray, h_: float, y_: NDArray) -> tuple[NDArray, ...]:
        flat = f(xp_, xn_, h_, y_)
        return flat[:a], flat[a:b].reshape(sw).T, flat[b:c].reshape(sw).T, flat[c:d], flat[d:].reshape(se).T

    return evaluate  # type: ignore[return-value]
