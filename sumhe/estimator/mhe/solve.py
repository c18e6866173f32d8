"""The MHE's window solve: solvers built once per window-size bucket, the noise bounds of a window, retries.

Noise bounds are not estimated per epoch. The output bounds R are the steps' error allowances (as in
:mod:`sumhe.estimator.grid`) times the factors learned from the residuals (:mod:`.envelope`), the state bounds Q the
bounds the CAN data's errors leave over each step (:mod:`.preintegration`), else the q caps (the vehicle's limits,
:func:`mhe_q_caps`) scaled with each step's length: the estimate is the centre of the set of these bounds
(``docs/mhe.md``). A failed or infeasible solve is retried with Q, R and the arrival box
widened by ``estimator.widen_factor`` (001 algorithm 3.3), at most ``estimator.mhe.max_retries`` times.
"""

from __future__ import annotations

import bisect
import logging
import time

import numpy as np
from numpy.typing import NDArray

from sumhe.errors import SolverError
from sumhe.estimator.batch import state_box
from sumhe.estimator.bounds import q_caps
from sumhe.estimator.mhe.arrival import Arrival
from sumhe.estimator.mhe.nlp import NlpSolver
from sumhe.estimator.mhe.problem import SolveResult, WindowProblem, WindowSolver
from sumhe.estimator.mhe.sqp import SqpSolver
from sumhe.estimator.mhe.window import Window
from sumhe.frontend.tally import Tally
from sumhe.model.su import SuModel
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)

STARTUP_ITERATIONS = 3
"""SQP iterations per epoch until the window first reaches its normal length (the start point is rough)."""
NLP_TOL = 1e-6


def mhe_q_caps(model: SuModel, h: float, settings: EstimationSettings) -> NDArray[np.float64]:
    """The MHE's state-noise bounds for a step of ``h`` s: the q caps (vehicle limits,
    :func:`~sumhe.estimator.bounds.q_caps`), those of the integrated states (positions, azimuth; ``q_power`` 2)
    times ``estimator.mhe.trapezoid_q`` with the trapezoidal transition, whose one-step error is O(h^3), not
    Euler's O(h^2)."""
    caps = q_caps(model, h, settings)
    if settings.estimator.discretisation == "trapezoid":
        caps = np.where(np.array(model.q_power) == 2, settings.estimator.mhe.trapezoid_q * caps, caps)
    return caps


def make_solver(
    model: SuModel, capacity: int, name: str, max_iter: int, tol: float, iterations: int, flat: bool = False
) -> WindowSolver:
    """The window solver ``name`` (``"sqp"``, ``"ipopt"``, ``"fatrop"``) for ``capacity`` steps (``flat``: see
    :class:`~sumhe.estimator.mhe.sqp.SqpSolver`)."""
    try:
        if name == "sqp":
            return SqpSolver(model, capacity, max_iter, tol, iterations, flat=flat)
        return NlpSolver(model, capacity, name, max_iter, tol)
    except RuntimeError as e:
        raise SolverError(f"cannot build the {name} MHE solver for {capacity} steps: {e}") from e


class WindowSolve:
    """Solves the window (module docstring) with the solver of its size's bucket, built at first use."""

    def __init__(self, model: SuModel, settings: EstimationSettings, tally: Tally) -> None:
        self.model = model
        self.settings = settings
        self.tally = tally
        m = settings.estimator.mhe
        self.buckets = tuple(sorted({*range(m.steps, m.max_steps, m.bucket_steps), m.max_steps}))
        self._solvers: dict[int, WindowSolver] = {}
        self._capacity: int | None = None
        self.last_result: SolveResult | None = None
        self.Q = np.zeros((0, model.n_dynamic))
        self.q_caps = mhe_q_caps(model, settings.gnss.period_s, settings)
        self._q_caps_period = settings.gnss.period_s
        """The GNSS period (s) ``q_caps`` are for: they are made again only when the stream's period changes."""
        lo, hi = state_box(model, 1, settings)
        self.lo, self.hi = lo[0], hi[0]
        """The state box (11) of one step."""
        self._q_power = np.array(model.q_power)[None, :]
        self._no_box = np.full(model.n_states - model.n_dynamic, np.inf)
        """The arrival box's half-widths of the CAN states: none."""

    def capacity(self, size: int) -> int:
        """The bucket (solver capacity) of a window of ``size`` steps."""
        return self.buckets[bisect.bisect_left(self.buckets, size)]

    def solver(self, size: int) -> WindowSolver:
        """The solver for a window of ``size`` steps (built now if it is the bucket's first)."""
        capacity = self.capacity(size)
        solver = self._solvers.get(capacity)
        if solver is None:
            m = self.settings.estimator.mhe
            t0 = time.perf_counter()
            max_iter, tol = (m.qp_max_iter, m.qp_tol) if m.solver == "sqp" else (m.nlp_max_iter, NLP_TOL)
            # the window's normal size, where nearly every epoch is solved, with the faster flat function
            flat = capacity == self.buckets[0]
            solver = make_solver(self.model, capacity, m.solver, max_iter, tol, m.sqp_iterations, flat)
            self._solvers[capacity] = solver
            self.tally.counts["solver_builds"] += 1
            log.info(
                "MHE: %s solver for %d steps built in %.0f ms", m.solver, capacity, 1e3 * (time.perf_counter() - t0)
            )
        return solver

    def warm_up(self) -> None:
        """Build the solver of every bucket, and what each builds at its first use, now: memory stays flat over
        a drive, whatever window sizes its outages reach."""
        for size in self.buckets:
            self.solver(size).warm_up()

    def reset(self) -> None:
        """A new window: no warm start to shift."""
        self._capacity = None
        self.Q = np.zeros((0, self.model.n_dynamic))

    def noise_bounds(
        self, win: Window, period_s: float, out_factor: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """State bounds Q (L-1 x m_dynamic): the q caps at the nominal period scaled with each step's length, or,
        where the step's motion comes from the CAN data (:mod:`.preintegration`), the smaller bound its errors
        leave; output bounds R (L x n): the steps' error allowances times ``out_factor`` (n; :mod:`.envelope`)."""
        t = win.t
        scale = ((t[1:] - t[:-1])[:, None] / period_s) ** self._q_power  # np.diff's values, without its set-up
        # the CAN bounds are NaN where unknown, else finite and >= 0: fmin takes the caps there, the smaller one
        # elsewhere (the where(isfinite, minimum, caps) it replaces, bit for bit, in one call instead of three)
        Q = np.fmin(win.q_step[1:, : self.model.n_dynamic], self.q_caps[None, :] * scale)
        return Q, win.allow * out_factor[None, :]

    def problem(
        self, win: Window, arrival: Arrival, capacity: int, Q: NDArray, R: NDArray, widen: float, period_s: float
    ) -> WindowProblem:
        """The window as a problem for a solver of ``capacity`` steps, bounds widened by ``widen``."""
        L, md, n = len(win), self.model.n_dynamic, self.model.n_outputs
        pad = capacity - L
        t = win.t
        h = t[1:] - t[:-1]  # np.diff's values, without its set-up
        if pad == 0:
            x, y, avail, offset = win.x, win.y, win.avail, win.offset[1:, :md]
        else:
            offset = np.vstack([win.offset[1:, :md], np.zeros((pad, md))])
            x = np.vstack([win.x, np.repeat(win.x[-1:], pad, axis=0)])
            h = np.concatenate([h, np.full(pad, period_s)])
            y = np.vstack([win.y, np.zeros((pad, n))])
            avail = np.vstack([win.avail, np.zeros((pad, n), dtype=bool)])
            Q = np.vstack([Q, np.ones((pad, md))])
            R = np.vstack([R, np.ones((pad, n))])
        if widen != 1.0:  # times 1.0 is every bound itself: the first attempt's arrays are used as they are
            Q, R = Q * widen, R * widen
        return WindowProblem(
            n_steps=L,
            x=x,
            h=h,
            y=y,
            avail=avail,
            out_bound=R,
            state_bound=Q,
            lo=self.lo,
            hi=self.hi,
            box_centre=arrival.box_centre,
            box_half=np.concatenate([arrival.alpha * widen, self._no_box]),
            prior=arrival.prior,
            weight=arrival.weight,
            offset=offset,
        )

    def solve(
        self, win: Window, arrival: Arrival, period_s: float, shift: int | None, out_factor: NDArray[np.float64]
    ) -> tuple[NDArray, str]:
        """Solve the window with retries; the trajectory (L x m) and the mode (``"mhe"``, ``"mhe-widened"``, or
        ``"predict"``: every attempt failed, the window's own trajectory). ``out_factor``: see
        :meth:`noise_bounds`."""
        s, m = self.settings, self.settings.estimator.mhe
        L = len(win)
        capacity = self.capacity(L)
        solver = self.solver(L)
        if capacity != self._capacity:
            shift = None
        self._capacity = capacity
        if period_s != self._q_caps_period:
            self.q_caps, self._q_caps_period = mhe_q_caps(self.model, period_s, s), period_s
        Q, R = self.noise_bounds(win, period_s, out_factor)
        self.Q = Q
        iterations = m.sqp_iterations if m.steps <= L else max(m.sqp_iterations, STARTUP_ITERATIONS)
        for attempt in range(m.max_retries + 1):
            problem = self.problem(win, arrival, capacity, Q, R, s.estimator.widen_factor**attempt, period_s)
            try:
                result = solver.solve(problem, shift if attempt == 0 else None, iterations)
            except (RuntimeError, ValueError, ArithmeticError) as e:
                self.tally.count("solver_errors", "MHE solver raised %s", e)
                continue
            self.last_result = result
            self.tally.counts["solves"] += 1
            self.tally.counts["qp_iterations" if m.solver == "sqp" else "nlp_iterations"] += result.iterations
            if result.success:
                self.tally.counts["banded_solves"] += result.status == "banded"
                if attempt:
                    self.tally.counts["widened"] += 1
                return result.x[:L], "mhe-widened" if attempt else "mhe"
            self.tally.count("failed_solves", "MHE solve failed (%s)", result.status)
        return win.x.copy(), "predict"
