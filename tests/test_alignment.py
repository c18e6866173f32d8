"""Clock alignment: lags between the receiver's speed/course and the CAN speed/yaw rate, on signals with a known
lag, scale and bias."""

import math
from collections import deque

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sumhe.frontend.alignment import (
    UNLEARNED_TIME_OFFSET_SD_S,
    CanSpeed,
    ClockLearner,
    TimeSeries,
    course_lag,
    speed_lag,
)
from sumhe.sim import SimSettings, simulate

RNG = np.random.default_rng(7)


def true_speed(t):
    """A drive that speeds up and slows down (m/s)."""
    return 12.0 + 6.0 * np.sin(2 * math.pi * t / 40.0) + 2.0 * np.sin(2 * math.pi * t / 9.0)


def true_yaw_rate(t):
    """Turns left and right (rad/s, anticlockwise)."""
    return 0.15 * np.sin(2 * math.pi * t / 25.0) + 0.05 * np.sin(2 * math.pi * t / 7.0)


def true_azimuth(t):
    """-integral of the yaw rate (clockwise), from 0 at t = 0."""
    return 0.15 * 25.0 / (2 * math.pi) * (np.cos(2 * math.pi * t / 25.0) - 1.0) + 0.05 * 7.0 / (2 * math.pi) * (
        np.cos(2 * math.pi * t / 7.0) - 1.0
    )


@pytest.mark.parametrize("can_period_s", [0.02, 0.5])
@pytest.mark.parametrize("rate_hz", [1.0, 10.0])
@pytest.mark.parametrize("lag", [-0.25, 0.0, 0.37])
def test_speed_lag_recovers_the_lag_and_scale(rate_hz, lag, can_period_s):
    # a speed broadcast at 50 Hz, or polled at 2 Hz (OBD-II: its samples farther apart than the fit's mean is wide)
    t_can = np.arange(0.0, 300.0, can_period_s)
    can = 1.01 * true_speed(t_can) + RNG.normal(0, 0.02, len(t_can))
    t_fix = np.arange(2.0, 298.0, 1.0 / rate_hz)
    gnss = true_speed(t_fix - lag) + RNG.normal(0, 0.1, len(t_fix))
    fit = speed_lag(t_fix, gnss, t_can, can)
    assert fit is not None
    assert fit.lag_s == pytest.approx(lag, abs=0.02)
    assert fit.std_s < 0.02
    assert fit.scale == pytest.approx(1 / 1.01, abs=0.002)


def test_the_speed_lag_moves_with_the_fixes_stamps():
    """Fixes stamped a few ms later (a host clock off UTC, a receive time): the lag learned grows by as much. On a
    simulated urban drive (stop and go, the receiver's velocity errors) the residual between the 20 ms grid's points
    is no parabola: the parabola's vertex moved by 2.8 to 11.4 ms for shifts of 3.1 to 12.4 ms."""
    sim = simulate(SimSettings(scenario="urban", seed=5, duration_s=60.0))
    fixes = np.array([(f.t, f.speed_mps) for f in sim.fixes() if f.valid and f.speed_mps is not None])
    can = np.array([(s.t, s.value) for s in sim.can_samples() if s.quantity == "speed"])
    base = speed_lag(fixes[:, 0], fixes[:, 1], can[:, 0], can[:, 1])
    assert base is not None and base.std_s < 0.01
    for shift in (0.0031, 0.0062, 0.0093, 0.0124):
        fit = speed_lag(fixes[:, 0] + shift, fixes[:, 1], can[:, 0], can[:, 1])
        assert fit is not None
        assert fit.lag_s - base.lag_s == pytest.approx(shift, abs=3e-4)


def test_course_lag_recovers_lag_scale_and_bias():
    lag, gain, bias = 0.28, 1.05, math.radians(0.4)
    t_yaw = np.arange(0.0, 300.0, 0.01)
    yaw = gain * true_yaw_rate(t_yaw) + bias + RNG.normal(0, math.radians(0.1), len(t_yaw))
    yaw = np.round(yaw / math.radians(0.25)) * math.radians(0.25)  # the logger's quantum
    t_fix = np.arange(2.0, 298.0, 1.0)
    course = np.mod(true_azimuth(t_fix - lag) + RNG.normal(0, math.radians(0.3), len(t_fix)), 2 * math.pi)
    fit = course_lag(t_fix, course, np.full(len(t_fix), 15.0), t_yaw, yaw)
    assert fit is not None
    assert fit.lag_s == pytest.approx(lag, abs=0.03)
    assert fit.scale == pytest.approx(1 / gain, abs=0.02)
    assert fit.offset == pytest.approx(bias, abs=math.radians(0.03))


def test_the_fitted_scales_standard_errors_cover_their_errors():
    """The scales' and the yaw rate's bias's standard errors (the on-line sensor check judges a mapping by them):
    over 20 noise draws of the drives above the errors' root mean square is 0.88 (speed), 0.40 (course: conservative)
    and 0.09 (bias: the rates between consecutive fixes share their azimuths' noise, which a sum of them cancels, and
    the error is taken as the scale's is; a bias is told late rather than wrongly) of them."""
    z_speed, z_course, z_bias = [], [], []
    for seed in range(20):
        rng = np.random.default_rng(seed)
        t_can = np.arange(0.0, 300.0, 0.02)
        can = 1.01 * true_speed(t_can) + rng.normal(0, 0.02, len(t_can))
        t_fix = np.arange(2.0, 298.0, 1.0)
        fit = speed_lag(t_fix, true_speed(t_fix - 0.1) + rng.normal(0, 0.1, len(t_fix)), t_can, can)
        assert fit is not None
        z_speed.append((fit.scale - 1 / 1.01) / fit.scale_std)
        t_yaw = np.arange(0.0, 300.0, 0.01)
        yaw = np.round((1.05 * true_yaw_rate(t_yaw) + 0.007 + rng.normal(0, 0.002, len(t_yaw))) / 0.004) * 0.004
        course = np.mod(true_azimuth(t_fix - 0.28) + rng.normal(0, math.radians(0.3), len(t_fix)), 2 * math.pi)
        fit = course_lag(t_fix, course, np.full(len(t_fix), 15.0), t_yaw, yaw)
        assert fit is not None
        z_course.append((fit.scale - 1 / 1.05) / fit.scale_std)
        z_bias.append((fit.offset - 0.007) / fit.offset_std)
    for z, low in ((z_speed, 0.3), (z_course, 0.3), (z_bias, 0.03)):
        assert low < math.sqrt(np.mean(np.square(z))) < 1.3


def test_too_little_data_or_no_excitation_determines_no_lag():
    t_can = np.arange(0.0, 100.0, 0.02)
    t_fix = np.arange(2.0, 98.0, 1.0)
    assert speed_lag(t_fix[:10], np.full(10, 10.0), t_can, np.full(len(t_can), 10.0)) is None
    assert speed_lag(t_fix, np.full(len(t_fix), 1.0), t_can, np.full(len(t_can), 1.0)) is None  # below 2 m/s
    steady = speed_lag(t_fix, 10.0 + RNG.normal(0, 0.1, len(t_fix)), t_can, np.full(len(t_can), 10.0))
    assert steady is None or not steady.std_s < 0.03  # a constant speed says nothing about the lag
    assert course_lag(t_fix, np.full(len(t_fix), np.nan), np.full(len(t_fix), 10.0), t_can, t_can * 0) is None


def correlated_noise(n, rho, sd, rng):
    """Stationary first-order autoregressive noise: standard deviation ``sd``, lag-1 correlation ``rho``."""
    x = np.empty(n)
    x[0] = rng.normal(0, sd)
    for i, e in enumerate(rng.normal(0, sd * math.sqrt(1 - rho**2), n - 1), start=1):
        x[i] = rho * x[i - 1] + e
    return x


def test_a_short_fits_standard_error_covers_its_error_with_correlated_residuals():
    # a receiver's velocity smoothed over epochs: 30 s windows at 10 Hz, errors correlated 0.9 from epoch to epoch
    rng, lag = np.random.default_rng(11), 0.2
    z = []
    for start in np.arange(0.0, 1200.0, 30.0):
        t_can = np.arange(start - 2.0, start + 32.0, 0.02)
        can = true_speed(t_can) + rng.normal(0, 0.02, len(t_can))
        t_fix = np.arange(start, start + 30.0, 0.1)
        gnss = true_speed(t_fix - lag) + correlated_noise(len(t_fix), 0.9, 0.15, rng)
        fit = speed_lag(t_fix, gnss, t_can, can)
        assert fit is not None
        z.append((fit.lag_s - lag) / fit.std_s)
    assert 0.6 < math.sqrt(np.mean(np.square(z))) < 1.4  # as white: 3.9


def test_the_can_speed_is_read_as_its_mean_about_each_sample():
    t = np.concatenate([np.arange(0.0, 1.0, 0.01), [1.0, 1.5, 2.0]])  # 100 Hz, then polled at 2 Hz
    assert np.allclose(CanSpeed(t, np.full(len(t), 10.0)).mean, 10.0, rtol=0.0, atol=1e-9)  # the two ends too
    line = CanSpeed(t, 2.0 + 3.0 * t)
    assert np.allclose(line.mean[5:-1], 2.0 + 3.0 * t[5:-1])  # a straight line is its own mean
    noisy = CanSpeed(t[:100], 10.0 + np.random.default_rng(1).normal(0, 0.02, 100))
    assert np.std(noisy.mean[5:-5]) < 0.5 * 0.02  # ten samples of noise in each mean
    assert line.at(np.array([1.25])) == pytest.approx(2.0 + 3.0 * 1.25)


def test_a_fit_over_a_first_acceleration_is_as_sure_as_it_says():
    # a drive's first seconds: 1.5 m/s^2 from a standstill for 7 s, the CAN speed at 100 Hz (noise 0.02 m/s, 2 %
    # high), the speed over ground at 10 Hz (0.05 m/s); the fit's lag trades with its scale along the ramp, and read
    # sample by sample the CAN noise jagged the residual over the lags (so read, its lag alone: rms z 3.0, 20 ms)
    lag, errors, z = 0.0, [], []
    for seed in range(40):
        rng = np.random.default_rng(100 + seed)
        t_can = np.arange(0.0, 12.0, 0.01)
        t_fix = np.arange(0.05, 10.5, 0.1)
        ramp = lambda t: 1.5 * np.clip(t - 4.0, 0.0, 7.0)  # noqa: E731
        can = 1.02 * ramp(t_can) + rng.normal(0, 0.02, len(t_can))
        fit = speed_lag(t_fix, ramp(t_fix - lag) + rng.normal(0, 0.05, len(t_fix)), t_can, can)
        assert fit is not None
        errors.append(fit.lag_s - lag)
        z.append((fit.lag_s - lag) / fit.std_s)
    assert math.sqrt(np.mean(np.square(errors))) < 0.017
    assert 0.5 < math.sqrt(np.mean(np.square(z))) < 1.3


@pytest.mark.parametrize("seed", range(5))
def test_the_can_speeds_noise_is_no_speed_change(seed):
    # the estimator contract's drive: a constant 10 m/s, the CAN speed's noise alone moves (50 Hz, 0.02 m/s)
    rng = np.random.default_rng(seed)
    t_can = np.arange(0.0, 20.0, 0.02)
    t_fix = np.arange(1.05, 19.0, 0.1)
    fit = speed_lag(t_fix, np.full(len(t_fix), 10.0), t_can, 10.0 + rng.normal(0, 0.02, len(t_can)))
    assert fit is not None and not fit.std_s < UNLEARNED_TIME_OFFSET_SD_S  # as white: 0.05 s, for errors up to 0.94 s


def test_early_fits_on_a_steady_drive_leave_the_offset_alone():
    learner = ClockLearner(initial_s=0.0)
    rng = np.random.default_rng(3)
    for k, t in enumerate(np.arange(0.0, 60.0, 0.02)):
        learner.add_can_speed(float(t), 10.0 + float(rng.normal(0, 0.02)))
        if k % 5 == 2:
            learner.add_fix(float(t), 10.0)
    assert learner.offset_s == pytest.approx(0.0, abs=1e-3)
    assert learner.sigma_s == UNLEARNED_TIME_OFFSET_SD_S and math.isinf(learner.std_s)  # the fits said nothing


def test_learner_starts_at_its_initial_value_and_converges_to_the_offset():
    lag = 0.3
    learner = ClockLearner(initial_s=0.05, window_s=120.0, refit_s=5.0)
    t_can = np.arange(0.0, 200.0, 0.02)
    can = true_speed(t_can)
    k = 0
    for t in np.arange(1.0, 200.0, 1.0):
        while k < len(t_can) and t_can[k] <= t:
            learner.add_can_speed(float(t_can[k]), float(can[k]))
            k += 1
        if t < 20:
            assert learner.offset_s == 0.05
        learner.add_fix(float(t), float(true_speed(t - lag) + RNG.normal(0, 0.05)))
    assert learner.fits > 0
    assert learner.offset_s == pytest.approx(-lag, abs=0.02)


def test_before_a_sure_fit_the_learner_weighs_each_fit_against_its_prior():
    # no fit passes the gate: each moves the offset from the initial value by the weight of its precision
    lag, initial = 0.3, 0.05
    learner = ClockLearner(initial_s=initial, window_s=120.0, refit_s=5.0, max_std_s=1e-9)
    t_can = np.arange(0.0, 120.0, 0.02)
    for t, v in zip(t_can, true_speed(t_can), strict=True):
        learner.add_can_speed(float(t), float(v))
    for t in np.arange(1.0, 120.0, 1.0):
        learner.add_fix(float(t), float(true_speed(t - lag) + RNG.normal(0, 0.05)))
    assert learner.fits == 0  # not learned: the gate's fits alone count
    assert abs(learner.offset_s + lag) < 0.1 * abs(initial + lag)  # near the fit, not the prior
    assert 0.0 < learner.sigma_s < UNLEARNED_TIME_OFFSET_SD_S


def test_learner_ignores_fixes_without_speed_and_bad_values():
    learner = ClockLearner(initial_s=0.1)
    for t in range(100):
        learner.add_can_speed(float(t), 10.0)
        learner.add_fix(float(t), None)
        learner.add_fix(float(t) + 0.5, math.nan)
    assert learner.offset_s == 0.1
    assert learner.fits == 0


def test_course_lag_fits_the_antennas_lever_arm():
    lag, lever, bias = 0.2, 1.8, math.radians(0.3)
    t_yaw = np.arange(0.0, 600.0, 0.01)
    yaw = true_yaw_rate(t_yaw) + bias + RNG.normal(0, math.radians(0.05), len(t_yaw))
    t_fix = np.arange(2.0, 598.0, 0.2)
    t_true = t_fix - lag
    speed = 4.0 + 3.0 * (1.0 + np.sin(2 * math.pi * t_true / 97.0))  # 4 to 10 m/s: the lever's lead changes
    course = true_azimuth(t_true) - np.arctan(lever * true_yaw_rate(t_true) / speed)
    course = np.mod(course + RNG.normal(0, 0.05 / speed), 2 * math.pi)
    plain = course_lag(t_fix, course, speed, t_yaw, yaw)
    fit = course_lag(t_fix, course, speed, t_yaw, yaw, lever_prior_m=(1.0, 1.5), speed_weighted=True)
    assert plain is not None and fit is not None
    assert plain.lag_s < lag - 0.1  # the antenna's course leads the heading by about l / v
    assert fit.lag_s == pytest.approx(lag, abs=0.03)
    assert fit.lever_m == pytest.approx(lever, abs=0.2)
    assert fit.scale == pytest.approx(1.0, abs=0.01)
    assert fit.offset == pytest.approx(bias, abs=math.radians(0.03))


def test_course_lag_with_the_scale_held_gives_the_bias():
    t_yaw = np.arange(0.0, 300.0, 0.01)
    yaw = np.full(len(t_yaw), math.radians(0.4)) + RNG.normal(0, math.radians(0.1), len(t_yaw))  # straight on
    t_fix = np.arange(2.0, 298.0, 1.0)
    course = np.mod(1.0 + RNG.normal(0, math.radians(0.2), len(t_fix)), 2 * math.pi)
    fit = course_lag(t_fix, course, np.full(len(t_fix), 15.0), t_yaw, yaw, fixed_scale=1.0)
    assert fit is not None and fit.scale == 1.0
    assert fit.offset == pytest.approx(math.radians(0.4), abs=math.radians(0.03))


@given(
    st.lists(st.floats(-1e3, 1e3), max_size=60),
    st.lists(st.tuples(st.integers(0, 60), st.floats(-1e3, 1e3)), max_size=10),
)
def test_series_keeps_what_a_deque_trimmed_by_its_second_pair_keeps(times, trims):
    """The learner's CAN speeds: the same pairs as the deque they replaced, popped from the front while more than
    two remain and the second is before the trim time (in or out of order), at every length and trim."""
    series, pairs = TimeSeries(), deque()
    for i, t in enumerate(times):
        series.append(t, float(i))
        pairs.append((t, float(i)))
        for at, t_min in trims:
            if at == i:
                series.trim(t_min, keep=2)
                while len(pairs) > 2 and pairs[1][0] < t_min:
                    pairs.popleft()
        assert len(series) == len(pairs)
        t, v = series.columns()
        assert t.tolist() == [p[0] for p in pairs] and v.tolist() == [p[1] for p in pairs]
