"""The batch SU estimator: accuracy, the constraints it claims, missing outputs, CAN errors, bad input."""

import logging
import math

import numpy as np
import pytest
import su_samples as S

from sumhe.config import build_section
from sumhe.errors import EstimatorInputError
from sumhe.estimator.batch import antenna_distance_error, estimate_batch, model_args, model_for, state_box
from sumhe.estimator.grid import build_grid
from sumhe.estimator.problem import build_nlp
from sumhe.frontend.epochs import nominal_period
from sumhe.messages import CanSample, GnssFix
from sumhe.model import output_residuals, state_residuals
from sumhe.settings import BatchSettings, EstimationSettings, EstimatorSettings, with_changes

SETTINGS = EstimationSettings()
TOL = 1e-5


def test_noise_free_outage_is_bridged() -> None:
    motion = S.Motion(v=12.0, omega=0.3)
    res = estimate_batch(S.window(motion, 4.0, outage=(0.95, 3.05)), SETTINGS, frame=S.FRAME)
    assert res.success, res.status
    east, north = S.truth(motion, res.t)
    assert np.hypot(res.east - east, res.north - north).max() < 0.02
    assert len(res.t) == 41  # the 20 missing epochs are steps of the grid
    assert res.gps.sum() == 20
    assert res.ipopt_time_s > 0 and res.solve_time_s >= res.ipopt_time_s


def test_solution_satisfies_every_box_it_claims() -> None:
    samples = S.window(S.Motion(omega=-0.4), 3.0, outage=(1.0, 2.0), gps_noise_m=0.03, bias_rps=0.005, seed=5)
    res = estimate_batch(samples, SETTINGS, frame=S.FRAME)
    assert res.success, res.status
    model = model_for(SETTINGS, streaming=False)
    grid = build_grid(samples, model, SETTINGS, S.FRAME)
    b = res.bounds
    widen = 1.0 + SETTINGS.estimator.batch.centre_margin  # the centre lies in S(q', r') with q' = (1 + margin) q
    w = np.abs(state_residuals(model, res.states, grid.h))
    assert np.all(w <= widen * res.q * b.q_scale + TOL)
    e = np.abs(output_residuals(model, res.states, grid.y))
    assert np.all(e[grid.avail] <= (widen * res.r * b.r_scale)[grid.avail] + TOL)
    assert np.all(res.q >= b.q_lo - TOL) and np.all(res.q <= b.q_hi + TOL)
    assert np.all(res.r >= b.r_lo - TOL) and np.all(res.r <= b.r_hi + TOL)
    lo, hi = state_box(model, len(res.t), SETTINGS)
    assert np.all(res.states >= lo - TOL) and np.all(res.states <= hi + TOL)
    bias, scale = res.state("yaw_rate_bias"), res.state("speed_scale")
    assert np.ptp(bias) == 0 and np.ptp(scale) == 0  # constant over the window


def test_missing_outputs_drop_exactly_their_constraints() -> None:
    samples = S.window(S.Motion(), 2.0, gps_noise_m=0.02, seed=6)
    model = model_for(SETTINGS, streaming=False)
    grid = build_grid(samples, model, SETTINGS, S.FRAME)
    nlp = build_nlp(*model_args(SETTINGS, streaming=False), grid.n_steps, 300, 1e-8)
    res = estimate_batch(samples, SETTINGS, frame=S.FRAME)
    N, m, n = grid.n_steps, model.n_states, model.n_outputs
    origin = np.mean(grid.y[grid.gps, :2], axis=0)
    y = grid.y.copy()
    y[:, :2] -= origin
    lbx, ubx = state_box(model, N, SETTINGS)
    x0 = res.states.copy()
    x0[:, :2] -= origin
    q, r = res.q * 1.1, res.r * 1.1

    def solve(avail: np.ndarray, y: np.ndarray):
        p = nlp.params(
            y,
            avail,
            res.bounds.r_scale,
            res.bounds.q_scale,
            grid.h,
            np.ones(n),
            res.bounds.q_hi,
            res.bounds.r_hi,
            (0.0, 0.0, 1.0),
        )
        return nlp.solve(x0, q, r, p, lbx, ubx, (q, q), (r, r))

    k = 10
    avail = grid.avail.copy()
    avail[k, :3] = False
    a = solve(avail, y)
    junk = y.copy()
    junk[k, :3] = [40.0, -30.0, 2.0]
    b = solve(avail, junk)
    assert a.success and b.success
    assert a.x == pytest.approx(b.x, abs=1e-6)  # a missing output has no constraint and no cost
    c = solve(grid.avail, junk)
    assert not c.success  # the same junk, present, is outside S(q, r)
    assert m == 7


def test_can_bias_and_scale_are_estimated() -> None:
    motion = S.Motion(v=15.0, omega=0.25)
    samples = S.window(motion, 5.0, outage=(1.5, 3.5), gps_noise_m=0.01, bias_rps=0.007, scale=1.02, seed=7)
    res = estimate_batch(samples, SETTINGS, frame=S.FRAME)
    assert res.success
    assert res.state("yaw_rate_bias")[0] == pytest.approx(0.007, abs=0.002)
    assert res.state("speed_scale")[0] == pytest.approx(1.02, abs=0.003)
    east, north = S.truth(motion, res.t)
    assert np.hypot(res.east - east, res.north - north).max() < 0.05
    plain = estimate_batch(
        samples, with_changes(SETTINGS, {"estimator.yaw_rate_bias": False, "estimator.speed_scale": False})
    )
    assert "yaw_rate_bias" not in plain.state_names


def test_extent_contains_the_newest_position() -> None:
    motion = S.Motion(v=10.0, omega=0.1)
    samples = S.window(motion, 3.0, outage=(2.0, 3.1), gps_noise_m=0.02, seed=8)
    res = estimate_batch(samples, SETTINGS, frame=S.FRAME, extent=True)
    assert res.extent is not None
    e_min, e_max, n_min, n_max = res.extent
    assert e_min <= res.east[-1] <= e_max and n_min <= res.north[-1] <= n_max
    assert e_max - e_min > 0.01  # ten epochs without GNSS leave room
    assert estimate_batch(samples, SETTINGS, frame=S.FRAME).extent is None  # only on request


def test_su7_keeps_the_antenna_distance() -> None:
    settings = with_changes(SETTINGS, {"estimator.model": "su7"})
    motion = S.Motion(v=8.0, omega=-0.5)
    samples = S.window(motion, 3.0, outage=(1.0, 2.0), gps_noise_m=0.02, antennas=2, seed=9)
    res = estimate_batch(samples, settings, frame=S.FRAME)
    assert res.success
    assert res.state_names[:4] == ("px1", "py1", "px2", "py2")
    assert np.all(antenna_distance_error(res, 1.0) <= settings.vehicle.antenna_tolerance_m2 + TOL)
    east, north = S.truth(motion, res.t)
    assert np.hypot(res.east - east, res.north - north).max() < 0.1


@pytest.mark.slow
@pytest.mark.parametrize(
    "change",
    [
        {"estimator.batch.objective": "log"},
        {"estimator.batch.objective": "caps"},
        {"estimator.batch.centre": "none"},
        {"estimator.discretisation": "euler"},
    ],
)
def test_formulation_variants_solve(change: dict) -> None:
    settings = with_changes(SETTINGS, change)
    motion = S.Motion(v=10.0, omega=0.2)
    res = estimate_batch(S.window(motion, 3.0, outage=(1.0, 2.0), gps_noise_m=0.02, seed=10), settings)
    assert res.success, res.status
    assert (res.frame.lat0_deg, res.frame.lon0_deg) == pytest.approx((S.FRAME.lat0_deg, S.FRAME.lon0_deg))
    east, north = S.truth(motion, res.t)
    assert np.hypot(res.east - east, res.north - north).max() < 0.15


def test_caps_are_widened_to_hold_the_start_point_before_the_first_solve(caplog) -> None:
    """CAN speed 5 % above the GNSS speed, the speed scale held within 0.5 %: the start point (the CAN speed)
    misses the GNSS speed by 0.75 m/s against a cap of 0.2: two widenings by 2 before IPOPT runs, which then
    starts feasible and does not find the problem infeasible."""
    settings = with_changes(SETTINGS, {"can.speed_scale_max": 0.005})
    samples = S.window(S.Motion(v=15.0, omega=0.1), 3.0, gps_noise_m=0.02, scale=1.05, seed=11)
    with caplog.at_level(logging.INFO, logger="sumhe.estimator.batch"):
        res = estimate_batch(samples, settings, frame=S.FRAME)
    assert res.success, res.status
    assert res.widenings == 2
    assert [r.getMessage() for r in caplog.records] == [
        "SU NLP: the start point needs the caps of q and r widened by 4"
    ]
    assert res.r[res.output_names.index("gps_speed")] > 0.2  # the GNSS speed's bound beyond its cap
    plain = estimate_batch(S.window(S.Motion(v=15.0, omega=0.1), 3.0, gps_noise_m=0.02, seed=11), SETTINGS)
    assert plain.success and plain.widenings == 0


def test_failed_ipopt_is_a_result_not_an_exception() -> None:
    settings = with_changes(SETTINGS, {"estimator.batch.ipopt_max_iter": 1})
    res = estimate_batch(S.window(S.Motion(), 2.0, gps_noise_m=0.02), settings, frame=S.FRAME)
    assert not res.success
    assert res.status == "Maximum_Iterations_Exceeded"
    assert np.isfinite(res.states).all()  # the LP start point


def _fix(t: float, lat: float = 50.0755, lon: float = 14.4378, valid: bool = True) -> GnssFix:
    return GnssFix(t=t, time_utc=None, lat_deg=lat, lon_deg=lon, alt_m=0.0, quality=4, valid=valid)


@pytest.mark.parametrize(
    ("samples", "message"),
    [
        ([], "at least 2 samples"),
        ([_fix(0.0)], "at least 2 samples"),
        ([_fix(0.0), _fix(0.1, lat=math.nan)], "lat_deg"),
        ([_fix(0.0), CanSample(0.05, "speed", math.nan), _fix(0.1)], "not finite"),
        ([_fix(0.0), _fix(0.2), _fix(0.1)], "backwards"),
        ([_fix(0.0), _fix(math.inf)], "not finite"),
        ([_fix(0.0), "not a sample", _fix(0.1)], "not a GnssFix"),
        ([_fix(0.0), _fix(0.1, valid=False), CanSample(0.1, "speed", 1.0)], "2 valid GNSS"),
    ],
)
def test_bad_input_gives_a_clear_error(samples: list, message: str) -> None:
    with pytest.raises(EstimatorInputError, match=message):
        estimate_batch(samples, SETTINGS)


def test_settings_are_validated_naming_the_field() -> None:
    with pytest.raises(ValueError, match="objective"):
        with_changes(EstimationSettings(), {"estimator.batch.objective": "quadratic"})
    with pytest.raises(ValueError, match="r_cap_sigmas"):
        with_changes(EstimationSettings(), {"estimator.r_cap_sigmas": 0.0})
    with pytest.raises(ValueError, match="speed_scale_max"):
        with_changes(EstimationSettings(), {"can.speed_scale_max": 1.5})
    with pytest.raises(ValueError, match="widen_factor"):
        with_changes(EstimationSettings(), {"estimator.widen_factor": 1.0})
    table = {"model": "su7", "yaw_rate_bias": False, "batch": {"objective": "caps", "max_widenings": 3}}
    built = build_section(EstimatorSettings, table, "estimator")
    assert (built.model, built.batch.objective, built.yaw_rate_bias, built.batch.max_widenings) == (
        "su7",
        "caps",
        False,
        3,
    )
    assert built.batch.window_s == BatchSettings().window_s  # a nested table changes only the keys it names
    with pytest.raises(ValueError, match=r"estimator\.batch\.objective"):
        build_section(EstimatorSettings, {"batch": {"objective": "maximum"}}, "estimator")
    with pytest.raises(ValueError, match=r"estimator\.can_delay_s: moved: set sensors\.can\.delay_s"):
        build_section(EstimatorSettings, {"can_delay_s": 0.02}, "estimator")
    with pytest.raises(ValueError, match=r"estimator\.gps_time"):  # GNSS time is the [gps] table's, not here
        build_section(EstimatorSettings, {"gps_time": "utc"}, "estimator")


def test_the_grid_period_ignores_outage_gaps_and_needs_three_epochs() -> None:
    assert nominal_period(np.diff([0.0, 0.1, 0.2, 5.0, 5.1]), 0.5) == pytest.approx(0.1)
    assert nominal_period(np.diff(np.arange(0.0, 10.0, 1.0)), 0.1) == pytest.approx(1.0)  # a 1 Hz receiver
    assert nominal_period(np.diff([110.1, 140.2]), 0.1) == 0.1  # two fixes around an outage
    # a window holding only the fixes on either side of a 3 s outage: 0.1 s steps in between, not one 3 s step
    samples = [
        s
        for s in S.window(S.Motion(), 3.0, outage=(0.05, 2.95))
        if not isinstance(s, GnssFix) or s.t in (S.T0, S.T0 + 3.0)
    ]
    grid = build_grid(samples, model_for(SETTINGS, streaming=False), SETTINGS, S.FRAME)
    assert grid.gps.sum() == 2 and np.allclose(np.diff(grid.t), 0.1)
