"""The bench's metrics on hand-made cases whose errors are known exactly."""

import math

import numpy as np
import pytest

from sumhe.bench import metrics
from sumhe.bench.demo import summarise
from sumhe.geo import LocalFrame
from sumhe.service.histogram import histogram_percentile, latency_histogram
from sumhe.sim import Truth


def straight_truth(speed=10.0, azimuth=math.pi / 2, duration=100.0):
    """A vehicle going east at ``speed`` m/s from the origin, 10 Hz truth."""
    t = np.arange(0.0, duration + 0.05, 0.1)
    ones = np.ones_like(t)
    east = speed * t * math.sin(azimuth)
    north = speed * t * math.cos(azimuth)
    return Truth(
        t=t,
        lat=ones,
        lon=ones,
        east=east,
        north=north,
        azimuth=np.full_like(t, azimuth % (2 * math.pi)),
        speed=speed * ones,
        yaw_rate=0 * ones,
        accel=0 * ones,
        steering=0 * ones,
        speed_scale=ones,
        yaw_rate_bias=0 * ones,
    )


def test_horizontal_errors_are_the_distances_to_the_truth_at_each_time():
    truth = straight_truth()
    t = np.array([1.0, 2.5, 50.05])  # 50.05 s lies between two truth samples: interpolated
    east = 10.0 * t + np.array([3.0, 0.0, -6.0])
    north = np.array([4.0, -2.0, 8.0])
    np.testing.assert_allclose(metrics.horizontal_errors(t, east, north, truth), [5.0, 2.0, 10.0], atol=1e-9)


def test_split_by_interval_puts_each_error_in_its_outage_and_the_rest_after_the_warm_up_with_gps():
    t = np.array([0.0, 5.0, 10.0, 12.0, 19.9, 20.0, 30.0, 31.0, 40.0])
    err = np.arange(len(t), dtype=float)
    outages = [(10.0, 20.0), (30.0, 35.0)]  # half-open: 20.0 is after the first outage
    inside, with_gps = metrics.split_by_interval(t, err, outages, after=5.0)
    np.testing.assert_array_equal(inside[0], [2.0, 3.0, 4.0])
    np.testing.assert_array_equal(inside[1], [6.0, 7.0])
    np.testing.assert_array_equal(with_gps, [1.0, 5.0, 8.0])  # 0.0 is the warm-up
    np.testing.assert_array_equal(metrics.interval_index(t, outages), [-1, -1, 0, 0, 0, -1, 1, 1, -1])


def test_mean_p95_max_of_known_values_and_of_nothing():
    mean, p95, mx = metrics.mean_p95_max(np.arange(1.0, 101.0))
    assert mean == pytest.approx(50.5)
    assert p95 == pytest.approx(95.05)  # linear interpolation between the 95th and 96th value
    assert mx == 100.0
    assert all(math.isnan(v) for v in metrics.mean_p95_max([]))


def test_angle_errors_wrap_around():
    deg = np.radians
    got = metrics.angle_errors(deg([359.0, 1.0, -179.0, 180.0, 90.0, 720.5]), deg([1.0, 359.0, 179.0, 0.0, 90.0, 0.0]))
    np.testing.assert_allclose(np.degrees(got), [2.0, 2.0, 2.0, 180.0, 0.0, 0.5], atol=1e-9)


def test_heading_errors_against_a_truth_heading_north_across_the_wrap():
    truth = straight_truth(azimuth=2 * math.pi - 0.01)  # just west of north: the truth stores 6.273 rad
    t = np.array([10.0, 20.0])
    np.testing.assert_allclose(metrics.heading_errors(t, [0.01, 2 * math.pi - 0.05], truth), [0.02, 0.04], atol=1e-9)


def test_geodetic_errors_of_positions_given_as_latitude_and_longitude():
    frame = LocalFrame(50.0, 14.0, 250.0)
    truth = straight_truth()
    t = np.array([3.0, 7.0])
    east = 10.0 * t + np.array([0.0, 6.0])
    north = np.array([-1.5, 8.0])
    lla = frame.to_geodetic(east, north, 0.0)
    err = metrics.geodetic_errors(t, lla[:, 0], lla[:, 1], truth, frame)
    np.testing.assert_allclose(err, [1.5, 10.0], atol=1e-3)


def test_latency_percentiles_from_merged_histograms():
    fast = latency_histogram(np.full(990, 1.0))
    slow = latency_histogram(np.full(10, 100.0))
    merged = fast + slow
    assert merged.sum() == 1000
    assert histogram_percentile(merged, 50.0) == pytest.approx(1.0, rel=0.025)
    assert histogram_percentile(merged, 99.5) == pytest.approx(100.0, rel=0.025)
    assert math.isnan(histogram_percentile(latency_histogram([]), 50.0))
    values = np.random.default_rng(1).lognormal(-3.0, 1.5, 20_000)
    for q in (50.0, 99.0):
        exact = metrics.percentiles(values, (q,))[0]
        assert histogram_percentile(latency_histogram(values), q) == pytest.approx(exact, rel=0.03)
    # beyond the edges: counted in the end bins, never lost
    assert latency_histogram([0.0, 1e9]).sum() == 2


def test_percentiles_and_throughput():
    assert metrics.percentiles(np.arange(101.0), (50.0, 99.0)) == (50.0, 99.0)
    assert all(math.isnan(v) for v in metrics.percentiles([], (50.0, 99.0)))
    assert metrics.throughput(120.0, 2.0) == 60.0
    assert math.isnan(metrics.throughput(120.0, 0.0))
    assert math.isnan(metrics.throughput(0.0, 1.0))


def test_demo_summary_splits_json_estimates_by_their_gps_flag():
    frame = LocalFrame(50.0, 14.0, 250.0)
    truth = straight_truth()
    records = []
    for t, offset, gps in ((1.0, 1.0, "ok"), (2.0, 3.0, "ok"), (3.0, 10.0, "outage"), (4.0, 20.0, "rejected")):
        lat, lon, _ = frame.to_geodetic(10.0 * t, offset)
        records.append({"t": t, "lat": lat, "lon": lon, "gps": gps})
    s = summarise(records, truth, frame)
    assert (s.n_ok, s.n_outage) == (2, 2)
    np.testing.assert_allclose(s.ok, (2.0, 2.9, 3.0), atol=1e-3)
    np.testing.assert_allclose(s.outage, (15.0, 19.5, 20.0), atol=1e-3)
    empty = summarise([], truth, frame)
    assert (empty.n_ok, empty.n_outage) == (0, 0)
    assert math.isnan(empty.ok[0])


def test_errors_net_of_the_gnss_offset_each_outage_starts_from():
    truth = straight_truth()
    # fixes every 0.1 s, off by (+1, -2) m before 30 s and by (-3, 0) m after
    t_fix = np.arange(0.0, 60.0, 0.1)
    off = np.where(t_fix[:, None] < 30.0, [1.0, -2.0], [-3.0, 0.0])
    at = truth.at(t_fix)
    offsets = metrics.offsets_before(t_fix, at.east + off[:, 0], at.north + off[:, 1], truth, [20.0, 40.0, -5.0], 10)
    np.testing.assert_allclose(offsets[:2], [[1.0, -2.0], [-3.0, 0.0]], atol=1e-9)
    assert np.isnan(offsets[2]).all()  # no fix before it
    # estimates that kept the offset of the outage's start are 0 m off net of it; one outside the outages is left out
    t = np.array([21.0, 25.0, 41.0, 35.0])
    est = truth.at(t)
    east = est.east + np.array([1.0, 1.0, -3.0 + 4.0, 0.0])
    north = est.north + np.array([-2.0, 1.0, 3.0, 0.0])
    net = metrics.net_errors(t, east, north, truth, [(20.0, 30.0), (40.0, 50.0)], offsets[:2])
    np.testing.assert_allclose(net, [0.0, 3.0, 5.0], atol=1e-9)
