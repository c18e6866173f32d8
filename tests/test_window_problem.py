"""The moving horizon's window problem is the batch estimator's centre stage: on the same data, with the same
bounds and no arrival, both give the same trajectory."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import su_samples as S

from sumhe.estimator.batch import estimate_batch, lever_m, model_for, start_states, state_box
from sumhe.estimator.bounds import noise_bounds
from sumhe.estimator.grid import build_grid
from sumhe.estimator.lp import solve_lp
from sumhe.estimator.mhe.nlp import NlpSolver
from sumhe.estimator.mhe.problem import WindowProblem, residual_functions
from sumhe.estimator.mhe.sqp import BLOCK_STEPS, SqpSolver, _linearisation
from sumhe.settings import EstimationSettings, with_changes

# "caps": the centre stage runs with q, r at their caps, the MHE's fixed bounds
SETTINGS = with_changes(EstimationSettings(), {"estimator.batch.objective": "caps"})


@pytest.fixture(scope="module")
def case() -> tuple:
    samples = S.window(S.Motion(v=12.0, omega=0.15), 4.0, outage=(1.5, 2.5), gps_noise_m=0.3, bias_rps=0.004, seed=3)
    batch = estimate_batch(samples, SETTINGS, frame=S.FRAME)
    assert batch.success and batch.widenings == 0
    model = model_for(SETTINGS, streaming=False)
    grid = build_grid(samples, model, SETTINGS, S.FRAME)
    bounds = noise_bounds(model, grid, SETTINGS, lever_m(SETTINGS))
    origin = np.mean(grid.y[grid.gps, :2], axis=0)
    lo, hi = state_box(model, 1, SETTINGS)
    x0 = np.clip(start_states(solve_lp(grid, model, bounds, SETTINGS, origin), model, np.zeros(2), SETTINGS), lo, hi)
    m, md, L = model.n_states, model.n_dynamic, grid.n_steps
    problem = WindowProblem(
        n_steps=L,
        x=x0,
        h=grid.h,
        y=np.where(grid.avail, grid.y, 0.0),
        avail=grid.avail,
        out_bound=bounds.r_hi * bounds.r_scale,
        state_bound=bounds.q_hi * bounds.q_scale,
        lo=lo[0],
        hi=hi[0],
        box_centre=x0[0],
        box_half=np.full(m, np.inf),
        prior=np.zeros(m),
        weight=np.zeros((m, m)),
        offset=np.zeros((L - 1, md)),
    )
    return model, batch, problem


def test_the_nlp_window_problem_is_the_centre_stage(case: tuple) -> None:
    model, batch, problem = case
    result = NlpSolver(model, problem.n_steps, "ipopt", max_iter=500, tol=1e-10).solve(problem, None)
    assert result.success
    assert np.abs(result.x[:, :2] - batch.states[:, :2]).max() < 1e-4  # m
    assert np.abs(result.x[:, 2:] - batch.states[:, 2:]).max() < 1e-4  # rad, m/s, rad/s, bias, scale


def test_the_real_time_iteration_converges_to_it(case: tuple) -> None:
    model, batch, problem = case
    result = SqpSolver(model, problem.n_steps, max_iter=4000, tol=1e-9, iterations=30).solve(problem, None)
    assert result.success
    assert np.abs(result.x[:, :2] - batch.states[:, :2]).max() < 1e-3


def test_the_flat_window_function_gives_the_same_bits(case: tuple) -> None:
    # the window's function expanded into one SX function does the same operations on the same numbers
    model, _, problem = case
    plain, flat = (SqpSolver(model, problem.n_steps, iterations=3, flat=f).solve(problem, None) for f in (False, True))
    assert plain.status == flat.status == "banded"
    assert np.array_equal(plain.x, flat.x)


def test_the_start_point_is_not_the_answer(case: tuple) -> None:
    _, batch, problem = case
    assert np.abs(problem.x[:, :2] - batch.states[:, :2]).max() > 0.05  # the solvers had to move


@pytest.mark.parametrize("C", [6, BLOCK_STEPS + 7])
def test_the_window_jacobian_from_one_steps_is_the_whole_windows(case: tuple, C: int) -> None:
    # the SQP solver puts J together from one step's Jacobian (in flat blocks of steps, then the rest: C = 32 has
    # one of each): the same pattern and, bit for bit, the same values as differentiating the whole window's
    # residuals at once
    model, _, problem = case
    md, n = model.n_dynamic, model.n_outputs
    assert problem.n_steps >= C
    lin, rows, cols = _linearisation(model, C)
    fw, fe = residual_functions(model)
    Xd, th = ca.SX.sym("x", md, C), ca.SX.sym("theta", model.n_states - md)
    H, Y = ca.SX.sym("h", 1, C - 1), ca.SX.sym("y", n, C)
    X = ca.vertcat(Xd, ca.repmat(th, 1, C))
    res = ca.vertcat(ca.vec(fw.map(C - 1)(X[:, :-1], X[:, 1:], H)), ca.vec(fe.map(C)(X, Y)))
    z = ca.vertcat(ca.vec(Xd), th)
    J = ca.jacobian(res, z)
    whole = ca.Function("whole", [z, H, Y], [ca.vertcat(res, J.nz[:])])
    assert np.array_equal(rows, J.sparsity().get_triplet()[0]) and np.array_equal(cols, J.sparsity().get_triplet()[1])
    zz, hh, yy = (
        np.concatenate([problem.x[:C, :md].reshape(-1), problem.x[0, md:]]),
        problem.h[: C - 1],
        problem.y[:C].T,
    )
    assert np.array_equal(np.asarray(lin(zz, hh, yy)), np.asarray(whole(zz, hh, yy)))
