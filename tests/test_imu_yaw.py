"""A yaw rate from a 3-axis IMU mounted any way (``can.signals.yaw_rate = { message, rates, accelerations }``): the
angular rate about the up direction the accelerometer finds; its config, decoding, bad input and the real drive."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sumhe.calibration import DriveSignals, _spec_toml, calibrate
from sumhe.config import SignalSpec, load_config
from sumhe.errors import ConfigError
from sumhe.io.can import CanDecoder, load_dbc, read_logs
from sumhe.io.imu import REPORT_AFTER, Mounting, VerticalRate
from sumhe.io.quanta import signal_quanta
from sumhe.messages import CanSample

from loggerframes import frame

DEG = math.pi / 180
G = 9.81
REPO = Path(__file__).resolve().parents[1]
REAL_DRIVE = REPO.parent / "shared" / "data" / "real_drives" / "canedge_obd_2021-07-26_a"

IMU_DBC = """VERSION ""

BU_: LOGGER

BO_ 10 IMU6: 8 LOGGER
 SG_ VALID : 0|1@1+ (1,0) [0|1] "" Vector__XXX
 SG_ AX : 1|10@1- (0.05,0) [-25.6|25.55] "m/s^2" Vector__XXX
 SG_ AY : 11|10@1- (0.05,0) [-25.6|25.55] "m/s^2" Vector__XXX
 SG_ AZ : 21|10@1- (0.05,0) [-25.6|25.55] "m/s^2" Vector__XXX
 SG_ WX : 31|11@1- (0.01,0) [-10.24|10.23] "deg/s" Vector__XXX
 SG_ WY : 42|11@1- (0.01,0) [-10.24|10.23] "deg/s" Vector__XXX
 SG_ WZ : 53|11@1- (0.01,0) [-10.24|10.23] "deg/s" Vector__XXX

BO_ 11 IMU_G: 8 LOGGER
 SG_ AX : 0|16@1- (0.001,0) [-32.768|32.767] "g" Vector__XXX
 SG_ AY : 16|16@1- (0.001,0) [-32.768|32.767] "m/s^2" Vector__XXX
 SG_ AZ : 32|16@1- (0.001,0) [-32.768|32.767] "m/s^2" Vector__XXX
 SG_ WX : 48|16@1- (0.01,0) [-327.68|327.67] "rad/s" Vector__XXX
"""
RATES = ("WX", "WY", "WZ")
ACCELERATIONS = ("AX", "AY", "AZ")


def imu_db() -> cantools.database.can.Database:
    db = cantools.database.can.Database()
    db.add_dbc_string(IMU_DBC)
    return db


def spec(**changes) -> SignalSpec:
    return SignalSpec("IMU6", "", rates=RATES, accelerations=ACCELERATIONS, **changes)


def rotation(x_deg: float, z_deg: float) -> np.ndarray:
    """A mounting: the device turned by ``x_deg`` about the car's x axis, then by ``z_deg`` about its z axis."""
    a, b = math.radians(x_deg), math.radians(z_deg)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    rz = np.array([[math.cos(b), -math.sin(b), 0], [math.sin(b), math.cos(b), 0], [0, 0, 1]])
    return rz @ rx


def imu_frame(t: float, mount: np.ndarray, accel: np.ndarray, rate_dps: np.ndarray, valid: int = 1):
    """One IMU6 frame of a device whose axes are ``mount``'s columns in the car (x forward, y left, z up): the car's
    specific force ``accel`` and angular rate ``rate_dps`` read in the device's axes."""
    a, w = mount.T @ accel, mount.T @ rate_dps
    values = dict(zip(ACCELERATIONS, a.tolist(), strict=True)) | dict(zip(RATES, w.tolist(), strict=True))
    message = imu_db().get_message_by_name("IMU6")
    return frame(t, message.frame_id, message.encode({"VALID": valid, **values}), channel=2)


def yaw_rates(decoder: CanDecoder, frames) -> list[float]:
    return [s.value for f in frames for s in decoder.decode(f) if isinstance(s, CanSample)]


def drive(mount: np.ndarray) -> list:
    """10 s at rest, then 20 s of turning left at 8 deg/s and 10 m/s while slowing at 1 m/s^2 (a roll rate of 0.4
    deg/s beside it), at 20 Hz."""
    out = [imu_frame(0.05 * k, mount, np.array([0.0, 0.0, G]), np.zeros(3)) for k in range(200)]
    turning = np.array([-1.0, 10.0 * 8.0 * DEG, G]), np.array([0.4, 0.0, 8.0])
    out += [imu_frame(10.0 + 0.05 * k, mount, *turning) for k in range(400)]
    return out


def imu_up(decoder: CanDecoder) -> np.ndarray:
    return np.array(decoder.imu_mountings()["can.signals.yaw_rate"].up)


@pytest.mark.parametrize(
    ("x_deg", "z_deg"),
    [(0, 0), (0, 90), (180, 0), (90, 0), (-90, 30), (35, 50), (20, -140)],
    ids=["upright", "turned-90", "upside-down", "on-its-side", "side-turned", "tilted-35", "tilted-20-reversed"],
)
def test_the_yaw_rate_is_the_rate_about_up_whichever_way_the_imu_is_mounted(x_deg, z_deg):
    mount = rotation(x_deg, z_deg)
    dec = CanDecoder(imu_db(), {"yaw_rate": spec(valid="VALID")})
    got = yaw_rates(dec, drive(mount))
    assert len(got) == 600 and dec.stats.decode_errors == 0
    assert got[:200] == pytest.approx([0.0] * 200, abs=0.02 * DEG)
    # 20 s of one turn, slowing, tilt the mean specific force by 6 deg at the end (a drive's turns either way and
    # its stops take that out): the rate within 1.5 %
    assert got[200:] == pytest.approx([8.0 * DEG] * 400, rel=0.015)
    car_up = mount.T @ np.array([0.0, 0.0, 1.0])
    assert math.degrees(math.acos(float(imu_up(dec) @ car_up))) == pytest.approx(6.3, abs=0.5)


@pytest.mark.parametrize(("x_deg", "exact"), [(5, True), (-8.5, True), (10, False), (25, False)])
def test_within_ten_degrees_of_an_axis_that_axis_alone_is_the_yaw_rate(x_deg, exact):
    """A device tilted a few degrees (or an accelerometer with an offset) gives its nearest axis's rate as it is;
    tilted more, the rate about up."""
    mount = rotation(x_deg, 0)
    frames = [imu_frame(0.05 * k, mount, np.array([0.0, 0.0, G]), np.array([1.5, 0.0, 8.0])) for k in range(10)]
    single = yaw_rates(CanDecoder(imu_db(), {"yaw_rate": SignalSpec("IMU6", "WZ")}), frames)
    projected = yaw_rates(CanDecoder(imu_db(), {"yaw_rate": spec()}), frames)
    assert (projected == single) is exact
    assert projected == pytest.approx([8.0 * DEG] * 10, rel=0.002 if not exact else 0.02)


def test_the_axis_is_taken_within_9_deg_and_left_beyond_11():
    """A band, so that a mounting near 10 deg does not switch between the axis and the rate about up."""
    vertical = VerticalRate(RATES, ACCELERATIONS)

    def tilted(deg: float, n: int) -> None:
        a = (0.0, G * math.sin(math.radians(deg)), G * math.cos(math.radians(deg)))
        for _ in range(n):
            vertical(dict(zip(ACCELERATIONS, a, strict=True)) | dict.fromkeys(RATES, 1.0))

    tilted(10.0, 1)
    assert not vertical.on_axis  # 10 deg from the start: the rate about up
    tilted(0.0, 1)
    assert vertical.on_axis  # the mean at 5 deg
    tilted(11.0, 9)  # the mean at 10.1 deg: kept
    assert vertical.on_axis
    tilted(15.0, 10)
    assert not vertical.on_axis  # 12.3 deg


def test_a_single_axis_of_a_tilted_imu_reads_the_roll_rate_in_its_yaw_rate():
    """Why the three axes: the upright mapping of a device on its side reads another axis."""
    mount = rotation(90, 0)
    single = CanDecoder(imu_db(), {"yaw_rate": SignalSpec("IMU6", "WZ")})
    assert yaw_rates(single, drive(mount))[-1] == pytest.approx(0.0, abs=0.02 * DEG)
    assert yaw_rates(CanDecoder(imu_db(), {"yaw_rate": spec()}), drive(mount))[-1] == pytest.approx(8 * DEG, rel=0.015)


def test_scale_turns_the_projected_rate_and_invalid_frames_stay_out_of_the_mean():
    mount = rotation(35, 50)
    dec = CanDecoder(imu_db(), {"yaw_rate": spec(valid="VALID", scale=-1.0)})
    sideways = imu_frame(0.0, mount, np.array([0.0, -G, 0.0]), np.zeros(3), valid=0)  # flagged: not gravity
    assert dec.decode(sideways) == [] and dec.stats.invalid == 1
    got = yaw_rates(dec, [imu_frame(0.1, mount, np.array([0.0, 0.0, G]), np.array([0.0, 0.0, 5.0]))])
    assert got == pytest.approx([-5.0 * DEG], rel=0.01)


def test_accelerations_that_point_no_one_way_give_no_yaw_rate_counted_and_logged(caplog):
    """A dead accelerometer (zeros) or one whose readings point every way gives no yaw rate rather than a wrong
    one, each sample a counted decode error; the rates come once the mean of the readings points one way."""
    dec = CanDecoder(imu_db(), {"yaw_rate": spec()}, source="c.toml")
    rate = np.array([0.0, 0.0, 3.0])
    dead = [imu_frame(0.1 * k, np.eye(3), np.zeros(3), rate) for k in range(2)]
    with caplog.at_level(logging.WARNING, logger="sumhe.io.can"):
        assert yaw_rates(dec, dead) == []
    assert dec.stats.decode_errors == 2 and dec.imu_mountings() == {"can.signals.yaw_rate": None}
    assert "can.signals.yaw_rate: the IMU's accelerations point no one way" in caplog.text
    swinging = [imu_frame(1.0 + 0.1 * k, np.eye(3), np.array([0.0, 0.0, G * (-1) ** k]), rate) for k in range(20)]
    assert len(yaw_rates(dec, swinging)) == 1  # the first alone points one way
    upright = [imu_frame(3.0 + 0.1 * k, np.eye(3), np.array([0.0, 0.0, G]), rate) for k in range(100)]
    got = yaw_rates(dec, upright)
    assert len(got) == 21 and got == pytest.approx([3.0 * DEG] * 21, rel=0.01)  # the mean 80 % of the magnitudes
    assert dec.stats.decode_errors == 2 + 19 + 79


def test_a_non_finite_acceleration_is_a_decode_error_and_stays_out_of_the_mean():
    vertical = VerticalRate(RATES, ACCELERATIONS)
    sample = {"AX": 0.0, "AY": 0.0, "AZ": G, "WX": 0.0, "WY": 0.0, "WZ": 2.0}
    assert math.isnan(vertical(sample | {"AX": math.inf}))
    assert vertical.up() is None  # nothing taken in
    assert vertical(sample) == pytest.approx(2.0)
    assert vertical.up() == pytest.approx((0.0, 0.0, 1.0))


def test_the_rate_quantum_is_the_coarsest_rate_signals_and_the_units_convert(tmp_path):
    (tmp_path / "imu.dbc").write_text(IMU_DBC)
    config = tmp_path / "c.toml"
    config.write_text(
        f'[can]\ndbc = "{tmp_path / "imu.dbc"}"\n[can.signals]\nyaw_rate = {{ message = "IMU6", '
        'rates = ["WX", "WY", "WZ"], accelerations = ["AX", "AY", "AZ"], channel = 2, scale = 2 }\n'
    )
    loaded = load_config(config, env={})
    assert loaded.can.signals["yaw_rate"] == spec(channel="2", scale=2.0)
    assert signal_quanta(loaded)["yaw_rate"] == pytest.approx(0.02 * DEG)


def test_the_calibration_snippet_writes_the_imu_mapping_back(tmp_path):
    imu = spec(channel="2", valid="VALID")
    text = f"[can.signals]\nyaw_rate = {_spec_toml(imu, 0.98)}\n"
    (tmp_path / "c.toml").write_text(text)
    assert load_config(tmp_path / "c.toml", env={}).can.signals["yaw_rate"] == spec(
        channel="2", valid="VALID", scale=0.98
    )


@pytest.mark.parametrize(
    ("table", "message"),
    [
        (
            "{ signal = 'IMU6.WX', message = 'IMU6', rates = ['WX', 'WY', 'WZ'], accelerations = ['AX', 'AY', 'AZ'] }",
            r"can\.signals\.yaw_rate: either signal or message",
        ),
        (
            "{ message = 'IMU6', rates = ['WX', 'WY'], accelerations = ['AX', 'AY', 'AZ'] }",
            r"can\.signals\.yaw_rate\.rates: expected a list of the three",
        ),
        (
            "{ message = 'IMU6', rates = ['WX', 'WY', 'WX'], accelerations = ['AX', 'AY', 'AZ'] }",
            r"can\.signals\.yaw_rate\.rates: three different signals",
        ),
        (
            "{ message = 'IMU6', rates = ['WX', 'WY', 'WZ'], accelerations = ['IMU6.AX', 'AY', 'AZ'] }",
            r"can\.signals\.yaw_rate\.accelerations: expected the name of a signal",
        ),
        ("{ message = 'IMU6', rates = ['WX', 'WY', 'WZ'] }", r"can\.signals\.yaw_rate\.accelerations: expected a list"),
        (
            "{ rates = ['WX', 'WY', 'WZ'], accelerations = ['AX', 'AY', 'AZ'] }",
            r"can\.signals\.yaw_rate\.message: expected the name of the IMU's message",
        ),
    ],
)
def test_a_bad_imu_mapping_is_a_config_error_naming_the_key(tmp_path, table, message):
    (tmp_path / "c.toml").write_text(f"[can.signals]\nyaw_rate = {table}\n")
    with pytest.raises(ConfigError, match=message):
        load_config(tmp_path / "c.toml", env={})


def test_only_the_yaw_rate_may_come_from_an_imu(tmp_path):
    table = "{ message = 'IMU6', rates = ['WX', 'WY', 'WZ'], accelerations = ['AX', 'AY', 'AZ'] }"
    for section, key in (("can.signals", "speed"), ("gps.signals", "heading")):
        (tmp_path / "c.toml").write_text(f"[{section}]\n{key} = {table}\n")
        with pytest.raises(ConfigError, match=rf"{section}\.{key}\.(accelerations|message|rates): unknown key"):
            load_config(tmp_path / "c.toml", env={})
    with pytest.raises(ConfigError, match=r"can\.signals\.speed: rates and accelerations .*yaw_rate only"):
        CanDecoder(imu_db(), {"speed": spec()})


@pytest.mark.parametrize(
    ("imu", "message"),
    [
        (
            SignalSpec("IMU6", "", rates=("WX", "WY", "W"), accelerations=ACCELERATIONS),
            r"can\.signals\.yaw_rate\.rates: no signal 'W' in message IMU6 \(VALID, AX",
        ),
        (
            SignalSpec("IMU6", "", rates=RATES, accelerations=("AX", "AY", "A")),
            r"can\.signals\.yaw_rate\.accelerations: no signal 'A'",
        ),
        (
            SignalSpec("IMU_G", "", rates=("WX", "AY", "AZ"), accelerations=ACCELERATIONS),
            r"can\.signals\.yaw_rate\.rates: the signals' units differ \(m/s\^2, rad/s\)",
        ),
        (SignalSpec("IMU_G", "", rates=("WX", "WX2", "WX3"), accelerations=ACCELERATIONS), r"no signal 'WX2'"),
        (
            SignalSpec("IMU_G", "", rates=("WX", "WX", "WX"), accelerations=ACCELERATIONS, unit="deg/s"),
            r"can\.signals\.yaw_rate\.accelerations: the signals' units differ \(g, m/s\^2\)",
        ),
    ],
)
def test_imu_signals_the_dbc_lacks_or_whose_units_differ_are_config_errors(imu, message):
    with pytest.raises(ConfigError, match=message):
        CanDecoder(imu_db(), {"yaw_rate": imu})


@pytest.mark.skipif(not REAL_DRIVE.is_dir(), reason="the shared real drive (../shared/data/real_drives) is absent")
def test_the_real_loggers_imu_points_its_x_axis_up_and_its_yaw_rate_is_that_axiss():
    """The shared drive's CANmod.gps (its first file: 10 minutes) with configs/canedge-obd.toml: up 2-8 deg from its
    X axis (4.8 over the whole drive), so the yaw rate is the X rate as the single-axis mapping reads it."""
    config = load_config(REPO / "configs" / "canedge-obd.toml", env={})
    dbs = [load_dbc(REPO / "dbc" / "obd2.dbc"), load_dbc(REAL_DRIVE / "canmod-gps.dbc")]
    imu = CanDecoder(dbs, {"yaw_rate": config.can.signals["yaw_rate"]})
    single = CanDecoder(dbs, {"yaw_rate": SignalSpec("gnss_imu", "AngularRateX", valid="ImuValid", channel="2")})
    pairs = []
    for msg in read_logs(sorted(REAL_DRIVE.glob("*.MF4"))[:1]):
        pairs += [(x.value, y.value) for x, y in zip(imu.decode(msg), single.decode(msg), strict=True)]
    assert len(pairs) > 50_000 and imu.stats.decode_errors == 0 and imu.stats.invalid == single.stats.invalid
    assert all(a == b for a, b in pairs)
    up = imu_up(imu)
    assert up[0] > 0 and 2 < math.degrees(math.acos(up[0])) < 8


def test_the_mounting_names_up_its_tilt_from_the_nearest_axis_and_the_rate_taken():
    tilted = (math.cos(math.radians(5)), 0.0, math.sin(math.radians(5)))
    assert Mounting(tilted, True, RATES, ACCELERATIONS).describe() == (
        "the IMU's up: +0.996 AX +0.000 AY +0.087 AZ (5.0 deg from +AX); the yaw rate is +WX alone"
    )
    on_its_side = Mounting((0.0, -1.0, 0.0), True, RATES, ACCELERATIONS).describe()
    assert on_its_side.endswith("(0.0 deg from -AY); the yaw rate is -WY alone")
    steep = Mounting((0.0, math.sin(math.radians(30)), math.cos(math.radians(30))), False, RATES, ACCELERATIONS)
    assert steep.describe().endswith("(30.0 deg from +AZ); the yaw rate is the rate about up")


def test_calibrate_names_how_the_imu_sits():
    """``sumhe calibrate``'s first note, from the drive's decoder."""
    mounting = Mounting((1.0, 0.0, 0.0), True, RATES, ACCELERATIONS)
    signals = DriveSignals(*([np.zeros(0)] * 10), speed_quantum_mps=0.1, fixes=0, imu=mounting)
    assert calibrate(signals).notes[0] == mounting.describe()


@settings(max_examples=80, deadline=None)
@given(st.lists(st.binary(max_size=12), max_size=40))
def test_any_payloads_give_finite_yaw_rates_or_counted_errors_never_a_crash(payloads):
    dec = CanDecoder(imu_db(), {"yaw_rate": spec(valid="VALID")})
    frames = [frame(0.01 * k, 10, data, channel=2) for k, data in enumerate(payloads)]
    rates = yaw_rates(dec, frames)
    assert all(math.isfinite(r) and abs(r) <= 10.24 * math.sqrt(3) * DEG for r in rates)
    s = dec.stats
    assert len(rates) == s.decoded and s.decoded + s.invalid + s.decode_errors + s.long_frames == len(payloads)


def test_how_the_imu_sits_is_logged_once_settled_and_at_each_switch(caplog):
    vertical = VerticalRate(RATES, ACCELERATIONS, "c.toml: can.signals.yaw_rate")

    def tilted(deg: float, n: int) -> None:
        a = (0.0, G * math.sin(math.radians(deg)), G * math.cos(math.radians(deg)))
        for _ in range(n):
            vertical(dict(zip(ACCELERATIONS, a, strict=True)) | dict.fromkeys(RATES, 1.0))

    with caplog.at_level(logging.INFO, logger="sumhe.io.imu"):
        tilted(5.0, REPORT_AFTER - 1)
        assert caplog.messages == []
        tilted(5.0, 500)
        tilted(40.0, 600)  # the mean past 11 deg after some 330 of them: the rate about up from there
    assert caplog.messages == [
        "c.toml: can.signals.yaw_rate: the IMU's up: +0.000 AX +0.087 AY +0.996 AZ (5.0 deg from +AZ); the yaw rate "
        "is +WZ alone (after 1000 samples)",
        caplog.messages[1],
    ]
    assert "; the yaw rate is the rate about up (after 18" in caplog.messages[1]
