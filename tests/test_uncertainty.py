"""Error estimates (issue 13): gpsd's 95 % figures, their JSON and NMEA (GST, GGA) output, every estimator's through
an outage, the MHE's SU bound box on a bounded-noise drive, and the calibration figures of the benchmarks."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pynmea2
import pytest

from sumhe.baseline.ekf import Ekf
from sumhe.bench import metrics, report
from sumhe.bench.mhe import drive_stream
from sumhe.bench.report import calibration_cells
from sumhe.commands.candump import reference_config
from sumhe.estimator.base import Receiver, StateEstimate, StreamEstimator, predicted_at, sensor_drift, to_estimate
from sumhe.estimator.registry import make_estimator
from sumhe.estimator.uncertainty import (
    K1,
    K2,
    MIN_GROWTH_SCALE,
    OUTLIER_CAP,
    InnovationScale,
    Spread,
    drift_variance,
    exact_radius_95,
    gpsd_errors,
    radius_95,
)
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.stream import FixMeasurement
from sumhe.geo import LocalFrame
from sumhe.io.nmea_format import nmea_checksum
from sumhe.io.udp import encode_json, encode_nmea
from sumhe.messages import ErrorEstimate, Estimate
from sumhe.settings import EstimationSettings, with_changes
from sumhe.settings.peers import EKF_TUNED
from sumhe.sim import SimSettings, simulate

from estimators import estimator_params


@pytest.mark.parametrize("q", [0.0, 1e-3, 0.01, 0.3, 0.7, 0.99, 1.0])
def test_exact_radius_95_holds_95_percent_by_an_independent_quadrature(q: float) -> None:
    """The radius against the Cartesian form of the probability, integrated adaptively by scipy: ``P(r) = E_x[2
    Phi(sqrt(r^2 - x^2) / q) - 1 ; |x| < r]`` for a major sigma of 1 (the 1-D answer where ``q`` is 0), split where
    the inner probability falls from 1 to 0 (``r^2 - x^2 < (8 q)^2``: narrow for a thin ellipse)."""
    from scipy.integrate import quad
    from scipy.stats import norm

    r = exact_radius_95(2.0, 2.0 * q) / 2.0
    if q == 0.0:
        held = norm.cdf(r) - norm.cdf(-r)
    else:
        inner = lambda x: norm.pdf(x) * (2.0 * norm.cdf(math.sqrt(max(r * r - x * x, 0.0)) / q) - 1.0)  # noqa: E731
        edge = math.sqrt(max(r * r - 64.0 * q * q, 0.0))
        held = quad(inner, -r, r, epsabs=1e-13, epsrel=1e-13, limit=500, points=[-edge, 0.0, edge])[0]
    assert held == pytest.approx(0.95, abs=1e-9)


@pytest.mark.parametrize(("s1", "s2"), [(2.0, 2.0), (2.0, 1.0), (3.0, 0.3), (1.0, 0.01)])
def test_radius_95_holds_95_percent_of_a_gaussian_error(s1: float, s2: float) -> None:
    e = np.random.default_rng(7).standard_normal((400_000, 2)) * [s1, s2]
    r = radius_95(s1, s2)
    assert np.mean(np.hypot(*e.T) <= r) == pytest.approx(0.95, abs=0.002)
    assert r == pytest.approx(exact_radius_95(s1, s2), rel=2e-3)
    assert K1 * s1 <= r <= K2 * s1 + 1e-9


def test_gpsd_figures_of_a_spread() -> None:
    # 2 m east, 1 m north, correlated: the ellipse's major axis points north-east of east
    spread = Spread(var_east_m2=4.0, var_north_m2=1.0, cov_en_m2=1.0, sigma_speed_mps=0.1, sigma_azimuth_rad=0.01)
    err = gpsd_errors(spread)
    assert err.epx_m == pytest.approx(1.96 * 2.0, rel=1e-3)
    assert err.epy_m == pytest.approx(1.96 * 1.0, rel=1e-3)
    assert err.eps_mps == pytest.approx(0.196, rel=1e-3)
    assert err.epd_rad == pytest.approx(0.0196, rel=1e-3)
    values, vectors = np.linalg.eigh([[4.0, 1.0], [1.0, 1.0]])
    assert err.sigma_major_m == pytest.approx(math.sqrt(values[1]))
    assert err.sigma_minor_m == pytest.approx(math.sqrt(values[0]))
    east, north = vectors[:, 1]
    assert err.orient_rad == pytest.approx(math.atan2(east, north) % math.pi)
    assert 60.0 < math.degrees(err.orient_rad) < 90.0
    assert err.eph_m == pytest.approx(radius_95(err.sigma_major_m, err.sigma_minor_m))


def _estimate(gps: str = "outage") -> Estimate:
    error = ErrorEstimate(
        eph_m=5.0,
        epx_m=3.92,
        epy_m=2.94,
        eps_mps=0.2,
        epd_rad=math.radians(1.5),
        sigma_major_m=2.1,
        sigma_minor_m=1.4,
        orient_rad=math.radians(80.0),
        sigma_east_m=2.0,
        sigma_north_m=1.5,
    )
    return Estimate(
        t=1_780_000_000.25,
        east_m=1.0,
        north_m=2.0,
        lat_deg=50.1,
        lon_deg=14.4,
        alt_m=200.0,
        track_rad=0.5,
        speed_mps=12.0,
        yaw_rate_rps=0.01,
        gps=gps,  # type: ignore[arg-type]
        mode="mhe",
        bound_east_m=7.5,
        bound_north_m=6.5,
        error=error,
        sats=0 if gps != "ok" else 9,
        hdop=2.4,
    )


def test_json_carries_gpsd_error_fields_and_the_bound() -> None:
    out = json.loads(encode_json(_estimate()))
    assert out["eph"] == 5.0 and out["epx"] == 3.92 and out["epy"] == 2.94 and out["eps"] == 0.2
    assert out["epd"] == pytest.approx(1.5)  # degrees at the edge
    assert out["bound_east"] == 7.5 and out["bound_north"] == 6.5
    assert out["sats"] == 0 and out["hdop"] == 2.4
    bare = json.loads(encode_json(Estimate(**{**_fields(_estimate()), "error": None, "sats": None, "hdop": None})))
    assert not {"eph", "epx", "epy", "eps", "epd", "sats", "hdop"} & bare.keys()


def _fields(est: Estimate) -> dict:
    return {name: getattr(est, name) for name in est.__dataclass_fields__}


@pytest.mark.parametrize("gps", ["ok", "outage"])
def test_nmea_has_gga_with_satellites_and_hdop_and_a_gst(gps: str) -> None:
    lines = encode_nmea(_estimate(gps)).decode("ascii").split("\r\n")
    assert lines[-1] == "" and len(lines) == 4
    for line in lines[:-1]:
        body, checksum = line[1:].split("*")
        assert checksum == nmea_checksum(body)
    gga, rmc, gst = (pynmea2.parse(line) for line in lines[:3])
    assert (gga.sentence_type, rmc.sentence_type, gst.sentence_type) == ("GGA", "RMC", "GST")
    assert int(gga.num_sats) == (9 if gps == "ok" else 0)
    assert float(gga.horizontal_dil) == 2.4
    assert gga.gps_qual == (1 if gps == "ok" else 6)
    _, rms, major, minor, orient, sigma_lat, sigma_lon, sigma_alt = gst.data
    assert (float(sigma_lat), float(sigma_lon)) == (1.5, 2.0)
    assert (float(major), float(minor)) == (2.1, 1.4) and float(orient) == pytest.approx(80.0)
    assert rms == "" and sigma_alt == ""
    assert gst.timestamp == gga.timestamp


def test_no_gst_without_an_error_estimate() -> None:
    lines = encode_nmea(Estimate(**{**_fields(_estimate()), "error": None})).decode().split("\r\n")
    assert [line[3:6] for line in lines[:-1]] == ["GGA", "RMC"]


def test_calibration_counts_errors_within_eph_and_inside_the_box() -> None:
    # four estimates: errors (3, 4) -> 5 m, (1, 0), (0, 2), (6, 8) -> 10 m
    cols = metrics.calibration_columns(
        [3.0, 1.0, 0.0, 6.0], [4.0, 0.0, 2.0, 8.0], [6.0, 0.5, 2.0, np.nan], [3.0, 2.0, 1.0, 7.0], [4.0, 2.0, 1.0, 9.0]
    )
    c = metrics.calibration(cols)
    assert c["n"] == 3  # the one without eph is left out
    assert c["eph_coverage"] == pytest.approx(2 / 3)  # 5 <= 6 and 2 <= 2, not 1 <= 0.5
    assert c["median_eph_m"] == 2.0 and c["median_error_m"] == 2.0 and c["eph_over_error"] == 1.0
    assert c["box_n"] == 4
    assert c["box_coverage"] == pytest.approx(3 / 4)  # (0, 2) lies outside a 1 m box
    assert c["median_box_half_m"] == pytest.approx(3.0)
    cells = calibration_cells(c)
    assert "(missed)" in cells[0] and "(met)" in cells[1] and "(< 99 %)" in cells[2]
    no_box = metrics.calibration(metrics.calibration_columns([1.0], [1.0], [3.0], [np.nan], [np.nan]))
    assert no_box["box_n"] == 0 and calibration_cells(no_box)[2] == "no box"


def test_the_coverage_interval_resamples_groups_not_estimates() -> None:
    # 10 outages of 10 estimates: 9 wholly within eph, one wholly out -> 90 %, and an outage-level spread
    inside = np.repeat([True] * 9 + [False], 10)
    low, high = metrics.coverage_interval(inside, np.repeat(np.arange(10), 10))
    assert low < 0.9 < high and low <= 0.75 and high == 1.0
    assert metrics.coverage_interval(inside, np.repeat(np.arange(10), 10)) == (low, high)  # seeded
    # the same estimates as 100 independent groups: a far narrower interval around 90 %
    low_each, high_each = metrics.coverage_interval(inside, np.arange(100))
    assert low < low_each < 0.9 < high_each < high
    # every group alike: no spread at all
    assert metrics.coverage_interval(np.tile([True, False], 5), np.repeat(np.arange(5), 2)) == (0.5, 0.5)
    assert all(math.isnan(v) for v in metrics.coverage_interval([], []))


def test_the_runs_groups_stay_apart_when_their_columns_are_stacked() -> None:
    # two runs whose outages are both numbered 0 and 1: four groups, not two
    run = metrics.calibration_columns(
        [1.0, 1.0, 9.0, 9.0], [0.0] * 4, [2.0] * 4, [np.nan] * 4, [np.nan] * 4, [0, 0, 1, 1]
    )
    stacked = report._rows([run, run])
    assert list(stacked[:, -1]) == [0, 0, 1, 1, 2, 2, 3, 3]
    c = metrics.calibration(stacked)
    assert c["groups"] == 4 and c["eph_coverage"] == 0.5 and c["eph_coverage_low"] < 0.5 < c["eph_coverage_high"]
    assert "% (missed) [" in calibration_cells(c)[0]


@pytest.fixture(scope="module")
def outage_drive():
    return simulate(SimSettings(scenario="urban", seed=3, duration_s=60.0, outages=((30.0, 15.0),)))


WITH_COVARIANCE = ("mhe", "ekf", "ukf", "rts", "imm", "pf", "gtsam-fls", "dead-reckoning", "mskf-em", "sr-upf")
"""The live estimators that report an error estimate (a recursive filter does through ``_covariance()``)."""


@pytest.mark.parametrize("name", estimator_params(WITH_COVARIANCE))
def test_every_estimate_has_an_error_estimate_that_grows_through_an_outage(name: str, outage_drive) -> None:
    estimator = make_estimator(name, reference_config())
    out = [e for s in drive_stream(outage_drive) for e in estimator.push(s)]
    assert out and all(e.spread is not None for e in out)
    sigma = np.array([math.sqrt(e.spread.var_east_m2 + e.spread.var_north_m2) for e in out])
    t = np.array([e.t for e in out])
    t0 = outage_drive.truth.t[0]
    inside = np.array([e.gps == "outage" for e in out]) & (t > t0 + 30.0) & (t < t0 + 45.0)
    before = (t > t0 + 20.0) & (t < t0 + 29.0) & np.array([e.gps == "ok" for e in out])
    assert inside.any() and before.any()
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    late = sigma[inside][t[inside] > t0 + 42.0]
    first = sigma[inside][np.argmin(t[inside])]
    assert late.min() > max(first, np.median(sigma[before])), (name, np.median(sigma[before]), first, late.min())
    assert all(e.sats == 0 for e in np.array(out)[inside])


@pytest.mark.slow
def test_the_mhe_bound_box_holds_the_truth_on_a_bounded_noise_drive() -> None:
    drive = simulate(
        SimSettings(scenario="urban", seed=11, duration_s=120.0, gps_error="uniform", outages=((50.0, 20.0),))
    )
    estimator = make_estimator("mhe", reference_config())
    out = [e for s in drive_stream(drive) for e in estimator.push(s)]
    out = [e for e in out if e.t > drive.truth.t[0] + 5.0]
    t = np.array([e.t for e in out])
    at = drive.truth.at(t)
    de = np.array([e.east_m for e in out]) - at.east
    dn = np.array([e.north_m for e in out]) - at.north
    be = np.array([e.bound_east_m for e in out], dtype=float)
    bn = np.array([e.bound_north_m for e in out], dtype=float)
    assert np.all(np.isfinite(be)) and np.all(np.isfinite(bn))
    inside = (np.abs(de) <= be) & (np.abs(dn) <= bn)
    assert inside.mean() >= 0.99, inside.mean()
    outage = np.array([e.gps == "outage" for e in out])
    assert np.median(be[outage]) > np.median(be[~outage])  # the set grows while no fix cuts it


def test_a_filter_without_a_covariance_sends_no_error_estimate(outage_drive) -> None:
    class NoCovariance(Ekf):
        def _covariance(self) -> None:
            return None

    frame = LocalFrame(50.0, 14.0, 0.0)
    out = [e for s in drive_stream(outage_drive)[:3000] for e in NoCovariance().push(s)]
    assert out and all(e.spread is None for e in out)
    sent = json.loads(encode_json(to_estimate(out[-1], frame)))
    assert "lat" in sent and not {"eph", "epx", "epy", "eps", "epd"} & sent.keys()


def _innovations(scale: InnovationScale, n: int, var_p: float, var_r: float, var_g: float, periods: float) -> None:
    """``n`` fixes at 1 s whose innovations have the covariance ``var_p + var_g + var_r`` per axis, fed to ``scale``
    as predictions of own variance ``1`` at the fix and ``1`` of growth (per axis) and fixes of variance ``var_r``."""
    rng = np.random.default_rng(5)
    t0 = scale._fix.t if math.isfinite(scale._fix.t) else 0.0
    for k in range(n):
        nu = rng.standard_normal(2) * math.sqrt(var_p + var_g + var_r)
        scale.add(t0 + 1.0 + k, nu, 2.0 * var_r, 2.0, 2.0 if var_g else 0.0, periods)


def test_the_consistency_scale_is_one_for_consistent_innovations_and_rises_for_too_large_ones() -> None:
    scale = InnovationScale()
    assert scale.scale == 1.0 and scale.growth_scale == 1.0  # nothing seen: the estimator's own figures
    _innovations(scale, 2000, var_p=1.0, var_r=4.0, var_g=0.0, periods=1.0)
    assert scale.scale == pytest.approx(1.0, abs=0.4) and scale.growth_scale == scale.scale
    # an overconfident filter: its prediction errs 3 times as far as its covariance says (9 times the variance)
    _innovations(scale, 2000, var_p=9.0, var_r=4.0, var_g=0.0, periods=1.0)
    assert scale.scale == pytest.approx(9.0, rel=0.2)
    assert scale.growth_scale == scale.scale  # no gap seen: the growth taken as overconfident as the fix
    # fixes after gaps: the drift through them is 4 times the growth the estimator claimed (variance)
    _innovations(scale, 2000, var_p=9.0, var_r=4.0, var_g=4.0, periods=30.0)
    assert scale.growth_scale == pytest.approx(4.0, rel=0.25)
    assert scale.scale == pytest.approx(9.0, rel=0.2)  # the gaps leave the scale at a fix alone
    scale.reset()
    assert scale.scale == 1.0 and scale.growth_scale == 1.0


def test_the_fixes_correlated_error_is_not_taken_for_the_estimators() -> None:
    # fixes with a slow offset (1.9 m per axis, which the estimate shares) and a small white error (0.3 m): the
    # estimator lags them by 2 m per axis (correlated over 10 s) where its covariance says 1 m; subtracting the
    # fixes' whole variance from the innovations' saw nothing wrong (a scale of 1)
    rng = np.random.default_rng(7)
    scale = InnovationScale()
    lag, seen = np.zeros(2), []
    for k in range(3000):
        lag = 0.9 * lag + 2.0 * math.sqrt(1.0 - 0.81) * rng.standard_normal(2)
        nu = lag + 0.3 * rng.standard_normal(2)
        scale.add(float(k), nu, 2.0 * (1.9**2 + 0.3**2), 2.0, 0.0, 1.0)
        seen.append(scale.scale)
    # E|nu|^2 = 8.2 m^2; the white part read from the changes of nu, 1 m^2 (the lag's own changes included)
    assert np.mean(seen[100:]) == pytest.approx(3.6, rel=0.2)


def test_an_outlier_after_a_gap_moves_the_growth_scale_a_bounded_step() -> None:
    scale = InnovationScale()
    _innovations(scale, 300, var_p=1.0, var_r=4.0, var_g=1.0, periods=30.0)
    before = scale.growth_scale
    assert before == pytest.approx(1.0, abs=0.5)
    # the first fix after a gap lies 500 m from the prediction (an outlier, a filter's re-acquisition): without
    # the cap its square alone made the growth scale tens of thousands
    scale.add(scale._growth.t + 30.0, np.array([500.0, 0.0]), 8.0, 2.0 * scale.scale, 2.0, 30.0)
    assert before < scale.growth_scale <= 1.2 * OUTLIER_CAP * before
    # a fix the estimator restarted at is not fed, and the next innovation's change is not taken for white error
    scale.skip()
    assert scale._last is None


def test_a_consistent_or_underconfident_covariance_at_a_fix_is_never_shrunk() -> None:
    scale = InnovationScale()
    _innovations(scale, 500, var_p=0.01, var_r=4.0, var_g=0.0, periods=1.0)
    assert scale.scale == 1.0 and scale.growth_scale == 1.0


def test_the_part_of_the_covariance_at_a_fix_a_considered_parameter_makes_is_shrunk_to_what_the_fixes_say() -> None:
    # the own covariance at a fix says 1 m^2 per axis, the innovations a quarter of it: the floor at 1 holds the
    # estimator's own statistics (the fixes' slow error the innovations cannot see), not a considered parameter's
    # part (a heading's offset read from its bound: a lag behind the fixes, which the innovations see)
    scale = InnovationScale()
    _innovations(scale, 3000, var_p=0.25, var_r=0.01, var_g=0.0, periods=1.0)
    assert scale.scale == 1.0
    at_fix = Spread(1.0, 1.0, 0.0, 0.1, 0.01)
    assert scale.at_fix_m2(2.0) == 2.0 and scale.calibrated(at_fix, at_fix).var_east_m2 == 1.0
    shrunk = scale.at_fix_m2(2.0, 2.0)  # all of it considered: what the innovations say
    assert shrunk == pytest.approx(0.5, rel=0.4)
    assert scale.at_fix_m2(2.0, 1.0) == 1.0  # at least the own covariance less the considered part
    assert scale.calibrated(at_fix, at_fix, 0.0, 2.0).var_east_m2 == pytest.approx(0.5 * shrunk)
    grown = Spread(2.0, 2.0, 0.0, 0.1, 0.01)  # the growth since is scaled as before
    assert scale.calibrated(grown, at_fix, 0.0, 2.0).var_east_m2 == pytest.approx(
        0.5 * shrunk + scale.growth_scale * scale.growth_spread
    )


def test_an_underconfident_growth_is_shrunk_to_what_the_gaps_say() -> None:
    # an estimator whose own growth through gaps is 4 times what the fixes after them find (variance): the MHE,
    # whose growth from the bounds read as sigmas was 15-100 times the real drive's; under the old rule (at
    # least 1) its eph was 4.3-5.3 times its median error there
    scale = InnovationScale()
    _innovations(scale, 500, var_p=1.0, var_r=0.25, var_g=0.0, periods=1.0)
    _innovations(scale, 500, var_p=1.0, var_r=0.25, var_g=0.25, periods=30.0)
    assert scale.scale == pytest.approx(1.0, abs=0.3)
    assert scale.growth_scale == pytest.approx(0.25, abs=0.1)
    # innovations below even the fix's own errors: the growth scale stays positive
    _innovations(scale, 500, var_p=0.0, var_r=0.25, var_g=1e-6, periods=30.0)
    assert MIN_GROWTH_SCALE <= scale.growth_scale < 0.01


def test_a_gap_too_short_to_grow_does_not_move_the_growth_scale() -> None:
    # a fix or two missed: the estimator's own growth since (0.0003 m^2) is nothing beside its error at the fix
    # and the fix's (25 m^2), so the innovation says nothing of the growth. The old rule (a ratio of sums,
    # (|nu|^2 - fixed) / growth = -16000) took the growth scale to its floor, and a 56 s outage that followed on a
    # realistic highway drive had an eph of 5 m against errors to 31 m
    scale = InnovationScale()
    scale.add(0.0, np.zeros(2), 5.0, 20.0, 0.0, 1.0)
    scale.add(1.0, np.array([2.0, 1.0]), 5.0, 20.0, 3e-4, 10.0)
    assert scale.growth_scale == pytest.approx(1.0, rel=0.01)
    at_fix, outage = Spread(0.5, 0.5, 0.0, 0.1, 0.01), Spread(150.0, 150.0, 0.0, 0.1, 0.01)
    grown = scale.calibrated(outage, at_fix)
    assert grown.var_east_m2 + grown.var_north_m2 > 299.0  # the estimator's own growth, at least
    # nor to 10^4 when its innovation is large: a gap whose growth is 10^-8 of the fixed part cannot tell
    scale.add(2.0, np.array([20.0, 0.0]), 5.0, 20.0, 3e-7, 10.0)
    assert scale.growth_scale < 2.0
    # an informative gap (its growth as large as the rest) then sets it, as a ratio would
    scale.add(60.0, np.array([20.0, 0.0]), 5.0, 20.0, 200.0, 60.0)
    assert scale.growth_scale == pytest.approx((400.0 - 25.0) / 200.0, rel=0.1)


def test_the_change_of_the_fixes_slow_error_over_a_short_gap_is_not_taken_for_growth() -> None:
    # fixes whose error is a slow offset (2.25 m^2 per axis) and little white error (the residuals' changes from one
    # fix to the next: 0.01 m^2 per axis); after three fixes missed the offset has moved by 1.5 m, which the
    # estimator, whose own growth in 0.3 s was 0.0004 m^2, cannot have followed. Taken for growth (the change's
    # expected square only the white errors), it made the growth scale thousands (gtsam-fls 3049 eight seconds into a
    # realistic drive, its eph over the 55 s outage that followed 47 times its error); the offset's change lies
    # between nothing and the two fixes' slow errors independent, and explains it
    scale = InnovationScale()
    rng = np.random.default_rng(3)
    for k in range(100):
        nu = 0.1 * rng.standard_normal(2)
        scale.add(0.1 * k, nu, 4.5, 1.0, 0.0, 1.0, residual=nu)
    assert scale.white_m2(4.5) == pytest.approx(0.02, rel=0.3)
    scale.add(10.2, np.array([1.4, 0.5]), 4.5, 1.0, 4e-4, 3.0, residual=np.array([0.1, 0.0]))
    assert scale.growth_scale < 3.0
    # a change far beyond what the slow error allows is growth, as before: (|nu|^2 less the slow error) / growth
    scale.add(40.0, np.array([20.0, 0.0]), 4.5, 1.0, 200.0, 300.0, residual=np.array([0.1, 0.0]))
    assert scale.growth_scale == pytest.approx((400.0 - 4.5) / 200.0, rel=0.1)


def test_the_slow_error_of_a_poorer_fix_before_a_gap_is_not_taken_for_growth() -> None:
    # the fix before the gap said 7 m per axis (trace 98 m^2) and was off by that much, the fix after it 1 m: their
    # slow errors' change squares to between (7 - 1)^2 and 7^2 + 1^2 per axis, not to between 0 and twice the fix
    # after the gap's. Dead reckoning, which took the first fix as it was, had a growth scale of 5.4 after the first
    # 10 s outage of the shared real drive (its own growth 17 m^2 there; 3.9 with the fix's own variance counted)
    def learned(trace_before: float) -> float:
        scale = InnovationScale()
        rng = np.random.default_rng(3)
        for k in range(100):
            nu = 0.1 * rng.standard_normal(2)
            scale.add(0.1 * k, nu, trace_before, 1.0, 0.0, 1.0, residual=nu)
        scale.add(20.0, np.array([7.0, 7.0]), 2.0, trace_before, 10.0, 100.0, residual=np.zeros(2))
        return scale.growth_scale

    assert learned(98.0) < 2.0
    assert learned(2.0) > 5.0  # the same change after a fix that said 1 m is growth


def test_gaps_that_say_nothing_of_the_growth_leave_what_the_others_said() -> None:
    # ten 30 s gaps find the growth 4 times too small; then a burst of fixes missed one at a time, each innovation
    # all the fix's and the estimate's own error: the old rule dragged the scale down by their negative excess
    scale = InnovationScale()
    _innovations(scale, 300, var_p=1.0, var_r=0.25, var_g=4.0, periods=30.0)
    learned = scale.growth_scale
    assert learned == pytest.approx(4.0, rel=0.25)
    t = scale._growth.t
    for k in range(20):
        scale.add(t + 1.0 + k, np.array([0.1, 0.0]), 0.5, 2.0, 1e-4, 3.0)
    assert scale.growth_scale == pytest.approx(learned, rel=0.1)


def test_the_lag_the_estimate_carries_through_a_gap_is_not_taken_for_growth() -> None:
    # an estimator whose residuals were centimetres (its covariance at a fix right) falls 4 m behind the fixes in a
    # turn just before they stop, and carries that lag through a 30 s gap in which it drifts by 2 m^2 as its own
    # growth says: the fix after the gap lies the lag plus the drift from the prediction. Against the prediction
    # (the expected square at the fix and the white error, not this lag) the gap said 12 times the growth, and so
    # did the MHE's first gaps of a realistic drive, its lag at their start not yet in the scale at a fix (up to
    # 1315); the innovation's change over the gap holds the drift alone
    def learned(skip: bool) -> float:
        scale = InnovationScale()
        for k in range(100):
            scale.add(float(k), np.array([0.1, 0.0]), 0.0, 2.0, 0.0, 1.0)
        scale.add(100.0, np.array([4.0, 0.0]), 0.0, 2.0, 0.0, 1.0)
        if skip:
            scale.skip()  # the residual before the gap unknown: measured against the prediction
        scale.add(130.0, np.array([5.0, 1.0]), 0.0, 2.0, 2.0, 30.0, residual=np.array([0.2, 0.1]))
        return scale.growth_scale

    assert learned(skip=False) == pytest.approx(1.0, rel=0.05)
    assert learned(skip=True) > 10.0


def test_a_growth_scale_learned_from_few_gaps_widens_the_growth_by_the_predictive_factor() -> None:
    # one gap says little of the growth's variance: the 95 % radius of the next error, with the variance
    # estimated from n 2-D errors, is sqrt(2 F_0.95(2, 2n) / chi2_2(0.95)) Gaussian radii (2.5 for n = 1)
    scale = InnovationScale()
    assert scale.growth_spread == 1.0  # no gap: the prior (the scale at a fix) as it is
    at_fix, later = Spread(1.0, 1.0, 0.0, 0.1, 0.01), Spread(2.0, 2.0, 0.0, 0.1, 0.01)
    scale.add(30.0, np.array([2.0, 0.0]), 0.0, 2.0, 2.0, 30.0)  # no residual before it: against the prediction
    assert scale.growth_scale == pytest.approx(1.0, rel=1e-3)  # (4 - 2) / 2, to the likelihood grid's resolution
    assert scale.growth_spread == pytest.approx(6.34, rel=0.01)
    assert scale.calibrated(later, at_fix).var_east_m2 == pytest.approx(0.5 * (2.0 + 2.0 * 6.34), rel=0.01)
    # many gaps (the sums forget in 300 s: gaps 30 s apart weigh as 20): the factor near 1, the Gaussian radius
    for k in range(2, 200):
        scale.add(30.0 * k, np.array([2.0, 0.0]), 0.0, 2.0, 2.0, 30.0)
    assert scale.growth_scale == pytest.approx(1.0, rel=1e-3) and 1.0 < scale.growth_spread < 1.1


@pytest.mark.parametrize("n", [1.0, 1.5, 3.0, 20.0, 1e4])
def test_the_predictive_factor_in_closed_form_is_scipys_quantiles(n: float) -> None:
    from scipy.stats import chi2, f

    from sumhe.estimator.uncertainty import _predictive

    expected = 2.0 * f.ppf(0.95, 2.0, 2.0 * n) / chi2.ppf(0.95, 2.0)
    assert _predictive(n) == pytest.approx(expected, rel=1e-12)


def test_the_calibrated_spread_scales_the_covariance_at_the_fix_and_its_growth_apart() -> None:
    scale = InnovationScale()
    _innovations(scale, 3000, var_p=9.0, var_r=4.0, var_g=0.0, periods=1.0)
    _innovations(scale, 3000, var_p=9.0, var_r=4.0, var_g=4.0, periods=30.0)
    c, g = scale.scale, scale.growth_scale * scale.growth_spread
    at_fix = Spread(1.0, 1.0, 0.0, 0.1, 0.01)
    later = Spread(3.0, 1.0, 0.5, 0.2, 0.02)  # grew by 2 m^2 east since the fix
    out = scale.calibrated(later, at_fix)
    factor = (c * 2.0 + g * 2.0) / 4.0
    assert out.var_east_m2 == pytest.approx(3.0 * factor) and out.var_north_m2 == pytest.approx(factor)
    assert out.cov_en_m2 == pytest.approx(0.5 * factor)
    assert (out.sigma_speed_mps, out.sigma_azimuth_rad) == (0.2, 0.02)  # only the position is checked by fixes
    assert scale.calibrated(at_fix, None).var_east_m2 == pytest.approx(c)  # no fix yet: all of it is at a fix


def _state(t: float, east: float, var: float | None) -> StateEstimate:
    spread = None if var is None else Spread(var, var, 0.0, 0.1, 0.01)
    return StateEstimate(t, east, -east, 0.0, 10.0, 0.0, "ok", "x", spread=spread)


def test_the_prediction_of_a_fix_is_interpolated_from_the_estimates_since_the_previous_epoch() -> None:
    # the epoch's estimate may come after CAN-rate ones of later times (the Kalman family): sorted by time
    estimates = [_state(10.0, 0.0, 1.0), _state(10.5, 5.0, 2.0), _state(10.2, 2.0, 1.5), _state(10.4, 9.0, None)]
    east, north, trace = predicted_at(estimates, 10.35)
    assert east == pytest.approx(3.5) and north == pytest.approx(-3.5) and trace == pytest.approx(2 * 1.75)
    assert predicted_at(estimates, 10.0)[0] == pytest.approx(0.0)
    # later than the newest (the CAN data lag the fix): moved on with its speed (10 m/s) and azimuth (north)
    east, north, trace = predicted_at(estimates, 10.7)
    assert (east, north, trace) == pytest.approx((5.0, -3.0, 4.0))
    assert predicted_at(estimates, 10.7, ahead_s=0.1) is None  # too far on (a gap in the CAN data): no prediction
    assert predicted_at(estimates, 9.9) is None
    assert predicted_at([], 10.0) is None


def test_an_overconfident_filter_gets_a_consistency_scale_and_wider_error_estimates(outage_drive) -> None:
    # little process noise and CAN sigmas far below the sensors': a covariance of centimetres on a filter that
    # trusts its dead reckoning and lags the fixes by metres; the same filter tuned is less so (on this drive its
    # squared error with GPS is still 29 times its own trace: a scale of 6 at a fix)
    tuned, overconfident = Ekf(), Ekf(noise=OVERCONFIDENT)
    for estimator in (tuned, overconfident):
        out = [e for s in drive_stream(outage_drive) for e in estimator.push(s)]
    assert 1.0 < tuned.consistency.scale < 0.2 * overconfident.consistency.scale
    assert overconfident.consistency.scale > 10.0 and overconfident.consistency.growth_scale > 10.0
    own = overconfident._covariance()
    assert out[-1].spread is not None
    assert out[-1].spread.var_east_m2 + out[-1].spread.var_north_m2 > 10.0 * (own[0, 0] + own[1, 1])


OVERCONFIDENT = dataclasses.replace(
    EKF_TUNED,
    pos_rw=1e-6,
    heading_rw=1e-6,
    speed_rw=1e-3,
    yaw_rate_rw=1e-4,
    can_speed_mps=1e-3,
    can_yaw_rate_rps=1e-5,
    gps_scale=10.0,
)


def test_the_drift_of_the_can_calibration_is_the_least_growth_through_an_outage() -> None:
    # a filter whose covariance does not grow through an outage (process noise tuned away: the EKF on a realistic
    # highway drive, eph 4.3 m to 5.0 m over 56 s while its error reached 31 m) still gets the growth that a
    # yaw-rate bias and a speed scale drifting as the config allows make: v^2 (q_b^2 t^5 / 20 + q_s^2 t^3 / 3)
    bias, scale_drift = sensor_drift(EstimationSettings())
    assert bias == pytest.approx(0.05 * 0.02 / math.sqrt(60.0)) and scale_drift == pytest.approx(
        0.05 * 0.05 / 7.746, rel=1e-3
    )
    assert drift_variance(50.0, 20.0, 1e-4, 0.0) == pytest.approx(400.0 * 1e-8 * 50.0**5 / 20.0)
    assert drift_variance(50.0, 20.0, 0.0, 1e-3) == pytest.approx(400.0 * 1e-6 * 50.0**3 / 3.0)
    assert drift_variance(-1.0, 20.0, 1e-4, 1e-3) == 0.0
    scale = InnovationScale()
    at_fix = Spread(1.0, 1.0, 0.0, 0.1, 0.01)
    assert scale.calibrated(at_fix, at_fix).var_east_m2 == pytest.approx(1.0)  # no growth: the old rule's answer
    out = scale.calibrated(at_fix, at_fix, drift_m2=62.5)
    assert out.var_east_m2 + out.var_north_m2 == pytest.approx(2.0 + 62.5)
    # a gap's fix then measures the growth against the larger of the two (the residual at the fix before the gap
    # nil: all the innovation's change over the gap is growth)
    scale.add(0.0, np.zeros(2), 0.0, 2.0, 0.0, 1.0)
    scale.add(50.0, np.array([8.0, 0.0]), 0.0, 2.0, 0.0, 50.0, drift_m2=62.5)
    assert scale.growth_scale == pytest.approx(64.0 / 62.5, rel=0.01)


def test_the_receiver_adds_only_the_fixes_error_that_carries_from_fix_to_fix() -> None:
    # fixes of 2 m sigma per axis (8 m^2) whose innovations change by a white 1 m per axis from one fix to the next:
    # the calibrated covariance at the fix holds that white part; the offset every estimate carries is the rest
    # (the old rule added all 8 m^2, counting the white 2 m^2 twice)
    scale = InnovationScale()
    rng = np.random.default_rng(3)
    for k in range(400):
        scale.add(float(k), rng.standard_normal(2), 8.0, 2.0, 0.0, 1.0)
    white = scale.white_m2(8.0)
    assert white == pytest.approx(2.0, rel=0.15)
    fix = FixMeasurement(0.0, 0.0, 0.0, 2.0, 2.0, None, 0.01, False, None, 0.1, LocalFix(t=0.0, valid=True))
    receiver = Receiver(fix, None, True, white)
    assert receiver.var_east_m2 == pytest.approx(4.0 * (1.0 - white / 8.0))
    assert receiver.var_north_m2 == pytest.approx(receiver.var_east_m2)
    at_fix = Spread(1.0, 1.0, 0.0, 0.1, 0.01)
    spread, _, _ = receiver.tag("outage", at_fix)
    assert spread is not None and spread.var_east_m2 == pytest.approx(1.0 + 4.0 - 0.5 * white)
    # a receiver whose errors are all white (before two consecutive fixes: all of it) adds nothing; dead
    # reckoning (offset False), which takes each fix as it is, never
    assert Receiver(fix, None, True, 8.0).var_east_m2 == 0.0
    assert Receiver(fix, None, False, 0.0).var_east_m2 == 0.0


def _along_across(spread: Spread, azimuth_rad: float) -> tuple[float, float]:
    """A spread's position variances (m^2) along and across the azimuth (clockwise from north)."""
    u = np.array([math.sin(azimuth_rad), math.cos(azimuth_rad)])
    cov = np.array([[spread.var_east_m2, spread.cov_en_m2], [spread.cov_en_m2, spread.var_north_m2]])
    w = np.array([u[1], -u[0]])
    return float(u @ cov @ u), float(w @ cov @ w)


def test_the_receiver_adds_the_error_of_the_fixes_time_along_the_track_at_the_fix() -> None:
    # a fix placed on the CAN clock with an offset of 0.3 s sigma (the learner's prior before its first fit) at
    # 20 m/s heading 30 deg east of north: every estimate after it is off along that track by 6 m (1-sigma), in
    # outages too, whatever the estimate's own azimuth since; across it nothing
    fix = FixMeasurement(0.0, 0.0, 0.0, 2.0, 2.0, None, 0.01, False, None, 0.1, LocalFix(t=0.0, valid=True))
    azimuth = math.radians(30.0)
    receiver = Receiver(fix, None, False, 0.0, 0.3, (20.0, azimuth))
    own = Spread(1.0, 4.0, 0.5, 0.1, 0.01)
    for gps in ("ok", "outage"):
        spread, _, _ = receiver.tag(gps, own)  # type: ignore[arg-type]
        assert spread is not None
        along, across = _along_across(spread, azimuth)
        own_along, own_across = _along_across(own, azimuth)
        assert along == pytest.approx(own_along + 36.0) and across == pytest.approx(own_across)
    # with a learned offset (a fit's standard error of 0.02 s) the term is small; with the offset configured (a
    # calibration: the front-end reports 0 s) there is none, and a car standing still has none either
    learned, _, _ = Receiver(fix, None, False, 0.0, 0.02, (20.0, azimuth)).tag("ok", own)
    assert learned is not None and _along_across(learned, azimuth)[0] == pytest.approx(
        _along_across(own, azimuth)[0] + 0.16
    )
    for sigma_s, speed in ((0.0, 20.0), (0.3, 0.0)):
        assert Receiver(fix, None, False, 0.0, sigma_s, (speed, azimuth)).tag("outage", own)[0] == own


def test_every_estimate_carries_the_front_ends_time_offset_error(outage_drive) -> None:
    """The same drive with the time offset learned (0.3 s sigma before the learner's first fit) and configured (a
    calibration, 0 s as the front-end reports): before the learner moves the offset the estimates are the same,
    and the learned run's covariance is larger by (speed x 0.3 s)^2 along the azimuth of the estimate at the
    newest fix used (dead reckoning: the Kalman peers weigh the speed over ground by that sigma too)."""
    config = reference_config()
    learned = make_estimator("dead-reckoning", config)
    configured = make_estimator("dead-reckoning", with_changes(config, {"sensors.gnss.learn_time_offset": False}))
    assert isinstance(learned, StreamEstimator) and learned.frontend.time_offset_sigma_s == 0.3
    assert isinstance(configured, StreamEstimator) and configured.frontend.time_offset_sigma_s == 0.0
    at_fix, checked = None, 0
    for sample in drive_stream(outage_drive):
        pairs = list(zip(learned.push(sample), configured.push(sample), strict=True))
        if learned.frontend.time_offset_s != 0.0:
            break
        for a, b in pairs:
            assert (a.t, a.east_m, a.azimuth_rad) == (b.t, b.east_m, b.azimuth_rad)
            if isinstance(sample, LocalFix) and a.gps == "ok" and a.t == sample.t:
                at_fix = a  # the epoch's estimate, which used the fix
            if at_fix is not None and a.spread is not None and b.spread is not None:
                along, across = _along_across(a.spread, at_fix.azimuth_rad)
                along0, across0 = _along_across(b.spread, at_fix.azimuth_rad)
                assert along - along0 == pytest.approx((0.3 * at_fix.speed_mps) ** 2, rel=1e-6, abs=1e-9)
                assert across == pytest.approx(across0, rel=1e-6, abs=1e-9)
                checked += 1
    assert checked > 100 and at_fix is not None and at_fix.speed_mps > 1.0
