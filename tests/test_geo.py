"""WGS84 <-> local east/north/up: round trips, independent references, poles and the antimeridian."""

from __future__ import annotations

import math

import numpy as np
import pymap3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sumhe.geo import WGS84_A, LocalFrame, ecef_to_geodetic, geodetic_to_ecef

MM = 1e-3

# Reference values from GeographicLib's CartConvert 2.1.2 (C. Karney; Debian package geographiclib-tools),
# `CartConvert -p 9` for geocentric and `CartConvert -p 9 -l LAT0 LON0 H0` for local cartesian coordinates.
CARTCONVERT_ECEF = [
    ((33.3, 44.4, 6000.0), (3816209.604493091, 3737108.550254264, 3485109.572568041)),  # its manual's example
    ((-45.877567167, 170.500111333, 16.0), (-4387108.489204372, 734141.417476616, -4555795.368888582)),
    ((89.9999, -120.0, 100.0), (-5.584786245, -9.673133525, 6356852.314235432)),
    ((0.0, 180.0, 0.0), (-6378137.0, 0.0, 0.0)),
    ((-33.68, 151.29, 50.0), (-4659889.894428774, 2552272.380985219, -3516992.959960065)),
]
CARTCONVERT_LOCAL = [
    ((48.1173, 11.516666667, 500.0), (48.5, 11.9, 300.0), (28329.992734636, 42627.077816534, -405.396950550)),
    ((48.1173, 11.516666667, 500.0), (47.8, 11.2, 1500.0), (-23728.002361376, -35239.742062499, 858.512139979)),
    ((89.99, 0.0, 0.0), (90.0, 0.0, 0.0), (0.0, 1116.939789807, -0.097471385)),
    ((89.99, 0.0, 0.0), (89.98, 180.0, 0.0), (0.0, 3350.819232634, -0.877242443)),  # across the pole
    ((89.99, 0.0, 0.0), (89.995, 90.0, 20.0), (558.471642401, 1116.943276212, 19.878160389)),
    ((90.0, 0.0, 0.0), (89.99, 90.0, 0.0), (1116.939789807, 0.0, -0.097471384)),  # datum on the pole
    ((90.0, 0.0, 0.0), (89.99, 180.0, 10.0), (0.0, 1116.941535136, 9.902528463)),
    ((-90.0, 45.0, 100.0), (-89.99, -90.0, 0.0), (-789.795699549, -789.795699549, -100.097471384)),
    ((0.0, 179.99, 0.0), (0.1, -179.95, 10.0), (6679.168593949, 11057.439534378, -3.146643652)),  # antimeridian
    ((0.0, 179.99, 0.0), (-0.2, 179.7, -5.0), (-32282.293825790, -22114.793702559, -125.295496760)),
]
# `CartConvert -r -p 9 -l -45.877 170.5 16`: local east, north, up -> latitude, longitude, height.
CARTCONVERT_REVERSE = [
    ((30000.0, -20000.0, 100.0), (-46.05627464573625, 170.88766311855849, 217.833226672)),
    ((-45000.0, 10000.0, -50.0), (-45.78556404953429, 169.92131328764404, 132.322284591)),
]


@pytest.mark.parametrize(("geodetic", "ecef"), CARTCONVERT_ECEF)
def test_ecef_agrees_with_geographiclib(geodetic, ecef):
    np.testing.assert_allclose(geodetic_to_ecef(*geodetic), ecef, rtol=0, atol=1e-6)
    lat, lon, h = ecef_to_geodetic(ecef)
    assert (lat, h) == (pytest.approx(geodetic[0], abs=1e-11), pytest.approx(geodetic[2], abs=1e-6))
    np.testing.assert_allclose(geodetic_to_ecef(lat, lon, h), ecef, rtol=0, atol=1e-6)  # lon, near the pole too


@pytest.mark.parametrize(("datum", "point", "enu"), CARTCONVERT_LOCAL)
def test_local_frame_agrees_with_geographiclib(datum, point, enu):
    frame = LocalFrame(*datum)
    np.testing.assert_allclose(frame.to_enu(*point), enu, rtol=0, atol=1e-6)
    back = frame.to_geodetic(*enu)
    np.testing.assert_allclose(geodetic_to_ecef(*back), geodetic_to_ecef(*point), rtol=0, atol=1e-6)


@pytest.mark.parametrize(("enu", "geodetic"), CARTCONVERT_REVERSE)
def test_local_to_geodetic_agrees_with_geographiclib(enu, geodetic):
    lat, lon, h = LocalFrame(-45.877, 170.5, 16.0).to_geodetic(*enu)
    assert (lat, lon) == (pytest.approx(geodetic[0], abs=1e-11), pytest.approx(geodetic[1], abs=1e-11))
    assert h == pytest.approx(geodetic[2], abs=1e-6)


latitudes = st.floats(-90.0, 90.0)
longitudes = st.floats(-180.0, 180.0)
heights = st.floats(-500.0, 9000.0)


@st.composite
def offsets(draw, radius_m: float = 50e3):
    """East, north (within ``radius_m`` of the datum) and up (m)."""
    r = radius_m * math.sqrt(draw(st.floats(0.0, 1.0)))
    a = draw(st.floats(0.0, 2 * math.pi))
    return r * math.sin(a), r * math.cos(a), draw(st.floats(-1000.0, 5000.0))


@settings(max_examples=400, deadline=None)
@given(latitudes, longitudes, heights, offsets())
def test_round_trips_are_exact_to_a_millimetre_within_50_km(lat0, lon0, alt0, enu):
    frame = LocalFrame(lat0, lon0, alt0)
    lat, lon, h = frame.to_geodetic(*enu)
    assert -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0
    np.testing.assert_allclose(frame.to_enu(lat, lon, h), enu, rtol=0, atol=MM)
    again = frame.to_geodetic(*frame.to_enu(lat, lon, h))
    np.testing.assert_allclose(geodetic_to_ecef(*again), geodetic_to_ecef(lat, lon, h), rtol=0, atol=MM)


@settings(max_examples=300, deadline=None)
@given(latitudes, longitudes, heights, offsets())
def test_agrees_with_pymap3d(lat0, lon0, alt0, enu):
    """pymap3d (an independent implementation) maps our geodetic point back to the same east/north/up."""
    lat, lon, h = LocalFrame(lat0, lon0, alt0).to_geodetic(*enu)
    np.testing.assert_allclose(pymap3d.geodetic2enu(lat, lon, h, lat0, lon0, alt0), enu, rtol=0, atol=MM)


def test_vectorised_calls_match_scalar_calls():
    frame = LocalFrame(52.52, 13.405, 34.0)
    e, n = np.linspace(-4e4, 4e4, 7), np.linspace(3e4, -3e4, 7)
    geo = frame.to_geodetic(e, n, 0.0)
    assert geo.shape == (7, 3)
    for i in range(7):
        np.testing.assert_allclose(geo[i], frame.to_geodetic(e[i], n[i], 0.0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(frame.to_enu(geo[:, 0], geo[:, 1], geo[:, 2])[:, :2], np.c_[e, n], rtol=0, atol=MM)


@pytest.mark.parametrize("lat0", [-60.0, 0.0, 45.0, 89.5])
def test_a_path_east_across_the_antimeridian_has_no_jump(lat0):
    frame = LocalFrame(lat0, 179.9, 0.0)
    east = np.linspace(-20e3, 40e3, 61)
    lat, lon, h = frame.to_geodetic(east, np.zeros_like(east)).T
    assert lon.min() < -179.0 and lon.max() > 179.0  # the path does cross 180 degrees
    assert np.all(np.abs(lon) <= 180.0)
    enu = frame.to_enu(lat, lon, h)
    np.testing.assert_allclose(enu[:, 0], east, rtol=0, atol=MM)
    assert np.all(np.diff(enu[:, 0]) > 0)


def test_a_path_north_over_the_pole_keeps_going_straight():
    frame = LocalFrame(89.9, 30.0, 0.0)
    north = np.linspace(0.0, 30e3, 31)  # the pole is about 11.2 km north of the datum
    lat, lon, h = frame.to_geodetic(np.zeros_like(north), north).T
    assert np.all(np.diff(lat[north < 11e3]) > 0) and np.all(np.diff(lat[north > 11.4e3]) < 0)
    beyond = north > 11.4e3
    np.testing.assert_allclose(lon[beyond], -150.0, atol=1e-6)  # the meridian opposite lon0 = 30
    np.testing.assert_allclose(frame.to_enu(lat, lon, h)[:, 1], north, rtol=0, atol=MM)
    assert np.all(h >= 0.0) and np.all(h < 71.0)  # the tangent plane rises above the ellipsoid by d^2 / 2R


def test_the_pole_itself_round_trips():
    for datum in [(90.0, 0.0, 0.0), (89.9, 0.0, 0.0), (-90.0, 120.0, 50.0)]:
        frame = LocalFrame(*datum)
        pole = math.copysign(90.0, datum[0])
        enu = frame.to_enu(pole, 0.0, 123.0)
        lat, _, h = frame.to_geodetic(*enu)
        assert lat == pytest.approx(pole, abs=1e-9) and h == pytest.approx(123.0, abs=MM)


def test_the_datum_maps_to_the_origin():
    frame = LocalFrame(-33.68, 151.29, 50.0)
    np.testing.assert_allclose(frame.to_enu(-33.68, 151.29, 50.0), 0.0, atol=1e-8)
    np.testing.assert_allclose(frame.to_geodetic(0.0, 0.0, 0.0), (-33.68, 151.29, 50.0), atol=1e-9)


def test_far_from_the_datum_the_frame_is_still_exact():
    """No zones: 500 km away the conversion is still a rigid rotation of ECEF (round trip to a millimetre)."""
    frame = LocalFrame(10.0, -75.0, 0.0)
    enu = (400e3, -300e3, 0.0)
    np.testing.assert_allclose(frame.to_enu(*frame.to_geodetic(*enu)), enu, rtol=0, atol=MM)
    assert np.linalg.norm(frame.to_enu(10.0, -75.0, -WGS84_A / 2)) == pytest.approx(WGS84_A / 2, abs=MM)


@pytest.mark.parametrize(("lat0", "lon0"), [(90.5, 0.0), (-91.0, 0.0), (math.nan, 0.0), (0.0, 180.5), (0.0, math.inf)])
def test_bad_datum_is_rejected_naming_the_field(lat0, lon0):
    with pytest.raises(ValueError, match="lat0_deg" if not -90 <= lat0 <= 90 else "lon0_deg"):
        LocalFrame(lat0, lon0)


def test_one_point_to_geodetic_equals_the_array_path():
    """The float path (math, one estimate at a time) and the numpy path are one algorithm: they agree."""
    frame = LocalFrame(50.0755, 14.4378, 250.0)
    enu = np.random.default_rng(5).uniform(-5e4, 5e4, (50, 3))
    one = np.array([frame.to_geodetic(float(e), float(n), float(u)) for e, n, u in enu])
    many = frame.to_geodetic(enu[:, 0], enu[:, 1], enu[:, 2])
    np.testing.assert_allclose(one[:, :2], many[:, :2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(one[:, 2], many[:, 2], rtol=0, atol=1e-6)


def test_point_to_geodetic_gives_to_geodetics_bits_for_floats_and_numpy_numbers() -> None:
    frame = LocalFrame(48.137, 11.575, 519.0)
    rng = np.random.default_rng(3)
    for east, north, up in rng.normal(0.0, 5000.0, (50, 3)).tolist():
        for args in ((east, north, up), (np.float64(east), np.float64(north), 0.0), (east, north, 2)):
            assert frame.point_to_geodetic(*args) == tuple(frame.to_geodetic(*args).tolist())


def test_to_enu_of_one_point_of_floats_gives_the_array_paths_bits() -> None:
    """The float path of one fix (math) carries the numpy path's operations in its order: the same bits."""
    rng = np.random.default_rng(7)
    for lat0, lon0, alt0 in ((48.137, 11.575, 519.0), (-33.68, 151.29, 50.0), (89.9, -179.9, 0.0)):
        frame = LocalFrame(lat0, lon0, alt0)
        lats = np.clip(lat0 + rng.normal(0.0, 0.3, 300), -90.0, 90.0).tolist()
        lons = (lon0 + rng.normal(0.0, 0.3, 300)).tolist()
        for lat, lon, h in zip(lats, lons, rng.uniform(-1e2, 3e3, 300), strict=True):
            numpy_path = frame.to_enu(np.float64(lat), lon, h)  # a numpy number: the array path
            assert frame.to_enu(lat, lon, float(h)).tolist() == numpy_path.tolist()
            assert frame.to_enu(lat, lon, round(h)).tolist() == frame.to_enu(np.float64(lat), lon, round(h)).tolist()
