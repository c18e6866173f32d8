import gzip
import logging
import math
import random
import struct
from pathlib import Path

import can
import cantools
import pytest

from sumhe.config import SignalSpec, load_config
from sumhe.errors import ConfigError, SourceError
from sumhe.io.can import (
    EXTENDED_FLAG,
    MAX_UNUSED_IDS,
    REFERENCE_E2E,
    REFERENCE_SIGNALS,
    CanDecoder,
    LogStats,
    _decoding,
    _in_use,
    _whole,
    load_dbc,
    read_log,
    si_factor,
)

from canframes import MESSAGE_FIELDS, REF_DBC, TOYOTA_DBC, encode, ref_db, speed_frame, toyota_db, yaw_frame

DEG = math.pi / 180


def reference_decoder(**overrides) -> CanDecoder:
    config = load_config(
        None, overrides={"can.signals": REFERENCE_SIGNALS, "can.e2e": list(REFERENCE_E2E), **overrides}
    )
    return CanDecoder.from_config(config)


def write_config(tmp_path, text: str):
    path = tmp_path / "sumhe.toml"
    path.write_text(text)
    return load_config(path, env={})


def std(arbitration_id: int, data: bytes = b"", **kw) -> can.Message:
    """An 11-bit frame (python-can's Message defaults to a 29-bit id)."""
    return can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, **kw)


def by_quantity(samples) -> dict[str, float]:
    return {s.quantity: s.value for s in samples}


# --- units ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("unit", "quantity", "factor"),
    [
        ("km/h", "speed", 1 / 3.6),
        ("KPH", "speed", 1 / 3.6),
        ("kmh", "wheel_speed_rl", 1 / 3.6),
        ("Km / h", "speed", 1 / 3.6),
        ("mph", "speed", 0.44704),
        ("m/s", "speed", 1.0),
        ("mps", "speed", 1.0),
        ("deg/s", "yaw_rate", DEG),
        ("°/s", "yaw_rate", DEG),
        ("deg/sec", "yaw_rate", DEG),
        ("rad/s", "yaw_rate", 1.0),
        ("deg", "steering_angle", DEG),
        ("°", "steering_angle", DEG),
        ("rad", "steering_angle", 1.0),
        ("m/s^2", "lat_accel", 1.0),
        ("m/s2", "lon_accel", 1.0),
        ("g", "lat_accel", 9.80665),
    ],
)
def test_unit_factors_to_si(unit, quantity, factor):
    assert si_factor(unit, quantity) == pytest.approx(factor)


@pytest.mark.parametrize(("unit", "quantity"), [(None, "speed"), ("", "speed"), ("km/h", "yaw_rate"), ("N", "speed")])
def test_missing_unknown_or_wrong_kind_of_unit_has_no_factor(unit, quantity):
    assert si_factor(unit, quantity) is None


# --- the reference DBC -----------------------------------------------------------------------------------------


def test_reference_dbc_frames_decode_to_si_golden_values():
    dec = reference_decoder()
    samples = (
        dec.decode(speed_frame(10.00, 72.0, 0))
        + dec.decode(yaw_frame(10.01, -12.5, 0, lat=1.5, lon=-0.25))
        + dec.decode(
            encode(ref_db(), "ESP_WHEEL_SPEEDS", 10.02, WHEEL_SPEED_FL=36, WHEEL_SPEED_FR=36.36, WHEEL_SPEED_RL=18)
        )
        + dec.decode(encode(ref_db(), "EPS_STEERING", 10.03, STEERING_ANGLE=-90.0))
    )
    got = by_quantity(samples)
    assert got == pytest.approx(
        {
            "speed": 20.0,
            "yaw_rate": -12.5 * DEG,
            "lat_accel": 1.5,
            "lon_accel": -0.25,
            "wheel_speed_fl": 10.0,
            "wheel_speed_fr": 10.1,
            "wheel_speed_rl": 5.0,
            "wheel_speed_rr": 0.0,
            "steering_angle": -math.pi / 2,
        },
        abs=1e-9,
    )
    assert {s.quantity: s.t for s in samples}["yaw_rate"] == 10.01
    assert dec.stats.decoded == 4 and dec.stats.frames == 4


def test_scale_minus_one_flips_a_sign_convention(tmp_path):
    config = write_config(
        tmp_path,
        f"""
        [can]
        dbc = "{REF_DBC}"
        signals.yaw_rate = {{ signal = "ESP_YAW_RATE.YAW_RATE", scale = -1 }}
        """,
    )
    dec = CanDecoder.from_config(config)
    (sample,) = dec.decode(yaw_frame(1.0, 10.0, 0))
    assert sample.value == pytest.approx(-10.0 * DEG)


def test_unit_override_gives_a_unitless_signal_its_unit():
    signals = {"speed": SignalSpec("EPS_STEERING", "STEERING_RATIO", unit="mph")}
    dec = CanDecoder(ref_db(), signals)
    (sample,) = dec.decode(encode(ref_db(), "EPS_STEERING", 0.0, STEERING_RATIO=10.0))
    assert sample.value == pytest.approx(4.4704)


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        (SignalSpec("NO_SUCH_MESSAGE", "X"), "no message 'NO_SUCH_MESSAGE'"),
        (SignalSpec("ESP_YAW_RATE", "NO_SUCH_SIGNAL"), "no signal 'NO_SUCH_SIGNAL'"),
        (SignalSpec("EPS_STEERING", "STEERING_RATIO"), "no unit"),
        (SignalSpec("ESP_YAW_RATE", "YAW_RATE"), "unit 'deg/s', not a speed unit"),
        (SignalSpec("ESP_YAW_RATE", "YAW_RATE", unit="furlongs"), "unit 'furlongs'"),
    ],
)
def test_mapping_mistakes_are_config_errors_naming_the_key(spec, expected):
    with pytest.raises(ConfigError, match=r"cfg\.toml: can\.signals\.speed: ") as err:
        CanDecoder(ref_db(), {"speed": spec}, source="cfg.toml")
    assert expected in str(err.value)


def test_empty_mapping_and_unknown_e2e_message_are_config_errors():
    with pytest.raises(ConfigError, match=r"can\.signals: no quantity mapped"):
        CanDecoder(ref_db(), {})
    with pytest.raises(ConfigError, match=r"can\.e2e: no message 'ESP_NOPE'"):
        CanDecoder(ref_db(), {"speed": SignalSpec("ESP_VEHICLE_SPEED", "VEHICLE_SPEED")}, e2e=["ESP_NOPE"])


def test_e2e_key_loads_from_toml(tmp_path):
    config = write_config(tmp_path, '[can]\ne2e = ["ESP_YAW_RATE"]\nsignals.yaw_rate = "ESP_YAW_RATE.YAW_RATE"\n')
    assert config.can.e2e == ("ESP_YAW_RATE",)
    dec = CanDecoder.from_config(config)
    good = yaw_frame(0.0, 1.0, 0)
    bad = std(good.arbitration_id, bytes([good.data[0] ^ 1]) + bytes(good.data[1:]))
    assert dec.decode(bad) == [] and dec.stats.crc_errors == 1


# --- dropping and counting bad frames -----------------------------------------------------------------------


def test_unused_ids_are_dropped_and_counted_with_a_bounded_id_table():
    dec = reference_decoder()
    for i in range(MAX_UNUSED_IDS + 10):
        assert dec.decode(std(0x700 + i % 0xFF, bytes(8))) == []
        assert dec.decode(can.Message(arbitration_id=0x1000 + i, is_extended_id=True, data=bytes(8))) == []
    assert dec.stats.unused == 2 * (MAX_UNUSED_IDS + 10)
    assert len(dec.stats.unused_ids) == MAX_UNUSED_IDS
    assert dec.stats.unused_ids[0x700] == 3  # 0x700 + i % 0xFF repeats every 255 frames
    assert dec.stats.decoded == 0


def test_error_and_remote_frames_are_ignored_and_counted():
    dec = reference_decoder()
    assert dec.decode(can.Message(is_error_frame=True, arbitration_id=0x40)) == []
    assert dec.decode(std(0x130, is_remote_frame=True, dlc=8)) == []
    assert (dec.stats.error_frames, dec.stats.remote_frames, dec.stats.frames) == (1, 1, 2)
    assert dec.stats.per_message["ESP_YAW_RATE"] == 0


def test_short_payload_is_a_counted_decode_error_logged_once(caplog):
    dec = reference_decoder()
    with caplog.at_level(logging.WARNING, logger="sumhe.io.can"):
        for _ in range(100):
            assert dec.decode(std(0x1B0, bytes(5))) == []
    assert dec.stats.decode_errors == 100
    assert len(caplog.records) == 1  # rate-limited, not one line per frame
    assert "ESP_WHEEL_SPEEDS: short payload (5 of 8 bytes)" in caplog.text


def test_crc_error_drops_jump_counts_repeat_drops():
    dec = reference_decoder()
    frames = [yaw_frame(0.01 * i, 1.0, i) for i in (14, 15, 0, 3)]  # 15 -> 0 wraps; 0 -> 3 loses two frames
    assert all(dec.decode(f) for f in frames)
    assert (dec.stats.counter_jumps, dec.stats.frames_lost) == (1, 2)
    assert dec.decode(yaw_frame(0.05, 1.0, 3)) == []  # the same counter again: a stale frame
    assert dec.stats.stale == 1
    corrupt = bytearray(yaw_frame(0.06, 1.0, 4).data)
    corrupt[3] ^= 0x10
    assert dec.decode(std(0x130, corrupt)) == []
    assert dec.stats.crc_errors == 1
    assert dec.decode(yaw_frame(0.07, 1.0, 4))  # the counter after a dropped frame is not a repeat
    assert dec.stats.decoded == 5


def test_unprotected_messages_are_not_crc_checked():
    dec = reference_decoder(**{"can.e2e": []})
    assert dec.decode(std(0x130, bytes(8)))  # CRC byte 0 is wrong
    assert dec.stats.crc_errors == 0


EXTRA_DBC = """VERSION ""
BS_:
BU_: ECU
BO_ 256 STD_WHEEL: 8 ECU
 SG_ WHEEL : 0|16@1+ (0.01,0) [0|655.35] "km/h" ECU
BO_ 2147483904 EXT_SPEED: 8 ECU
 SG_ SPEED : 0|16@1+ (0.1,0) [0|6553.5] "kph" ECU
BO_ 2566844926 CCVS1: 8 ECU
 SG_ WheelBasedVehicleSpeed : 8|16@1+ (0.00390625,0) [0|250.996] "km/h" ECU
BO_ 512 MUXED: 8 ECU
 SG_ MUX_ID M : 0|8@1+ (1,0) [0|255] "" ECU
 SG_ YAW_A m0 : 8|16@1- (0.01,0) [-327.68|327.67] "deg/s" ECU
 SG_ STEER_B m1 : 8|16@1- (0.1,0) [-3276.8|3276.7] "deg" ECU
BO_ 2566844672 EXT_MUXED: 8 ECU
 SG_ PAGE M : 0|8@1+ (1,0) [0|255] "" ECU
 SG_ YAW_P m3 : 8|16@1- (0.01,0) [-327.68|327.67] "deg/s" ECU
BO_ 513 FLOATS: 4 ECU
 SG_ ACCEL : 0|32@1- (1,0) [0|0] "g" ECU
SIG_VALTYPE_ 513 ACCEL : 1;
"""


@pytest.fixture(scope="module")
def extra_db():
    db = cantools.database.can.Database()
    db.add_dbc_string(EXTRA_DBC)
    return db


def test_extended_and_standard_ids_with_the_same_number_stay_apart(extra_db):
    signals = {
        "speed": SignalSpec("EXT_SPEED", "SPEED"),
        "wheel_speed_fl": SignalSpec("STD_WHEEL", "WHEEL"),
        "wheel_speed_fr": SignalSpec("CCVS1", "WheelBasedVehicleSpeed"),
    }
    dec = CanDecoder(extra_db, signals)
    data = struct.pack("<H", 360) + bytes(6)
    assert by_quantity(dec.decode(can.Message(arbitration_id=0x100, is_extended_id=True, data=data))) == pytest.approx(
        {"speed": 10.0}
    )
    assert by_quantity(dec.decode(std(0x100, data))) == pytest.approx({"wheel_speed_fl": 1.0})
    ccvs = can.Message(
        arbitration_id=0x18FEF1FE, is_extended_id=True, data=bytes([0]) + struct.pack("<H", 256 * 36) + bytes(5)
    )
    assert dec.decode(ccvs)[0].value == pytest.approx(10.0)
    filters = {(f["can_id"], f["extended"], f["can_mask"]) for f in dec.can_filters()}
    assert filters == {(0x100, True, 0x1FFFFFFF), (0x100, False, 0x7FF), (0x18FEF1FE, True, 0x1FFFFFFF)}
    assert EXTENDED_FLAG | 0x100 not in dec.stats.unused_ids and dec.stats.unused == 0


def test_multiplexed_signal_absent_or_unknown_mux_is_no_error(extra_db):
    dec = CanDecoder(extra_db, {"yaw_rate": SignalSpec("MUXED", "YAW_A")})
    assert dec.decode(std(0x200, bytes([0]) + struct.pack("<h", 1000) + bytes(5)))[0].value == pytest.approx(10 * DEG)
    assert dec.decode(std(0x200, bytes([1, 1, 0, 0, 0, 0, 0, 0]))) == []
    assert dec.decode(std(0x200, bytes([9, 1, 0, 0, 0, 0, 0, 0]))) == []  # a value the DBC does not know
    assert (dec.stats.decode_errors, dec.stats.other_mux, dec.stats.decoded) == (0, 2, 1)


def test_a_multiplexed_message_on_an_extended_id_decodes(extra_db):
    """The multiplexer decoded alone keeps the message's 29-bit id (the decoder is built, and decodes)."""
    dec = CanDecoder(extra_db, {"yaw_rate": SignalSpec("EXT_MUXED", "YAW_P")})
    frame = can.Message(
        arbitration_id=0x18FEF100, is_extended_id=True, data=bytes([3]) + struct.pack("<h", 500) + bytes(5)
    )
    assert dec.decode(frame)[0].value == pytest.approx(5 * DEG)
    other = can.Message(arbitration_id=0x18FEF100, is_extended_id=True, data=bytes([4]) + bytes(7))
    assert dec.decode(other) == [] and dec.stats.other_mux == 1


def test_non_finite_float_signal_never_becomes_a_sample(extra_db):
    dec = CanDecoder(extra_db, {"lat_accel": SignalSpec("FLOATS", "ACCEL")})
    assert dec.decode(std(0x201, struct.pack("<f", 0.5)))[0].value == pytest.approx(0.5 * 9.80665)
    assert dec.decode(std(0x201, struct.pack("<f", float("nan")))) == []
    assert dec.decode(std(0x201, struct.pack("<f", float("inf")))) == []
    assert dec.stats.decode_errors == 2


def test_every_message_mode_decodes_all_signals_in_dbc_units():
    dec = CanDecoder(ref_db(), {}, every_message=True)
    name, values = dec.decode_signals(encode(ref_db(), "GW_VEHICLE_STATUS", 1.0, IGNITION=2, ODOMETER=12345.6))
    assert name == "GW_VEHICLE_STATUS"
    assert values == pytest.approx({"IGNITION": 2.0, "ODOMETER": 12345.6})
    assert dec.decode_signals(std(0x7FF, bytes(8))) is None


SHARED_DBC = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real_drives" / "canedge_obd_2021-07-26_a"


def _dbcs(extra_db) -> list:
    dbs = [ref_db(), toyota_db(), extra_db, load_dbc(Path(__file__).resolve().parents[1] / "dbc" / "sumhe_prod.dbc")]
    return dbs + [load_dbc(p) for p in sorted(SHARED_DBC.glob("*.dbc"))]  # the real drive's, where it is


def test_a_message_with_only_the_signals_in_use_decodes_them_as_the_whole_message_to_the_bit(extra_db):
    """The decoder decodes only the signals its fields read (``_in_use``): for every message that is not
    multiplexed (little and big endian, signed, float, scaled and offset signals), random payloads give the same
    values, of the same types, as the whole message's decode; a multiplexed message, or one that cannot be decoded
    at all (its frames stay decode errors), is kept whole."""
    rng = random.Random(16)
    checked = kept = 0
    for db in _dbcs(extra_db):
        for message in db.messages:
            names = [s.name for s in message.signals]
            for k in (1, 2, len(names)):
                used = rng.sample(names, min(k, len(names)))
                part = _in_use(message, used)
                if message.is_multiplexed() or part is message:
                    assert part is message
                    kept += 1
                    continue
                for _ in range(20):
                    data = bytes(rng.getrandbits(8) for _ in range(message.length))
                    whole = message.decode(data, decode_choices=False)
                    got = part.decode(data, decode_choices=False)
                    assert set(got) == set(used)
                    for name in used:
                        assert type(got[name]) is type(whole[name])
                        assert repr(got[name]) == repr(whole[name]), (message.name, name, data.hex())
                    checked += 1
    assert checked > 1000 and kept > 0
    with pytest.raises(cantools.database.errors.DecodeError):  # a message kept whole: no decode at all
        toyota_db().get_message_by_name("PCS_HUD").decode(bytes(8))


def _outcome(decode, data):
    """What a decode gives: its values (with their types, as text) or its error's type and words."""
    try:
        return [(k, type(v).__name__, repr(v)) for k, v in decode(data).items()]
    except Exception as e:
        return (type(e).__name__, str(e))


def test_the_decoding_without_cantools_layers_is_cantools_decode_to_the_bit(extra_db):
    """``_decoding`` gives what ``Message.decode(data, decode_choices=False)`` gives (the same values of the same
    types in the same order, or the same error) for every message of the DBCs at hand, whole and with the signals
    of a field alone, on random payloads of its length, shorter and longer."""
    rng = random.Random(17)
    fast = 0
    for db in _dbcs(extra_db):
        for message in db.messages:
            names = [s.name for s in message.signals]
            for part in {id(m): m for m in (message, _in_use(message, rng.sample(names, min(2, len(names)))))}.values():
                decode, whole = _decoding(part), _whole(part)
                fast += not message.is_multiplexed()
                for n in (part.length, part.length, part.length, max(part.length - 1, 0), part.length + 1):
                    data = bytes(rng.getrandbits(8) for _ in range(n))
                    assert _outcome(decode, data) == _outcome(whole, data), (message.name, data.hex())
    assert fast > 40


# --- the acceptance case: a public production-car DBC by config alone -----------------------------------------


def toyota_config(tmp_path, strict: bool):
    return write_config(
        tmp_path,
        f"""
        [can]
        dbc = "{TOYOTA_DBC.name}"
        dbc_strict = {str(strict).lower()}
        signals.speed = "SPEED.SPEED"
        signals.yaw_rate = "KINEMATICS.YAW_RATE"
        signals.lat_accel = "KINEMATICS.ACCEL_Y"
        """,
    )


@pytest.fixture
def toyota_dir(tmp_path):
    (tmp_path / TOYOTA_DBC.name).write_bytes(TOYOTA_DBC.read_bytes())
    return tmp_path


def test_opendbc_toyota_speed_and_yaw_rate_decode_by_config_alone(toyota_dir):
    dec = CanDecoder.from_config(toyota_config(toyota_dir, strict=False))
    db = toyota_db()
    speed = dec.decode(encode(db, "SPEED", 5.0, SPEED=90.0, ENCODER=17))
    assert by_quantity(speed) == pytest.approx({"speed": 25.0})
    # YAW_RATE is 0.244 deg/s per bit with offset -125 deg/s: raw 553 is +9.932 deg/s (turning left)
    left = by_quantity(dec.decode(encode(db, "KINEMATICS", 5.01, YAW_RATE=9.932, ACCEL_Y=2.0)))
    assert left["yaw_rate"] == pytest.approx(9.932 * DEG, abs=1e-9)
    assert left["lat_accel"] == pytest.approx(2.0, abs=0.03589 / 2)
    right = by_quantity(dec.decode(encode(db, "KINEMATICS", 5.02, YAW_RATE=-20.0)))
    assert right["yaw_rate"] < 0
    assert right["yaw_rate"] == pytest.approx(-20.0 * DEG, abs=0.122 * DEG)


def test_opendbc_toyota_needs_strict_false_and_says_so(toyota_dir):
    with pytest.raises(ConfigError) as err:
        CanDecoder.from_config(toyota_config(toyota_dir, strict=True))
    text = str(err.value)
    assert TOYOTA_DBC.name in text and "overlapping" in text and "dbc_strict = false" in text


def test_load_dbc_errors_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match=r"missing\.dbc: DBC file not found"):
        load_dbc(tmp_path / "missing.dbc")
    bad = tmp_path / "bad.dbc"
    bad.write_text("BO_ garbage here\n")
    with pytest.raises(ConfigError, match=r"bad\.dbc: not a valid CAN database"):
        load_dbc(bad)
    assert load_dbc(REF_DBC).get_message_by_name("ESP_YAW_RATE").frame_id == 0x130


# --- log files ---------------------------------------------------------------------------------------------------


def sample_frames() -> list[can.Message]:
    frames = [yaw_frame(100.0 + 0.01 * i, 0.5 * i, i) for i in range(20)]
    frames.append(can.Message(timestamp=100.3, arbitration_id=0x18FEF1FE, is_extended_id=True, data=b"\x01\x02"))
    return frames


@pytest.mark.parametrize("suffix", [".log", ".log.gz", ".asc", ".blf", ".trc", ".csv"])
def test_read_log_reads_every_python_can_format(tmp_path, suffix):
    path = tmp_path / f"drive{suffix}"
    frames = sample_frames()
    with can.Logger(path) as writer:
        for msg in frames:
            writer.on_message_received(msg)
    stats = LogStats()
    got = list(read_log(path, stats))
    assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in got] == [
        (m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in frames
    ]
    assert stats.frames == len(frames) and stats.malformed == 0


def test_python_can_candump_reader_alone_stops_at_a_garbled_line(tmp_path):
    """Why read_log filters candump lines first: CanutilsLogReader raises and its iterator is finished."""
    path = tmp_path / "x.log"
    path.write_text("(1.0) vcan0 130#00\n(1.1) vcan0 13G#00\n(1.2) vcan0 130#01\n")
    reader = can.LogReader(path)
    it = iter(reader)
    assert next(it).data == b"\x00"
    with pytest.raises(ValueError):
        next(it)
    reader.stop()


GARBLED = [
    "(1.1) vcan0 13G#00",
    "(1.2) vcan0 130#0",
    "1.3 vcan0 130#00",
    "(1.4) vcan0 130 00",
    "(1.5) vcan0 1300#00",
    "(abc) vcan0 130#00",
    "\x00\x01garbage\xff",
    "(1.6) vcan0 130#00112233 X",
    "(1.7) vcan0 130##Z00",
]


def test_read_log_skips_and_counts_garbled_candump_lines(tmp_path, caplog):
    path = tmp_path / "drive.log"
    good = ["(1.0) vcan0 130#0011", "(2.0) vcan0 18FEF1FE#01 R", "(3.0) vcan0 7FF#R", "(4.0) vcan0 123##1AABB"]
    with path.open("w", encoding="latin-1") as f:
        for g, b in zip(good, GARBLED, strict=False):
            f.write(f"{g}\n{b}\n\n")
        f.write("\n".join(GARBLED[len(good) :]) + "\n")
    stats = LogStats()
    with caplog.at_level(logging.WARNING, logger="sumhe.io.can"):
        got = list(read_log(path, stats))
    assert [(m.timestamp, m.arbitration_id) for m in got] == [
        (1.0, 0x130),
        (2.0, 0x18FEF1FE),
        (3.0, 0x7FF),
        (4.0, 0x123),
    ]
    assert got[1].is_extended_id and got[2].is_remote_frame and got[3].is_fd and got[3].data == b"\xaa\xbb"
    assert stats.malformed == len(GARBLED) and stats.frames == 4
    assert len(caplog.records) == 1


def test_read_log_file_errors_are_source_errors(tmp_path):
    with pytest.raises(SourceError, match="not found"):
        read_log(tmp_path / "absent.log")
    (tmp_path / "drive.xyz").write_text("")
    with pytest.raises(SourceError, match="unsupported CAN log format"):
        read_log(tmp_path / "drive.xyz")
    (tmp_path / "junk.blf").write_bytes(b"\x00" * 300)
    with pytest.raises(SourceError, match="cannot read CAN log"):
        read_log(tmp_path / "junk.blf")


def test_corrupt_binary_or_csv_log_ends_early_without_crashing(tmp_path):
    csv_path = tmp_path / "drive.csv"
    csv_path.write_text("timestamp,arbitration_id,extended,remote,error,dlc,data\n1.0,0x130,0,0,0,2,AQI=\ngarbage\n")
    stats = LogStats()
    assert [m.arbitration_id for m in read_log(csv_path, stats)] == [0x130]
    assert stats.malformed == 1 and "ValueError" in stats.error
    fake_gz = tmp_path / "drive.log.gz"
    fake_gz.write_bytes(b"not gzip at all")
    stats = LogStats()
    assert list(read_log(fake_gz, stats)) == [] and stats.error
    gz = tmp_path / "ok.log.gz"
    with gzip.open(gz, "wt") as f:
        f.write("(1.0) vcan0 130#00\n")
    assert len(list(read_log(gz))) == 1


def test_candump_frames_equal_python_cans_reader(tmp_path):
    """sumhe parses classic candump lines itself (python-can's reader takes the rest): the same frames, field by
    field, for classic, extended, empty, CAN FD, remote and error frames, channel names and numbers, R/T flags."""
    from sumhe.sim import bundled_drive_dir

    lines = [
        "(1700000000.000100) can0 123#DEADBEEF",
        "(1700000000.000200) vcan1 18FEF100#0102030405060708 T",
        "(1700000000.000300) 1 7E8#",
        "(1700000000.000400) can0 456##1112233445566778899AABBCCDDEEFF00",
        "(1700000000.000500) can0 123#R",
        "(1700000000.000600) can0 123#R4 R",
        "(1700000000.000700) can0 20000080#0000000000000000",
        "(1700000000.000800) can0 7ff#00aaBB r",
    ]
    log = tmp_path / "mixed.log"
    log.write_text("\n".join(lines) + "\n")
    bundled = bundled_drive_dir() / "drive.log"
    for path in (log, bundled):
        ours = [tuple(getattr(m, f) for f in MESSAGE_FIELDS) for m in read_log(path)]
        with can.CanutilsLogReader(path) as reader:
            theirs = [tuple(getattr(m, f) for f in MESSAGE_FIELDS) for m in reader]
        assert ours == theirs and len(ours) >= len(lines)
