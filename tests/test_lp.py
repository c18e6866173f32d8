"""The linear SU program (000 (21)-(22) as 001's LP) with OSQP: accuracy, constraints, missing data, retry."""

import dataclasses
import logging

import numpy as np
import pytest
import su_samples as S

from sumhe.errors import SolverError
from sumhe.estimator.batch import estimate_batch, estimate_lp, model_for
from sumhe.estimator.bounds import noise_bounds
from sumhe.estimator.grid import Grid, build_grid
from sumhe.estimator.lp import displacements, solve_lp
from sumhe.settings import EstimationSettings, with_changes

SETTINGS = with_changes(EstimationSettings(), {"estimator.yaw_rate_bias": False, "estimator.speed_scale": False})


def _lp(samples, settings=SETTINGS, grid: Grid | None = None):
    model = model_for(settings)
    grid = grid or build_grid(samples, model, settings, S.FRAME)
    bounds = noise_bounds(model, grid, settings)
    origin = np.mean(grid.y[grid.gps, :2], axis=0)
    return grid, bounds, solve_lp(grid, model, bounds, settings, origin)


def test_noise_free_lp_follows_the_truth_through_an_outage() -> None:
    motion = S.Motion(v=12.0, omega=0.15)
    res = estimate_lp(S.window(motion, 4.0, outage=(1.0, 3.0)), SETTINGS, frame=S.FRAME)
    east, north = S.truth(motion, res.t)
    assert np.abs(res.east - east).max() < 0.01
    assert np.abs(res.north - north).max() < 0.01
    assert res.method == "lp"
    assert res.lp_retries == 0
    assert np.isnan(res.q[2:]).all()  # the LP estimates no q for azimuth, speed, yaw rate


def test_lp_solution_satisfies_its_constraints() -> None:
    samples = S.window(S.Motion(omega=0.3), 3.0, outage=(1.0, 2.0), gps_noise_m=0.03, seed=3)
    grid, bounds, lp = _lp(samples)
    model = model_for(SETTINGS)
    move = displacements(model, grid.h, lp.phi, lp.speed, lp.yaw_rate)
    w = np.diff(lp.p, axis=0) - move
    tol = 1e-4
    assert np.all(np.abs(w) <= lp.q * bounds.q_scale[:, :2] + tol)
    e = np.abs(grid.y[:, :2] - lp.p)[grid.gps]
    assert np.all(e <= lp.r * bounds.r_scale[grid.gps, :2] + tol)
    assert np.all(lp.q >= -tol) and np.all(lp.q <= bounds.q_hi[:2] + tol)
    assert np.all(lp.r >= -tol) and np.all(lp.r <= bounds.r_hi[:2] + tol)


def test_missing_fix_drops_exactly_its_constraints() -> None:
    samples = S.window(S.Motion(), 2.0, gps_noise_m=0.02, seed=4)
    grid, _, _ = _lp(samples)
    k = 8
    avail = grid.avail.copy()
    avail[k, :3] = False
    y = grid.y.copy()
    dropped = dataclasses.replace(grid, avail=avail)
    garbage = dataclasses.replace(grid, avail=avail, y=np.where(np.arange(len(y))[:, None] == k, y + 5.0, y))
    _, _, a = _lp(samples, grid=dropped)
    _, _, b = _lp(samples, grid=garbage)
    assert a.p == pytest.approx(b.p, abs=1e-6)  # what is missing cannot matter
    kept = dataclasses.replace(grid, y=garbage.y)  # the same garbage, present: it must matter
    _, _, c = _lp(samples, grid=kept)
    assert np.abs(c.p[k] - a.p[k]).max() > 1.0


def test_infeasible_lp_is_retried_with_wider_bounds(caplog: pytest.LogCaptureFixture) -> None:
    # CAN speed 10 % high, no scale state: with the caps of a gentle vehicle the LP is infeasible
    settings = with_changes(SETTINGS, {"vehicle.max_accel_mps2": 0.5})
    samples = S.window(S.Motion(v=15.0, omega=0.0), 3.0, scale=1.1)
    with caplog.at_level(logging.INFO, logger="sumhe.estimator.lp"):
        _, bounds, lp = _lp(samples, settings)
    assert lp.retries >= 1
    assert "widening" in caplog.text
    assert np.any(lp.q > bounds.q_hi[:2])  # the solution needed the widened bounds
    with pytest.raises(SolverError, match="widenings"):
        _lp(samples, with_changes(settings, {"estimator.batch.max_widenings": 0}))


def test_batch_survives_a_failed_lp(caplog: pytest.LogCaptureFixture) -> None:
    settings = with_changes(SETTINGS, {"vehicle.max_accel_mps2": 0.5, "estimator.batch.max_widenings": 0})
    with caplog.at_level(logging.WARNING):
        res = estimate_batch(S.window(S.Motion(v=15.0, omega=0.0), 3.0, scale=1.1), settings, frame=S.FRAME)
    assert "starts from the interpolated fixes" in caplog.text
    assert np.isfinite(res.states).all()
    assert not res.success  # the NLP is infeasible within the caps too and may not widen them
    assert res.status in ("Infeasible_Problem_Detected", "Restoration_Failed")


@pytest.mark.parametrize("model", ["su5", "su7"])
def test_lp_and_nlp_agree_on_noise_free_data(model: str) -> None:
    settings = with_changes(SETTINGS, {"estimator.model": model})
    motion = S.Motion(v=8.0, omega=0.25)
    samples = S.window(motion, 3.0, antennas=2 if model == "su7" else 1)
    lp = estimate_lp(samples, settings, frame=S.FRAME)
    nlp = estimate_batch(samples, settings, frame=S.FRAME)
    assert nlp.success
    assert np.hypot(lp.east - nlp.east, lp.north - nlp.north).max() < 0.01
    east, north = S.truth(motion, nlp.t)
    assert np.hypot(nlp.east - east, nlp.north - north).max() < 0.01
