"""``sumhe candump``: candump -L logs written here with cantools + python-can, decoded back to golden values."""

import json
import math
import sys

import can
import pytest

from sumhe.cli import main
from sumhe.io.can import REFERENCE_E2E, REFERENCE_SIGNALS

from canframes import ROOT, TOYOTA_DBC, encode, ref_db, speed_frame, toyota_db, yaw_frame

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

DEG = math.pi / 180
T0 = 1780300800.0


def write_candump(path, frames, extra_lines=()) -> None:
    with can.CanutilsLogWriter(path, channel="can0") as writer:
        for msg in frames:
            writer.on_message_received(msg)
    with path.open("a") as f:
        f.writelines(line + "\n" for line in extra_lines)


def reference_drive() -> list[can.Message]:
    """One second: yaw 100 Hz, speed 50 Hz, steering 100 Hz, an unknown id 3 times, one bad CRC, one stale frame."""
    frames = []
    for i in range(100):
        t = T0 + 0.01 * i
        frames.append(yaw_frame(t, 0.1 * i, i, lat=0.01 * i))
        frames.append(encode(ref_db(), "EPS_STEERING", t + 0.001, STEERING_ANGLE=i - 50))
        if i % 2 == 0:
            frames.append(speed_frame(t + 0.002, 3.6 * i, i // 2))
    for k in range(3):
        frames.append(
            can.Message(timestamp=T0 + 0.3 + 0.2 * k, arbitration_id=0x7FF, is_extended_id=False, data=bytes(8))
        )
    bad = yaw_frame(T0 + 0.505, 99.0, 51)
    bad.data[0] ^= 0xFF
    frames.append(bad)
    frames.append(speed_frame(T0 + 0.506, 99.0, 25))  # counter 25 % 16 again right after frame 50 / 2: stale
    frames.sort(key=lambda m: m.timestamp)
    return frames


GARBLED = ["(1780300800.5) can0 13G#00", "this is not candump"]


def run_cli(capsys, *argv):
    rc = main(["candump", *map(str, argv)])
    out, err = capsys.readouterr()
    return rc, [json.loads(line) for line in out.splitlines()], err


def test_reference_log_decodes_to_golden_si_values(tmp_path, capsys):
    log_path = tmp_path / "drive.log"
    write_candump(log_path, reference_drive(), GARBLED)
    rc, lines, err = run_cli(capsys, log_path)
    assert rc == 0
    by_q: dict[str, list[dict]] = {}
    for line in lines:
        by_q.setdefault(line["quantity"], []).append(line)
    assert [x["value"] for x in by_q["yaw_rate"]] == pytest.approx([0.1 * i * DEG for i in range(100)], abs=1e-9)
    assert [x["value"] for x in by_q["lat_accel"]] == pytest.approx([0.01 * i for i in range(100)], abs=1e-9)
    assert [x["value"] for x in by_q["speed"]] == pytest.approx([float(i) for i in range(0, 100, 2)], abs=1e-9)
    assert [x["value"] for x in by_q["steering_angle"]] == pytest.approx([(i - 50) * DEG for i in range(100)])
    assert [x["t"] for x in by_q["speed"]] == pytest.approx([T0 + 0.01 * i + 0.002 for i in range(0, 100, 2)])
    assert {x["message"] for x in by_q["yaw_rate"]} == {"ESP_YAW_RATE"}
    assert set(by_q) == {"yaw_rate", "lat_accel", "lon_accel", "speed", "steering_angle"}
    assert set(lines[0]) == {"t", "message", "quantity", "value"}

    assert "frames: 255 over 0.991 s" in err
    assert "CRC errors 1" in err and "stale 1" in err and "malformed log lines 2" in err
    assert "ESP_YAW_RATE: 101 frames, 101.9 Hz" in err  # mean over the log span
    assert "ESP_VEHICLE_SPEED: 51 frames" in err
    assert "unused ids: 0x7FF (3)" in err


def test_opendbc_toyota_log_by_config_alone(tmp_path, capsys):
    config = tmp_path / "toyota.toml"
    config.write_text(
        f"""
        [can]
        dbc = "{TOYOTA_DBC.as_posix()}"
        dbc_strict = false
        signals.speed = "SPEED.SPEED"
        signals.yaw_rate = "KINEMATICS.YAW_RATE"
        """
    )
    db = toyota_db()
    frames = [
        encode(db, "SPEED", 1.00, SPEED=50.4),
        encode(db, "KINEMATICS", 1.01, YAW_RATE=9.932),
        encode(db, "KINEMATICS", 1.02, YAW_RATE=-10.076),
        can.Message(timestamp=1.03, arbitration_id=0x18FEF1FE, is_extended_id=True, data=bytes(8)),
    ]
    log_path = tmp_path / "toyota.log"
    write_candump(log_path, frames)
    rc, lines, err = run_cli(capsys, log_path, "--config", config)
    assert rc == 0
    assert [(x["message"], x["quantity"]) for x in lines] == [
        ("SPEED", "speed"),
        ("KINEMATICS", "yaw_rate"),
        ("KINEMATICS", "yaw_rate"),
    ]
    assert [x["value"] for x in lines] == pytest.approx([14.0, 9.932 * DEG, -10.076 * DEG], abs=1e-9)
    assert "unused ids: 0x18FEF1FE (1)" in err


def test_all_prints_every_signal_in_dbc_units(tmp_path, capsys):
    log_path = tmp_path / "drive.log"
    frames = [
        encode(ref_db(), "GW_VEHICLE_STATUS", 5.0, IGNITION=2, ODOMETER=4321.5),
        speed_frame(5.01, 36.0, 0),
    ]
    write_candump(log_path, frames)
    rc, lines, err = run_cli(capsys, log_path, "--all")
    assert rc == 0
    got = {(x["message"], x["signal"]): (x["value"], x["unit"]) for x in lines}
    assert got[("GW_VEHICLE_STATUS", "ODOMETER")] == (pytest.approx(4321.5), "km")
    assert got[("GW_VEHICLE_STATUS", "IGNITION")] == (2.0, "")
    assert got[("ESP_VEHICLE_SPEED", "VEHICLE_SPEED")] == (pytest.approx(36.0), "km/h")
    assert len(lines) == 2 + 5
    assert "GW_VEHICLE_STATUS: 1 frames" in err


def test_empty_log_prints_nothing_and_a_zero_summary(tmp_path, capsys):
    log_path = tmp_path / "empty.log"
    log_path.write_text("")
    rc, lines, err = run_cli(capsys, log_path)
    assert (rc, lines) == (0, [])
    assert err.startswith("frames: 0 over 0.000 s")


def test_missing_log_and_bad_config_are_errors_not_tracebacks(tmp_path, capsys):
    rc, lines, err = run_cli(capsys, tmp_path / "absent.log")
    assert rc == 1 and lines == [] and err.startswith("error: ") and "CAN log not found" in err
    config = tmp_path / "bad.toml"
    config.write_text('[can]\nsignals.speed = "ESP_VEHICLE_SPEED.NOPE"\n')
    log_path = tmp_path / "drive.log"
    write_candump(log_path, [speed_frame(1.0, 1.0, 0)])
    rc, lines, err = run_cli(capsys, log_path, "--config", config)
    assert rc == 1 and "can.signals.speed: no signal 'NOPE'" in err


def test_default_config_maps_what_candump_uses_without_one():
    path = ROOT / "configs" / "default.toml"
    if not path.is_file():
        pytest.skip("configs/default.toml not written yet")
    can_table = tomllib.loads(path.read_text())["can"]
    assert can_table.get("signals") == REFERENCE_SIGNALS
    assert tuple(can_table.get("e2e", ())) == REFERENCE_E2E
