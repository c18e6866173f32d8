"""GNSS fixes decoded from CAN frames (``[gps] source = "can"``): epochs, validity, bad values, the replay's
time order and stamping, and the daemon with no serial port."""

from __future__ import annotations

import asyncio
import datetime as dt
import itertools
import math
import re
import time
from pathlib import Path

import can
import can.interfaces.virtual
import numpy as np
import pytest

from sumhe.config import SignalSpec, load_config
from sumhe.errors import ConfigError
from sumhe.estimator.registry import make_estimator
from sumhe.io.can import CanDecoder
from sumhe.io.can_gnss import GnssAssembler, checked_value
from sumhe.io.can_source import CanBusSource
from sumhe.io.replay import RecordedDrive
from sumhe.messages import CanSample, GnssFix
from sumhe.service.app import Service

from loggerframes import LOGGER_CONFIG, LOGGER_DBC, T0, encode, logger_db, obd_reply, write_drive

MESSAGES = ("GNSS_TIME", "GNSS_POS", "GNSS_MOTION")
GNSS = {
    "lat": SignalSpec("GNSS_POS", "LAT", valid="POS_VALID"),
    "lon": SignalSpec("GNSS_POS", "LON", valid="POS_VALID"),
    "accuracy": SignalSpec("GNSS_POS", "ACCURACY"),
    "speed": SignalSpec("GNSS_MOTION", "SPEED", valid="SPEED_VALID"),
    "heading": SignalSpec("GNSS_MOTION", "HEADING", valid="HEADING_VALID"),
    "time": SignalSpec("GNSS_TIME", "EPOCH"),
}


def assembler(span_s: float = 0.1) -> GnssAssembler:
    return GnssAssembler(MESSAGES, "GNSS_POS", span_s)


def epoch(a: GnssAssembler, t: float, lat: float | None = 56.1, speed: float | None = 10.0, skip: str = ""):
    """Feed one epoch's frames (``skip`` one message); the fixes they closed."""
    out = []
    frames = {
        "GNSS_TIME": {"time": t - 4.4},
        "GNSS_POS": {"lat": lat, "lon": None if lat is None else 10.2, "accuracy": 1.5},
        "GNSS_MOTION": {"speed": speed, "heading": math.radians(370.0)},
    }
    for k, name in enumerate(MESSAGES):
        if name != skip:
            out += a.add(t + 0.001 * k, name, frames[name])
    return out


# --- epochs -----------------------------------------------------------------------------------------------------


def test_complete_epoch_is_one_fix_at_once_stamped_with_the_position_frame():
    a = assembler()
    (fix,) = epoch(a, 100.0)
    assert fix.t == 100.001 and fix.valid and fix.quality == 1 and fix.talker == "CAN"
    assert (fix.lat_deg, fix.lon_deg, fix.speed_mps, fix.sigma_lat_m, fix.sigma_lon_m) == (56.1, 10.2, 10.0, 1.5, 1.5)
    assert fix.heading_rad == pytest.approx(math.radians(10.0)) and fix.course_rad is None
    assert fix.time_utc == dt.datetime.fromtimestamp(95.6, dt.timezone.utc)
    assert a.flush() == [] and a.stats.fixes == 1 and a.stats.incomplete == 0


def test_incomplete_epoch_closes_on_the_next_epoch_or_after_its_span():
    a = assembler(span_s=0.1)
    assert epoch(a, 100.0, skip="GNSS_MOTION") == []  # waits for the motion frame
    assert a.tick(100.05) == []
    (late,) = a.tick(100.2)  # any frame after the span closes it
    assert late.t == 100.001 and late.valid and late.speed_mps is None
    assert epoch(a, 101.0, skip="GNSS_MOTION") == []
    first, second = epoch(a, 101.05)  # the repeated GNSS_TIME closes the open epoch first
    assert (first.t, second.t) == (101.001, 101.051) and second.speed_mps == 10.0
    assert (a.stats.fixes, a.stats.incomplete) == (3, 2)


def test_epoch_without_the_position_frame_gives_no_fix():
    a = assembler()
    assert epoch(a, 100.0, skip="GNSS_POS") == [] and a.flush() == []
    assert (a.stats.fixes, a.stats.no_position, a.stats.incomplete) == (0, 1, 1)
    epoch(a, 101.0, skip="GNSS_MOTION")
    assert len(a.flush()) == 1  # the end of the input closes the open epoch


def test_invalid_position_is_an_invalid_fix_without_position_or_motion():
    a = assembler()
    (fix,) = epoch(a, 100.0, lat=None)
    assert not fix.valid and fix.quality == 0
    assert (fix.lat_deg, fix.lon_deg, fix.speed_mps, fix.heading_rad, fix.sigma_lat_m) == (None,) * 5
    assert fix.time_utc is not None  # the time of an epoch without a fix is still known
    assert (a.stats.fixes, a.stats.valid_fixes) == (1, 0)


@pytest.mark.parametrize(
    ("quantity", "value", "expected"),
    [
        ("lat", 90.5, None),
        ("lat", -90.0, -90.0),
        ("lon", 181.0, None),
        ("accuracy", 0.0, None),
        ("accuracy", -1.0, None),
        ("speed", -0.5, None),
        ("sats", -1.0, None),
        ("time", -5.0, None),
        ("alt", math.inf, None),
        ("lat", math.nan, None),
        ("course", math.radians(-10.0), pytest.approx(math.radians(350.0))),
        ("heading", 4 * math.pi, pytest.approx(0.0)),
    ],
)
def test_values_out_of_range_are_left_out(quantity, value, expected):
    assert checked_value(quantity, value) == expected


def test_heading_accuracy_rates_the_heading_of_its_fix_and_only_a_heading():
    a = GnssAssembler(MESSAGES, "GNSS_POS", 0.1)
    rated = a.add(100.0, "GNSS_POS", {"lat": 56.1, "lon": 10.2})
    rated += a.add(100.001, "GNSS_MOTION", {"heading": 1.0, "heading_accuracy": 0.05})
    rated += a.add(100.002, "GNSS_TIME", {"time": 95.6})
    (fix,) = rated
    assert fix.heading_rad == 1.0 and fix.heading_sigma_rad == 0.05
    (no_heading,) = [
        *a.add(101.0, "GNSS_POS", {"lat": 56.1, "lon": 10.2}),
        *a.add(101.001, "GNSS_MOTION", {"heading": None, "heading_accuracy": 0.05}),
        *a.add(101.002, "GNSS_TIME", {"time": 96.6}),
    ]
    assert no_heading.heading_rad is None and no_heading.heading_sigma_rad is None
    assert checked_value("heading_accuracy", 0.0) is None and checked_value("heading_accuracy", -0.1) is None


def test_bad_values_are_counted_and_a_bad_latitude_leaves_the_fix_invalid():
    a = assembler()
    (fix,) = epoch(a, 100.0, lat=95.0, speed=-3.0)
    assert not fix.valid and fix.lat_deg is None and a.stats.bad_values == 2


# --- through the decoder -------------------------------------------------------------------------------------


def gnss_frames(t: float, valid: int = 1, lat: float = 56.1):
    return [
        encode("GNSS_TIME", t, EPOCH=t - 4.4),
        encode("GNSS_POS", t + 0.001, POS_VALID=valid, ACCURACY=2.0, LAT=lat, LON=10.2),
        encode(
            "GNSS_MOTION", t + 0.002, SPEED_VALID=valid, HEADING_VALID=valid, SPEED=12.5, HEADING=90.0, HEADING_ACC=2.5
        ),
    ]


def test_decoder_turns_gnss_frames_into_fixes_beside_can_samples():
    dec = CanDecoder(logger_db(), {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW", scale=-1)}, gnss=GNSS)
    out = []
    for t in (100.0, 101.0):
        for f in [*gnss_frames(t, valid=int(t > 100.5)), encode("IMU", t + 0.5, IMU_VALID=1, YAW_RATE_CW=1.0)]:
            out += dec.decode(f)
    fixes = [s for s in out if isinstance(s, GnssFix)]
    assert [f.valid for f in fixes] == [False, True]
    assert fixes[1].lat_deg == pytest.approx(56.1) and fixes[1].speed_mps == pytest.approx(12.5)
    assert fixes[1].heading_rad == pytest.approx(math.pi / 2) and fixes[1].sigma_lat_m == pytest.approx(2.0)
    assert fixes[1].heading_sigma_rad is None  # not mapped: not read
    assert [s.quantity for s in out if isinstance(s, CanSample)] == ["yaw_rate", "yaw_rate"]
    assert dec.stats.invalid == 4  # the values flagged invalid: lat, lon, speed, heading of the first epoch
    assert dec.gnss is not None and dec.gnss.stats.incomplete == 0


def test_decoder_reads_the_heading_accuracy_in_radians_where_mapped():
    rated = GNSS | {"heading_accuracy": SignalSpec("GNSS_MOTION", "HEADING_ACC", valid="HEADING_VALID")}
    dec = CanDecoder(logger_db(), {}, gnss=rated)
    fixes = [s for t in (100.0, 101.0) for f in gnss_frames(t, valid=int(t > 100.5)) for s in dec.decode(f)]
    assert [f.heading_sigma_rad for f in fixes] == [None, pytest.approx(math.radians(2.5))]


def test_a_heading_accuracy_in_metres_is_a_config_error_naming_the_key():
    with pytest.raises(
        ConfigError, match=r"gps\.signals\.heading_accuracy: GNSS_POS\.ACCURACY has unit 'm', not an angle"
    ):
        CanDecoder(logger_db(), {}, gnss=GNSS | {"heading_accuracy": SignalSpec("GNSS_POS", "ACCURACY")})


def test_gnss_mapping_needs_lat_and_lon():
    with pytest.raises(ConfigError, match=r"gps\.signals: lat and lon"):
        CanDecoder(logger_db(), {}, gnss={"lat": GNSS["lat"]})


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[gps]\nsource = 'serial'\n", "gps.source"),
        ("[gps]\nsource = 'can'\n", "gps.signals"),
        ("[gps]\nsource = 'can'\n[gps.signals]\nlat = 'A.B'\n", "gps.signals"),
        ("[gps.signals]\nlat = 'A.B'\nlon = 'A.C'\n", "gps.signals"),  # only read with source = 'can'
        ("[gps]\nsource = 'can'\n[gps.signals]\nlat = 'A.B'\nlon = 'A.C'\nhdop = 'A.D'\n", "gps.signals.hdop"),
        ("[gps]\nsource = 'can'\nepoch_span_s = 0\n[gps.signals]\nlat = 'A.B'\nlon = 'A.C'\n", "gps.epoch_span_s"),
    ],
)
def test_gps_source_config_errors_name_the_key(tmp_path, text, key):
    path = tmp_path / "c.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(path, env={})


# --- replay: stamped on the frame clock, in time order ------------------------------------------------------------


def logger_config(tmp_path: Path) -> Path:
    path = tmp_path / "logger.toml"
    path.write_text(LOGGER_CONFIG)
    return path


def test_replay_of_a_logger_drive_is_time_ordered_with_fixes_on_the_frame_clock(tmp_path):
    logs = write_drive(tmp_path / "logs", 12.0, files=2)
    for latency in (0.0, 0.3):
        config = load_config(logger_config(tmp_path), env={}, overrides={"gps.latency_s": latency})
        drive = RecordedDrive(config, logs[::-1])
        samples = list(drive.samples())
        assert [s.t for s in samples] == sorted(s.t for s in samples)
        fixes = [s for s in samples if isinstance(s, GnssFix)]
        assert len(fixes) == 12 and sum(f.valid for f in fixes) == 10  # no fix in the first 2 s
        # the position frame of epoch k is at T0 + k + 0.5 + 0.021; UTC (4.4 s off) is not used: time = "receive"
        assert [f.t for f in fixes] == pytest.approx([T0 + k + 0.521 - latency for k in range(12)])
        assert drive.first_t == pytest.approx(T0 + 0.003)
        assert {s.quantity for s in samples if isinstance(s, CanSample)} == {"speed", "yaw_rate"}


def test_gps_source_can_with_nmea_logs_or_nmea_without_them_is_refused(tmp_path, capsys):
    from sumhe.cli import main

    logs = write_drive(tmp_path / "logs", 3.0)
    nmea = tmp_path / "drive.nmea"
    nmea.write_text("")
    assert main(["replay", *map(str, logs), "--nmea", str(nmea), "--config", str(logger_config(tmp_path))]) == 1
    assert "gps.source = 'can': the fixes come from the CAN logs; drop --nmea" in capsys.readouterr().err
    assert main(["replay", *map(str, logs)]) == 1
    assert "gps.source = 'nmea': give the NMEA logs with --nmea" in capsys.readouterr().err


# --- the daemon: CAN only, no serial port ------------------------------------------------------------------------

_channels = itertools.count()


def test_daemon_with_gnss_from_can_needs_no_serial_port(tmp_path):
    """A live bus (python-can's virtual bus, in real time) carrying the logger's frames: fixes decoded from CAN
    reach the estimator through the service's reorder buffer; the only source is the bus."""
    channel = f"sumhe-gnss-{next(_channels)}"
    (tmp_path / "logger.dbc").write_text(LOGGER_DBC)
    live = re.sub(r", channel = \d+", "", LOGGER_CONFIG)  # one live bus: no channels
    live = live.replace("[can]\n", f"[can]\ninterface = 'virtual'\nchannel = '{channel}'\n")
    path = tmp_path / "live.toml"
    path.write_text(live + "[output]\njson = []\n")
    config = load_config(path, env={})
    assert config.gps.source == "can" and all(s.channel is None for s in config.can.signals.values())
    got = []

    async def main():
        source = CanBusSource.from_config(config)
        service = Service(config, make_estimator("dead-reckoning", config), {"can": source}, sink=got.append)
        await source.start()
        stop = asyncio.Event()
        task = asyncio.create_task(service.run(stop))
        with can.Bus(interface="virtual", channel=channel) as bus:
            await asyncio.sleep(0.2)
            for k in range(30):  # 3 s: GNSS at 5 Hz, OBD speed and IMU at 10 Hz
                t = time.time()
                bus.send(obd_reply(t, 0x0D, 36))
                bus.send(encode("IMU", t, IMU_VALID=1, YAW_RATE_CW=-2.0))
                if k % 2 == 0:
                    for f in gnss_frames(t, lat=56.1 + 1e-5 * k):
                        bus.send(f)
                await asyncio.sleep(0.1)
            await asyncio.sleep(0.5)
        stop.set()
        await task
        return service

    service = asyncio.run(asyncio.wait_for(main(), 30))
    assert set(service.sources) == {"can"}
    assert service.pipeline.stats.valid_fixes >= 12 and service.pipeline.guard.stats.late == 0
    gps = np.array([e.gps for e in got])
    assert (gps == "ok").sum() >= 12 and got[-1].lat_deg == pytest.approx(56.1 + 28e-5, abs=2e-5)
