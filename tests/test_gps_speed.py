"""The receiver's speed over ground (Doppler) as a measurement: model output, grid, MHE and the Kalman peers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import su_samples as S

from sumhe.baseline.ekf import Ekf
from sumhe.bench.mhe import drive_stream, run_stream
from sumhe.config import Config
from sumhe.estimator.batch import model_for
from sumhe.estimator.grid import build_grid
from sumhe.estimator.mhe import MovingHorizonEstimator
from sumhe.estimator.registry import make_estimator
from sumhe.frontend.measurements import gps_speed
from sumhe.model.su import GPS_SPEED_OUTPUT, su_model
from sumhe.settings import EstimationSettings, with_changes
from sumhe.sim import SimSettings, simulate

SETTINGS = with_changes(EstimationSettings(), {"can.delay_s": 0.02})


def test_the_models_gain_the_speed_output_before_the_can_ones() -> None:
    su5 = su_model("su5", True, True, "trapezoid", gps_speed=True)
    assert su5.outputs == ("px", "py", "course", GPS_SPEED_OUTPUT, "can_speed", "can_yaw_rate")
    assert su5.gps_outputs == (0, 1, 2, 3)
    y = su5.output(np.array([1.0, 2.0, 0.3, 12.0, 0.1, 0.01, 1.02]))
    assert y[3] == 12.0 and y[4] == pytest.approx(12.0 * 1.02) and y[5] == pytest.approx(0.11)
    su7 = su_model("su7", gps_speed=True)
    assert su7.outputs.index(GPS_SPEED_OUTPUT) == 5 and su7.gps_outputs == (0, 1, 2, 3, 4, 5)
    plain = su_model("su5", True, True, "trapezoid")
    assert GPS_SPEED_OUTPUT not in plain.outputs and plain.gps_outputs == (0, 1, 2)
    assert model_for(with_changes(SETTINGS, {"gnss.use_speed": False})).n_outputs == 5


def test_which_speeds_count() -> None:
    assert gps_speed(10.0, 9.9, SETTINGS.gnss) == 10.0
    assert gps_speed(10.0, None, SETTINGS.gnss) == 10.0
    assert gps_speed(10.0, -9.9, SETTINGS.gnss) == -10.0  # reversing: the sign of the CAN speed
    assert gps_speed(1.5, 1.5, SETTINGS.gnss) is None  # below course_min_speed_mps: Doppler speeds are biased there
    assert gps_speed(None, 5.0, SETTINGS.gnss) is None
    assert gps_speed(math.nan, 5.0, SETTINGS.gnss) is None


def test_the_grid_carries_the_speed_of_the_fixes() -> None:
    model = model_for(SETTINGS)
    j = model.outputs.index(GPS_SPEED_OUTPUT)
    grid = build_grid(S.window(S.Motion(v=10.0, omega=0.1), 2.0), model, SETTINGS, S.FRAME)
    assert grid.avail[:, j].sum() == grid.gps.sum() > 0
    assert np.allclose(grid.y[grid.avail[:, j], j], 10.0)
    assert np.allclose(grid.allow[grid.avail[:, j], j], SETTINGS.estimator.r_cap_sigmas * SETTINGS.gnss.speed_sigma_mps)
    slow = build_grid(S.window(S.Motion(v=1.0, omega=0.1), 2.0), model, SETTINGS, S.FRAME)
    assert not slow.avail[:, j].any()


@pytest.mark.slow
def test_the_speed_pins_the_can_speed_scale() -> None:
    # a highway drive with correlated GNSS errors: the positions' slow wander looks like a speed-scale error
    drive = simulate(SimSettings(scenario="highway", seed=5, duration_s=60.0, gps_error="walk"))
    stream = drive_stream(drive)
    k_true = drive.truth.speed_scale[-1]
    errors: dict[tuple[str, bool], float] = {}
    for on in (False, True):
        settings = with_changes(SETTINGS, {"gnss.use_speed": on})
        mhe = MovingHorizonEstimator(settings)
        run_stream(mhe, stream)
        errors["mhe", on] = abs(mhe.smoothed()[1][-1, mhe.model.index("speed_scale")] - k_true)
        ekf = Ekf(settings)
        run_stream(ekf, stream)
        errors["ekf", on] = abs(ekf.x[ekf.layout.k] - k_true)
        assert (ekf.stats().get("gps_ok", 0) > 0) and (mhe.stats()["gps_ok"] > 0)
    for name in ("mhe", "ekf"):
        assert errors[name, True] < 0.5 * errors[name, False], errors
        assert errors[name, True] < 5e-4, errors


@pytest.mark.parametrize("name", ["pf", "dead-reckoning"])
def test_the_particle_filter_and_dead_reckoning_leave_the_speed_out(name: str) -> None:
    drive = simulate(SimSettings(scenario="urban", seed=6, duration_s=20.0))
    stream = drive_stream(drive)
    runs = []
    for on in (False, True):
        est = make_estimator(name, Config.of(with_changes(SETTINGS, {"gnss.use_speed": on})))
        runs.append([(e.t, e.east_m, e.north_m, e.speed_mps) for e in run_stream(est, stream).estimates])
    assert runs[0] == runs[1] and len(runs[0]) > 100
