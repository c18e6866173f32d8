import datetime as dt
import json
import math
import socket

import pytest
from hypothesis import given
from hypothesis import strategies as st

from sumhe.io.udp import UdpSender, _fixed, encode_json, estimate_to_json, iso_utc, json_line
from sumhe.messages import ErrorEstimate, Estimate


def _estimate(**kw) -> Estimate:
    base = dict(
        t=1780300800.1,
        east_m=12.3456,
        north_m=-7.5,
        lat_deg=48.1,
        lon_deg=11.5,
        alt_m=520.0,
        track_rad=-math.pi / 2,
        speed_mps=13.9,
        yaw_rate_rps=0.05,
        gps="outage",
        mode="mhe",
        window=73,
        solve_ms=2.5,
    )
    base.update(kw)
    return Estimate(**base)


@pytest.fixture
def receiver():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def test_iso_utc_has_milliseconds_and_z():
    assert iso_utc(1780300800.1) == "2026-06-01T08:00:00.100Z"


@pytest.mark.parametrize(
    "t", [1780300800.9999996, 1780300800.9999994, 1780300800.0000005, 1780300800.0000015, 0.9999999, 1.5, 1e9 + 0.1]
)
def test_iso_utc_rounds_microseconds_as_datetime_does(t):
    """The cached seconds and the millisecond arithmetic give what datetime's own formatting gives, where the
    microseconds round half to even and carry into the next second."""
    when = dt.datetime.fromtimestamp(t, tz=dt.timezone.utc)
    assert iso_utc(t) == when.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def test_json_keys_units_and_track_in_degrees():
    obj = estimate_to_json(_estimate())
    assert obj["class"] == "TPV"
    assert obj["track"] == pytest.approx(270.0)  # -90 deg wraps to 270, clockwise from north
    assert obj["gps"] == "outage"
    assert obj["east"] == pytest.approx(12.346)
    for key in ("time", "t", "lat", "lon", "alt", "north", "speed", "yaw_rate", "mode", "window", "solve_ms"):
        assert key in obj
    assert "bound_east" not in obj


def _round(value, digits):
    return None if value is None or not math.isfinite(value) else round(value, digits)


def _reference_object(est: Estimate) -> dict:
    """The TPV object built key by key (the format the README documents), for the template to match."""
    out = {
        "class": "TPV",
        "time": iso_utc(est.t),
        "t": round(est.t, 4),
        "lat": _round(est.lat_deg, 9),
        "lon": _round(est.lon_deg, 9),
        "alt": _round(est.alt_m, 3),
        "east": _round(est.east_m, 3),
        "north": _round(est.north_m, 3),
        "track": _round(math.degrees(est.track_rad) % 360.0, 3),
        "speed": _round(est.speed_mps, 3),
        "yaw_rate": _round(est.yaw_rate_rps, 5),
        "gps": est.gps,
        "mode": est.mode,
        "window": est.window,
        "solve_ms": _round(est.solve_ms, 3),
    }
    if est.error is not None:
        e = est.error
        out |= {"eph": _round(e.eph_m, 3), "epx": _round(e.epx_m, 3), "epy": _round(e.epy_m, 3)}
        out |= {"eps": _round(e.eps_mps, 3), "epd": _round(math.degrees(e.epd_rad), 3)}
    if est.bound_east_m is not None and est.bound_north_m is not None:
        out |= {"bound_east": _round(est.bound_east_m, 3), "bound_north": _round(est.bound_north_m, 3)}
    if est.sats is not None:
        out["sats"] = est.sats
    if est.hdop is not None:
        out["hdop"] = _round(est.hdop, 2)
    return out


_ANY = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([0.0, -0.0, 1e-7, 0.0005, 2.5e-5, 1e16])
_OPTIONAL = st.none() | _ANY
_ERROR = st.none() | st.builds(ErrorEstimate, *[_ANY] * 10)


@given(
    t=st.floats(0.0, 4e9) | st.sampled_from([1780300800.1, 1780300800.99995, 1e9 + 0.00005]),
    values=st.lists(_ANY, min_size=8, max_size=8),
    gps=st.sampled_from(["ok", "rejected", "outage"]),
    mode=st.sampled_from(["mhe", "mhe-widened", "can", "init", 'odd "mode"\\ é']),
    window=st.integers(0, 10**6),
    bounds=st.tuples(_OPTIONAL, _OPTIONAL),
    error=_ERROR,
    sats=st.none() | st.integers(0, 99),
    hdop=_OPTIONAL,
)
def test_json_line_is_the_text_json_writes_for_the_object(t, values, gps, mode, window, bounds, error, sats, hdop):
    """The template writes, to the character, what ``json`` writes for the object built key by key (floats as their
    ``repr``, non-finite as null, strings escaped, optional keys only where set)."""
    est = Estimate(t, *values, gps, mode, window, values[-1], *bounds, error, sats, hdop)
    line = json_line(est)
    assert line == json.dumps(_reference_object(est), separators=(",", ":"))
    assert estimate_to_json(est) == json.loads(line)


def test_non_finite_values_become_null_not_invalid_json():
    data = encode_json(_estimate(speed_mps=float("nan"), alt_m=float("inf")))
    obj = json.loads(data)  # strict JSON: NaN would not round-trip through other parsers
    assert obj["speed"] is None and obj["alt"] is None
    assert b"NaN" not in data and b"Infinity" not in data


def test_sender_delivers_one_json_object_per_datagram(receiver):
    port = receiver.getsockname()[1]
    with UdpSender([f"127.0.0.1:{port}"]) as sender:
        for i in range(3):
            sender.send(encode_json(_estimate(window=i)))
        got = [json.loads(receiver.recv(65535)) for _ in range(3)]
    assert [g["window"] for g in got] == [0, 1, 2]
    assert sender.stats.sent == 3


def test_sender_to_several_destinations_including_ipv6(receiver):
    v6 = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
    try:
        v6.bind(("::1", 0))
    except OSError:
        v6.close()
        pytest.skip("no IPv6 loopback on this machine")
    v6.settimeout(2.0)
    with v6, UdpSender([f"127.0.0.1:{receiver.getsockname()[1]}", f"[::1]:{v6.getsockname()[1]}"]) as sender:
        sender.send(b"x")
        assert receiver.recv(10) == b"x"
        assert v6.recv(10) == b"x"


def test_absent_receiver_is_not_an_error():
    free = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    free.bind(("127.0.0.1", 0))
    port = free.getsockname()[1]
    free.close()  # nothing listens there now
    with UdpSender([f"127.0.0.1:{port}"]) as sender:
        for _ in range(20):
            sender.send(b"{}")
    assert sender.stats.sent + sender.stats.refused + sender.stats.errors == 20


def test_bad_destination_is_rejected_up_front():
    with pytest.raises(ValueError, match="host:port"):
        UdpSender(["localhost"])


def test_each_format_goes_only_to_its_own_destinations(receiver):
    """The README's `gpsd -N udp://...` line receives NMEA only; a JSON client receives JSON only, each datagram
    numbered."""
    from sumhe.config import OutputSettings
    from sumhe.io.udp import UdpSink

    nmea_rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    nmea_rx.bind(("127.0.0.1", 0))
    nmea_rx.settimeout(2.0)
    json_dest = f"127.0.0.1:{receiver.getsockname()[1]}"
    nmea_dest = f"127.0.0.1:{nmea_rx.getsockname()[1]}"
    sink = UdpSink(OutputSettings(json=(json_dest,), nmea=(nmea_dest,)))
    try:
        assert sink.describe() == f"json to {json_dest}, nmea to {nmea_dest}"
        for _ in range(3):
            sink.send(_estimate())
        got_json = [receiver.recv(65535) for _ in range(3)]
        got_nmea = [nmea_rx.recv(65535) for _ in range(3)]
        receiver.settimeout(0.2)
        nmea_rx.settimeout(0.2)
        for sock in (receiver, nmea_rx):
            with pytest.raises(TimeoutError):
                sock.recv(65535)
    finally:
        sink.close()
        nmea_rx.close()
    # the JSON numbered in the order sent (a receiver may get them out of it), otherwise the estimate's own text
    objs = [json.loads(d) for d in got_json]
    assert sorted(obj.pop("seq") for obj in objs) == [0, 1, 2]
    assert all(obj == estimate_to_json(_estimate()) for obj in objs)
    assert all(d.startswith(b"$GPGGA") and b"$GPRMC" in d and b"seq" not in d for d in got_nmea)


def test_a_destination_that_does_not_resolve_is_a_config_error_naming_the_key():
    from sumhe.errors import ConfigError

    with pytest.raises(ConfigError, match=r"^c\.toml: output\.nmea: cannot resolve 'no-such-host\.invalid'"):
        UdpSender(["no-such-host.invalid:10110"], "output.nmea", "c.toml")


def _fixed_reference(value, digits):
    """What :func:`_fixed` writes, the slow way: ``json`` writing ``round(value, digits)``, null for non-finite."""
    return json.dumps(_round(value, digits))


_HALVES = [k / 2 * 10.0**-d for k in range(1, 400, 2) for d in (2, 3, 5, 9)]
"""Decimal halves (0.005, 2.675, ...): their floats lie either side of the half, rounded by their exact value."""
_EDGES = [
    *_HALVES,
    *(-v for v in _HALVES),
    0.0, -0.0, 1e-4, -1e-4, 0.99999e-4, 1.00001e-4, 5e-5, -5e-5, 0.00049999, 0.0005, 0.0004, -0.0004,
    999.9995, 999999.9999999995, 12345678.123456789, 1234567890123.4567, 1e6, 1e11, 1e12, 1e13, 1e15, 1e16,
    1.7803008e9 + 0.12345, -1.7803008e9 - 0.5,
    math.nan, math.inf, -math.inf, 1, -3, 0, 10**20, True,
]  # fmt: skip


@pytest.mark.parametrize("digits", [2, 3, 4, 5, 9])
def test_fixed_writes_the_text_of_the_rounded_value_at_the_edges(digits):
    """The formatted path and the ``round`` fallback write what ``json`` writes for ``round(value, digits)``:
    negatives, -0.0 (and values rounding to it), NaN and infinities as null, decimal halves, the ends of the
    formatted range (1e-4, 15 significant digits), ints."""
    for value in _EDGES:
        assert _fixed(value, digits) == _fixed_reference(value, digits), value


@given(value=st.floats(allow_nan=True, allow_infinity=True), digits=st.sampled_from([2, 3, 4, 5, 9]))
def test_fixed_writes_the_text_of_the_rounded_value(value, digits):
    assert _fixed(value, digits) == _fixed_reference(value, digits)


@given(mantissa=st.integers(-(10**18), 10**18), digits=st.sampled_from([2, 3, 5, 9]), extra=st.integers(0, 3))
def test_fixed_writes_the_text_of_the_rounded_value_for_decimals(mantissa, digits, extra):
    """Values that are (nearly) short decimals, where rounding halves and trailing zeros are: the hard cases."""
    value = mantissa / 10.0 ** (digits + extra)
    assert _fixed(value, digits) == _fixed_reference(value, digits)
