import json
import math
import socket

import pytest

from sumhe.io.udp import UdpSender, encode_json, estimate_to_json, iso_utc
from sumhe.messages import Estimate


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


def test_json_keys_units_and_track_in_degrees():
    obj = estimate_to_json(_estimate())
    assert obj["class"] == "TPV"
    assert obj["track"] == pytest.approx(270.0)  # -90 deg wraps to 270, clockwise from north
    assert obj["gps"] == "outage"
    assert obj["east"] == pytest.approx(12.346)
    for key in ("time", "t", "lat", "lon", "alt", "north", "speed", "yaw_rate", "mode", "window", "solve_ms"):
        assert key in obj
    assert "bound_east" not in obj


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
