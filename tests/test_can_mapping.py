"""The signal mapping for real loggers: bus channels, several DBCs, OBD-II replies multiplexed by PID, validity
flags, a yaw rate from an IMU axis with a sign; and the config errors of each."""

from __future__ import annotations

import math
from pathlib import Path

import cantools
import pytest

from sumhe.config import SignalSpec, load_config
from sumhe.errors import ConfigError
from sumhe.io.can import CanDecoder, load_dbc
from sumhe.io.can_source import CanBusSource
from sumhe.io.replay import beside_logs
from sumhe.messages import CanSample

from loggerframes import CAR_ID_9, LOGGER_CONFIG, LOGGER_DBC, OBD_DBC, encode, frame, logger_db, obd_reply

DEG = math.pi / 180

CAR_DBC = """VERSION ""

BU_: ECU

BO_ 9 CAR_STEERING: 8 ECU
 SG_ ANGLE : 0|16@1- (0.1,0) [-3276.8|3276.7] "deg" Vector__XXX
"""


def car_db() -> cantools.database.can.Database:
    db = cantools.database.can.Database()
    db.add_dbc_string(CAR_DBC)
    return db


def obd_db() -> cantools.database.can.Database:
    return load_dbc(OBD_DBC)


def values(samples) -> dict[str, float]:
    return {s.quantity: s.value for s in samples if isinstance(s, CanSample)}


# --- OBD-II: mode 01 replies multiplexed by PID ---------------------------------------------------------------


def test_obd_speed_from_pid_0x0d_and_other_pids_carry_nothing():
    dec = CanDecoder(obd_db(), {"speed": SignalSpec("OBD2", "VehicleSpeed")})
    assert values(dec.decode(obd_reply(1.0, 0x0D, 72))) == pytest.approx({"speed": 20.0})
    assert dec.decode(obd_reply(1.1, 0x0C, 0x1A, 0x2B)) == []  # engine speed: another PID of the same id
    assert dec.decode(obd_reply(1.2, 0x99, 1, 2)) == []  # a PID the DBC does not know
    s = dec.stats
    assert (s.decoded, s.other_mux, s.decode_errors, s.per_quantity) == (1, 2, 0, {"can.signals.speed": 1})


def test_obd_engine_speed_and_vehicle_speed_from_one_id():
    dec = CanDecoder(obd_db(), {"speed": SignalSpec("OBD2", "VehicleSpeed")}, every_message=True)
    assert dec.decode_signals(obd_reply(1.0, 0x0C, 0x1A, 0x2B))[1]["EngineSpeed"] == pytest.approx(1674.75)
    assert dec.decode_signals(obd_reply(1.0, 0x99, 1, 2)) is None  # unknown PID: nothing, and no error
    assert (dec.stats.other_mux, dec.stats.decode_errors) == (1, 0)


def test_short_obd_reply_is_a_counted_decode_error_and_gives_no_speed():
    dec = CanDecoder(obd_db(), {"speed": SignalSpec("OBD2", "VehicleSpeed")})
    short = frame(1.0, 0x7E8, bytes([3, 0x41, 0x0D, 72]), channel=1)  # not padded to 8 bytes
    assert dec.decode(short) == []
    assert dec.decode(frame(1.1, 0x7E8, b"", channel=1)) == []
    assert (dec.stats.decode_errors, dec.stats.decoded) == (2, 0)
    assert values(dec.decode(obd_reply(1.2, 0x0D, 36))) == pytest.approx({"speed": 10.0})


def test_reply_of_another_ecu_is_unused():
    dec = CanDecoder(obd_db(), {"speed": SignalSpec("OBD2", "VehicleSpeed")})
    other = obd_reply(1.0, 0x0D, 72)
    other.arbitration_id = 0x7E9
    assert dec.decode(other) == [] and dec.stats.unused_ids == {0x7E9: 1}


# --- channels and several DBCs ----------------------------------------------------------------------------------


def test_channel_keeps_apart_ids_that_repeat_across_buses():
    signals = {
        "yaw_rate": SignalSpec("IMU", "YAW_RATE_CW", scale=-1.0, channel="2"),
        "steering_angle": SignalSpec("CAR_STEERING", "ANGLE", channel="1"),
        "speed": SignalSpec("OBD2", "VehicleSpeed"),  # no channel: any bus
    }
    dec = CanDecoder([obd_db(), logger_db(), car_db()], signals)
    imu = encode("IMU", 1.0, channel=2, IMU_VALID=1, YAW_RATE_CW=-3.0)
    car = frame(1.0, CAR_ID_9, (900).to_bytes(2, "little", signed=True) + bytes(6), channel=1)
    assert values(dec.decode(imu)) == pytest.approx({"yaw_rate": 3.0 * DEG})
    assert values(dec.decode(car)) == pytest.approx({"steering_angle": 90.0 * DEG})
    assert values(dec.decode(obd_reply(1.0, 0x0D, 36, channel=2))) == pytest.approx({"speed": 10.0})
    other_bus = encode("IMU", 1.0, channel=3, IMU_VALID=1, YAW_RATE_CW=-3.0)
    assert dec.decode(other_bus) == [] and dec.stats.unused == 1
    assert dec.stats.channels == {"1": 1, "2": 2, "3": 1}
    assert {f["can_id"] for f in dec.can_filters()} == {CAR_ID_9, 0x7E8}


def test_a_mapping_without_channel_would_decode_the_other_bus_as_the_imu():
    """Why the channel matters: id 9 of the car's bus decodes as the logger's IMU without it."""
    dec = CanDecoder(logger_db(), {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW")})
    car = frame(1.0, CAR_ID_9, bytes([0xFF] * 8), channel=1)
    assert values(dec.decode(car)) == pytest.approx({"yaw_rate": -0.01 * DEG})  # garbage, silently
    checked = CanDecoder(logger_db(), {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW", channel="2")})
    assert checked.decode(car) == []


def test_same_id_on_the_same_bus_twice_is_a_config_error():
    signals = {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW"), "steering_angle": SignalSpec("CAR_STEERING", "ANGLE")}
    with pytest.raises(ConfigError, match="IMU and CAR_STEERING share the id 0x9") as err:
        CanDecoder([logger_db(), car_db()], signals, source="c.toml")
    assert "channel" in str(err.value)


def test_a_message_in_two_dbcs_is_ambiguous():
    with pytest.raises(ConfigError, match=r"can\.signals\.yaw_rate: message 'IMU' is in 2 of the databases"):
        CanDecoder([logger_db(), logger_db()], {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW")})


def test_several_dbcs_from_the_config_with_one_found_beside_the_logs(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "logger.dbc").write_text(LOGGER_DBC)
    path = tmp_path / "logger.toml"
    path.write_text(LOGGER_CONFIG)
    config = load_config(path, env={})
    with pytest.raises(ConfigError, match=r"can\.dbc: file not found: logger\.dbc"):
        CanDecoder.from_config(config)
    dec = CanDecoder.from_config(beside_logs(config, [logs / "drive.mf4"]))
    assert [len(db.messages) for db in dec.dbs] == [1, 4]
    assert dec.message_names() == {"speed": "OBD2", "yaw_rate": "IMU"}
    assert dec.channels() == {f"{t}.signals.{q}": c for t, q, c in CHANNELS}


CHANNELS = [
    ("can", "speed", "1"),
    ("can", "yaw_rate", "2"),
    *(("gps", q, "2") for q in ("lat", "lon", "accuracy", "speed", "heading", "time")),
]


def test_a_channel_without_frames_is_named_with_the_channels_seen():
    dec = CanDecoder(logger_db(), {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW", channel="3")}, source="c.toml")
    dec.decode(encode("IMU", 1.0, channel=2, IMU_VALID=1))
    assert dec.silent() == [
        "c.toml: can.signals.yaw_rate: no value from IMU.YAW_RATE_CW on channel 3 (frames came on channels: 2)"
    ]


# --- validity flags and signs ------------------------------------------------------------------------------------


def test_validity_flag_drops_the_value_and_counts_it():
    dec = CanDecoder(logger_db(), {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW", valid="IMU_VALID")})
    assert values(dec.decode(encode("IMU", 1.0, IMU_VALID=1, YAW_RATE_CW=4.0))) == pytest.approx({"yaw_rate": 4 * DEG})
    assert dec.decode(encode("IMU", 1.1, IMU_VALID=0, YAW_RATE_CW=4.0)) == []
    assert (dec.stats.invalid, dec.stats.decoded, dec.stats.decode_errors) == (1, 1, 0)


@pytest.mark.parametrize(("scale", "expected_dps"), [(1.0, -2.5), (-1.0, 2.5)])
def test_yaw_rate_from_an_imu_axis_with_a_sign(scale, expected_dps):
    """The IMU reads right turns positive; ``scale = -1`` makes left turns positive, as sumhe's yaw rate is."""
    dec = CanDecoder(logger_db(), {"yaw_rate": SignalSpec("IMU", "YAW_RATE_CW", scale=scale)})
    got = dec.decode(encode("IMU", 1.0, IMU_VALID=1, YAW_RATE_CW=-2.5))
    assert values(got) == pytest.approx({"yaw_rate": expected_dps * DEG})


# --- config errors name the key ----------------------------------------------------------------------------------


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "c.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("spec", "key"),
    [
        ("{ signal = 'IMU.YAW_RATE_CW', channel = true }", "can.signals.yaw_rate.channel"),
        ("{ signal = 'IMU.YAW_RATE_CW', channel = -1 }", "can.signals.yaw_rate.channel"),
        ("{ signal = 'IMU.YAW_RATE_CW', channel = 1.5 }", "can.signals.yaw_rate.channel"),
        ("{ signal = 'IMU.YAW_RATE_CW', channel = ' ' }", "can.signals.yaw_rate.channel"),
        ("{ signal = 'IMU.YAW_RATE_CW', valid = 'IMU.IMU_VALID' }", "can.signals.yaw_rate.valid"),
        ("{ signal = 'IMU.YAW_RATE_CW', valid = 1 }", "can.signals.yaw_rate.valid"),
        ("{ signal = 'IMU.YAW_RATE_CW', bus = 2 }", "can.signals.yaw_rate.bus"),
    ],
)
def test_bad_channel_and_flag_values_name_the_key(tmp_path, spec, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(write(tmp_path, f"[can.signals]\nyaw_rate = {spec}\n"), env={})


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (SignalSpec("IMU", "YAW_RATE", channel="2"), r"c\.toml: can\.signals\.yaw_rate: no signal 'YAW_RATE' in"),
        (SignalSpec("IMU", "YAW_RATE_CW", valid="VALID"), r"can\.signals\.yaw_rate\.valid: no signal 'VALID'"),
        (SignalSpec("NOPE", "X", channel="2"), r"can\.signals\.yaw_rate: no message 'NOPE'"),
    ],
)
def test_a_mapping_naming_an_unknown_signal_is_a_config_error_naming_the_key(spec, message):
    with pytest.raises(ConfigError, match=message):
        CanDecoder([obd_db(), logger_db()], {"yaw_rate": spec}, source="c.toml")


def test_unknown_quantities_are_config_errors_naming_the_key():
    with pytest.raises(ConfigError, match=r"can\.signals\.lat: unknown quantity"):
        CanDecoder(logger_db(), {"lat": SignalSpec("GNSS_POS", "LAT")})
    with pytest.raises(ConfigError, match=r"gps\.signals\.yaw_rate: unknown quantity"):
        CanDecoder(
            logger_db(), {}, gnss={"lat": SignalSpec("GNSS_POS", "LAT"), "yaw_rate": SignalSpec("IMU", "IMU_VALID")}
        )


def test_a_live_bus_refuses_a_mapping_for_another_channel(tmp_path):
    path = write(
        tmp_path,
        "[can]\ninterface = 'virtual'\nchannel = 'vcan0'\ndbc = 'dbc/obd2.dbc'\n"
        "[can.signals]\nspeed = { signal = 'OBD2.VehicleSpeed', channel = 1 }\n",
    )
    with pytest.raises(ConfigError, match=r"can\.signals\.speed\.channel: '1', but the live bus is can\.channel"):
        CanBusSource.from_config(load_config(path, env={}))
