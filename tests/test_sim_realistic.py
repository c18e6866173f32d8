"""The realistic profile: every real-car error is in the generated files with its configured size, per seed."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from pathlib import Path

import can
import cantools
import numpy as np
import pytest

from sumhe.cli import main
from sumhe.config import load_config
from sumhe.io.can import CanDecoder, read_log
from sumhe.io.nmea import iter_fixes
from sumhe.sim import PROFILES, SimSettings, load_settings, load_truth, profile_settings, simulate, write_drive
from sumhe.sim.measure import lever_arm, measure_errors
from sumhe.sim.obd import POLLED_PIDS, SPEED_PID
from sumhe.sim.production import OBD_DBC, OBD_REPLY_ID, OBD_REQUEST_ID, quantised_layout
from sumhe.sim.profiles import REALISTIC, Choice, Uniform
from sumhe.sim.vehicle import Body, Trajectory

REAL_DRIVE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_drives" / "canedge_obd_2021-07-26_a"
EXACT_GNSS = {"gps_error_m": 0.02, "gps_outliers_per_min": 0.0, "multipath_per_min": 0.0, "gps_drop_rate": 0.0}
"""Centimetre GNSS without outliers: what is left of a fix's error is the effect under test."""


def realistic(seed: int, **fixed: object) -> SimSettings:
    return profile_settings("realistic", seed, duration_s=90.0, **fixed)


@pytest.fixture(scope="module")
def broadcast_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("broadcast")
    write_drive(simulate(realistic(11, speed_source="broadcast", scenario="urban")), out)
    return out


@pytest.fixture(scope="module")
def obd_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("obd")
    write_drive(simulate(realistic(12, speed_source="obd", obd_rate_hz=2.0, scenario="urban")), out)
    return out


# --- profiles --------------------------------------------------------------------------------------------------


def test_kind_profile_is_the_default_settings() -> None:
    assert profile_settings("kind", 7) == SimSettings(seed=7)
    assert profile_settings("kind", 7, scenario="highway") == SimSettings(seed=7, scenario="highway")


def test_realistic_draws_stay_in_their_ranges_and_vary_with_the_seed() -> None:
    drawn = [realistic(seed) for seed in range(30)]
    for name, spec in REALISTIC.items():
        values = [getattr(s, name) for s in drawn]
        if isinstance(spec, Uniform):
            assert all(spec.low <= v <= spec.high for v in values), name
            assert len(set(values)) == len(values), name
        elif isinstance(spec, Choice):
            assert set(values) <= set(spec.options), name
            assert len(set(values)) > 1, name
        else:
            assert set(values) == {spec}, name
    assert all(s.profile == "realistic" for s in drawn)


def test_fixed_fields_override_and_leave_the_other_draws_alone() -> None:
    a, b = realistic(3), realistic(3, gps_time_offset_s=0.0, scenario="highway")
    assert b.gps_time_offset_s == 0.0 and b.scenario == "highway"
    changed = {f.name for f in dataclasses.fields(SimSettings) if getattr(a, f.name) != getattr(b, f.name)}
    assert changed == {"gps_time_offset_s", "scenario"}


def test_profile_rejects_bad_names() -> None:
    with pytest.raises(ValueError, match="wheels"):
        profile_settings("realistic", 0, wheels=3)
    with pytest.raises(ValueError, match="profile"):
        profile_settings("harsh", 0)
    assert set(PROFILES) == {"kind", "realistic"}


def test_same_seed_same_bytes_and_scenario_toml_regenerates(tmp_path: Path, broadcast_dir: Path) -> None:
    again = tmp_path / "again"
    write_drive(simulate(load_settings(broadcast_dir / "scenario.toml")), again)
    names = sorted(p.name for p in broadcast_dir.iterdir())
    assert names == ["config.toml", "drive.log", "drive.nmea", "scenario.toml", "truth.csv", "vehicle.dbc"]
    for name in names:
        assert (broadcast_dir / name).read_bytes() == (again / name).read_bytes(), name
    other = tmp_path / "other"
    write_drive(simulate(realistic(13, speed_source="broadcast")), other)
    assert (other / "drive.log").read_bytes() != (broadcast_dir / "drive.log").read_bytes()


def test_scenario_toml_records_the_true_errors(broadcast_dir: Path) -> None:
    import tomllib

    data = tomllib.loads((broadcast_dir / "scenario.toml").read_text(encoding="utf-8"))
    sim, cal = data["sim"], data["calibration"]
    for key in ("gps_time_offset_s", "yaw_rate_scale", "antenna_forward_m", "antenna_left_m", "speed_scale"):
        assert key in sim, key
    assert set(cal) == {"gps_time_offset_s", "speed_scale", "yaw_rate_bias_dps", "yaw_rate_scale", "can_delay_s"}
    assert cal["gps_time_offset_s"] == sim["gps_time_offset_s"]
    assert cal["speed_scale"] == pytest.approx(1.0 / sim["speed_scale"])
    assert cal["yaw_rate_scale"] == pytest.approx(1.0 / sim["yaw_rate_scale"])
    assert cal["yaw_rate_bias_dps"] == pytest.approx(sim["yaw_rate_bias_dps"], abs=0.1)


# --- GNSS ------------------------------------------------------------------------------------------------------


def _offset_from_files(directory: Path, settings: SimSettings) -> float:
    """The clock offset that best places the NMEA fixes on the truth (grid of 5 ms, lever arm applied)."""
    truth = load_truth(directory / "truth.csv")
    fixes = [f for f in iter_fixes(directory / "drive.nmea") if f.valid and f.time_utc is not None]
    tag = np.array([f.time_utc.timestamp() for f in fixes])
    from sumhe.geo import LocalFrame

    frame = LocalFrame(settings.datum_lat_deg, settings.datum_lon_deg, settings.datum_alt_m)
    measured = frame.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes], settings.datum_alt_m)[:, :2]
    moving = truth.at(tag).speed > 5.0
    grid = np.arange(-0.5, 0.5001, 0.005)
    cost = []
    for d in grid:
        at = truth.at(tag + d)
        ant = np.column_stack([at.east, at.north]) + lever_arm(truth, tag + d, settings)
        cost.append(np.mean(np.hypot(*(measured - ant)[moving].T)))
    return float(grid[int(np.argmin(cost))])


@pytest.mark.parametrize("offset", [-0.27, 0.0, 0.21])
def test_gnss_time_offset_is_recovered_from_the_nmea(tmp_path: Path, offset: float) -> None:
    settings = realistic(21, scenario="highway", gps_time_offset_s=offset, gps_clock_drift_ppm=0.0, **EXACT_GNSS)
    write_drive(simulate(settings), tmp_path)
    assert _offset_from_files(tmp_path, settings) == pytest.approx(offset, abs=0.011)


def test_nmea_receive_latency_follows_the_true_time(tmp_path: Path) -> None:
    settings = realistic(22, gps_time_offset_s=-0.2, gps_clock_drift_ppm=0.0, gps_drop_rate=0.0)
    drive = simulate(settings)
    e = drive.gps[0]
    lag = e.t_rx[e.sent] - (e.t_fix[e.sent] + settings.gps_time_offset_s)
    serial = 0.02
    assert lag.min() >= settings.gps_latency_s
    assert lag.max() <= settings.gps_latency_s + settings.gps_latency_jitter_s + serial
    assert drive.applied["gps_receive_minus_tag_s"] == pytest.approx(float(np.mean(lag)) - 0.2, abs=1e-6)


def test_nmea_without_hdop_and_gst_at_one_hertz(tmp_path: Path) -> None:
    settings = realistic(23, gps_rate_hz=1.0, gps_nmea_hdop=False, gps_nmea_gst=False, gps_talker="GN")
    write_drive(simulate(settings), tmp_path)
    lines = (tmp_path / "drive.nmea").read_text(encoding="ascii").splitlines()
    gga = [line.split(" ", 1)[1] for line in lines if "GGA" in line]
    assert gga and all(s.startswith("$GNGGA") for s in gga)
    assert all(s.split(",")[8] == "" for s in gga)
    assert not any("GST" in line for line in lines)
    fixes = [f for f in iter_fixes(tmp_path / "drive.nmea") if f.valid]
    assert all(f.hdop is None and f.sigma_lat_m is None for f in fixes)
    tags = np.array([f.time_utc.timestamp() for f in fixes if f.time_utc is not None])
    assert np.all(np.mod(tags, 1.0) == 0.0)
    assert set(np.round(np.diff(tags), 6)) <= {1.0, 2.0, 3.0}


def test_dropped_epochs_and_heavy_tailed_outliers() -> None:
    settings = realistic(24, gps_rate_hz=10.0, gps_drop_rate=0.05, gps_outliers_per_min=20.0, gps_outlier_m=5.0)
    settings = dataclasses.replace(settings, gps_error_m=0.05, multipath_per_min=0.0, duration_s=300.0)
    e = simulate(settings).gps[0]
    assert np.mean(~e.sent) == pytest.approx(0.05, abs=0.015)
    err = np.hypot(e.error_east, e.error_north)[e.valid]
    big = err > 2.0
    # ~100 events of 0.1-1.5 s over 300 s cover ~25 % of the epochs; exp(-2/5) of them exceed 2 m
    assert 0.08 < big.mean() < 0.3
    assert err.max() > 12.0


def test_lever_arm_moves_the_fix_with_the_heading(tmp_path: Path) -> None:
    settings = realistic(
        25, antenna_forward_m=2.0, antenna_left_m=0.3, gps_time_offset_s=0.0, gps_clock_drift_ppm=0.0, **EXACT_GNSS
    )
    write_drive(simulate(settings), tmp_path)
    rows = {r.name: r for r in measure_errors(tmp_path)}
    assert rows["GPS1 horizontal position error"].mean == pytest.approx(math.hypot(2.0, 0.3), abs=0.1)
    assert rows["GPS1 error vs true antenna at tag + offset"].p95 < 0.1


def test_course_differs_from_the_path_in_turns_by_the_lever_arm(tmp_path: Path) -> None:
    settings = realistic(
        26,
        scenario="urban",
        antenna_forward_m=2.5,
        antenna_left_m=0.0,
        sideslip_deg_per_mps2=0.0,
        gps_velocity_sigma_mps=0.001,
        **EXACT_GNSS,
    )
    drive = simulate(settings)
    e = drive.gps[0]
    at = drive.truth.at(e.t_fix + settings.gps_time_offset_s)
    use = e.valid & (at.speed > 5.0) & np.isfinite(e.course)
    err = np.angle(np.exp(1j * (e.course - at.azimuth)))[use]
    expected = -np.arctan2(2.5 * at.yaw_rate, at.speed)[use]
    assert np.degrees(np.abs(err)).max() > 1.0
    assert np.degrees(np.abs(err - expected)).max() < 0.1


def test_body_yaw_rate_integrates_to_the_body_heading() -> None:
    from sumhe.sim.routes import build_route

    trajectory = Trajectory(build_route("urban", 120.0, np.random.default_rng(4), 2.7))
    body = Body(trajectory, math.radians(0.5), math.radians(0.3))
    t = np.arange(0.0, 120.0, 0.001)
    m = trajectory.at(t)
    integrated = -np.concatenate([[0.0], np.cumsum((body.yaw_rate(m)[1:] + body.yaw_rate(m)[:-1]) / 2 * 0.001)])
    heading = body.heading(m)
    assert np.abs(integrated - (heading - heading[0])).max() < 1e-3
    assert np.abs(body.heading(m) - m.azimuth).max() > math.radians(0.6)


# --- CAN -------------------------------------------------------------------------------------------------------


def _decoded(directory: Path, message: str) -> tuple[np.ndarray, list[dict[str, float]]]:
    db = cantools.database.load_file(str(directory / "vehicle.dbc"))
    msg = db.get_message_by_name(message)
    frames = [m for m in read_log(directory / "drive.log") if m.arbitration_id == msg.frame_id]
    return np.array([m.timestamp for m in frames]), [msg.decode(bytes(m.data), decode_choices=False) for m in frames]


@pytest.mark.parametrize("quantum", [0.244, 0.1])
def test_yaw_rate_quantum_offset_and_scale_in_the_decoded_frames(tmp_path: Path, quantum: float) -> None:
    settings = realistic(
        31,
        speed_source="broadcast",
        yaw_rate_quantum_dps=quantum,
        yaw_rate_scale=0.92,
        sideslip_deg_per_mps2=0.0,
        yaw_rate_bias_drift_dps=0.0,
    )
    write_drive(simulate(settings), tmp_path)
    t, values = _decoded(tmp_path, "VSA_MOTION")
    yaw = np.array([v["YAW_RATE"] for v in values])
    _, offset = quantised_layout(quantum, 125.0)
    steps = (yaw - offset) / quantum
    assert np.allclose(steps, np.round(steps), atol=1e-6)
    assert len(np.unique(yaw)) > 10
    truth = load_truth(tmp_path / "truth.csv").at(t - settings.can_sensor_delay_s)
    a = np.column_stack([np.degrees(truth.yaw_rate), np.ones(len(t))])
    (scale, bias), *_ = np.linalg.lstsq(a, yaw, rcond=None)
    assert scale == pytest.approx(0.92, abs=0.01)
    assert bias == pytest.approx(settings.yaw_rate_bias_dps, abs=0.1)


def test_speed_scale_and_quantum_in_the_decoded_frames(broadcast_dir: Path) -> None:
    settings = load_settings(broadcast_dir / "scenario.toml")
    t, values = _decoded(broadcast_dir, "VSA_SPEED")
    kmh = np.array([v["VEHICLE_SPEED"] for v in values])
    steps = kmh / settings.speed_quantum_kmh
    assert np.allclose(steps, np.round(steps), atol=1e-6)
    truth = load_truth(broadcast_dir / "truth.csv").at(t - settings.can_sensor_delay_s)
    moving = truth.speed > 5.0
    ratio = np.median(kmh[moving] / 3.6 / truth.speed[moving])
    assert ratio == pytest.approx(settings.speed_scale, abs=0.003)


def test_production_frames_have_counters_and_sum_checksums(broadcast_dir: Path) -> None:
    frames = [m for m in read_log(broadcast_dir / "drive.log") if m.arbitration_id == 0x025]
    for m in frames[:200]:
        data = bytes(m.data)
        assert data[7] == (0x00 + 0x25 + 8 + sum(data[:7])) & 0xFF
    _, values = _decoded(broadcast_dir, "VSA_MOTION")
    counters = np.array([v["VSA_MOTION_COUNTER"] for v in values])
    assert set(np.diff(counters) % 16) <= {1, 2}


def test_usb_burst_timestamps() -> None:
    settings = realistic(32, speed_source="broadcast", can_poll_max_s=0.017, can_burst_per_min=0.0)
    frames = simulate(dataclasses.replace(settings, duration_s=60.0)).can_frames
    t = np.array([m.timestamp for m in frames])
    gaps = np.diff(t)
    assert np.mean(gaps < 0.0002) > 0.5
    yaw = np.diff([m.timestamp for m in frames if m.arbitration_id == 0x025]) * 1000.0
    assert yaw.min() < 0.5
    assert 20.0 < yaw.max() < 32.0
    assert np.median(yaw) == pytest.approx(12.0, abs=2.0)


def test_obd_replies_decode_to_whole_kmh_at_the_poll_rate(obd_dir: Path) -> None:
    settings = load_settings(obd_dir / "scenario.toml")
    db = cantools.database.load_file(str(OBD_DBC))
    frames = list(read_log(obd_dir / "drive.log"))
    requests = [m for m in frames if m.arbitration_id == OBD_REQUEST_ID]
    assert {bytes(m.data)[2] for m in requests} == set(POLLED_PIDS)
    assert all(bytes(m.data)[:2] == b"\x02\x01" for m in requests)
    replies = [m for m in frames if m.arbitration_id == OBD_REPLY_ID]
    decoded = [(m.timestamp, db.decode_message(2024, bytes(m.data), decode_choices=False)) for m in replies]
    speed = [(t, v["VehicleSpeed"]) for t, v in decoded if v["PID"] == SPEED_PID]
    t, kmh = np.array(speed).T
    assert np.all(kmh == np.round(kmh)) and kmh.max() > 20
    assert np.median(np.diff(t)) == pytest.approx(0.5, abs=0.01)
    truth = load_truth(obd_dir / "truth.csv").at(t - settings.obd_delay_s)
    expected = truth.speed * settings.speed_scale * 3.6
    assert np.abs(kmh - expected).max() < 1.2
    assert {m.channel for m in frames} == {"can0", "can1"}


def test_obd_drive_decodes_with_its_config(obd_dir: Path) -> None:
    config = load_config(obd_dir / "config.toml")
    decoder = CanDecoder.from_config(config)
    samples = [s for m in read_log(obd_dir / "drive.log") for s in decoder.decode(m)]
    speeds = [s.value for s in samples if s.quantity == "speed"]
    yaw = [s.value for s in samples if s.quantity == "yaw_rate"]
    assert len(speeds) > 100 and len(yaw) > 5000
    settings = load_settings(obd_dir / "scenario.toml")
    truth = load_truth(obd_dir / "truth.csv")
    yaw_t = np.array([s.t for s in samples if s.quantity == "yaw_rate"])
    turning = np.abs(truth.at(yaw_t).yaw_rate) > 0.1
    # the config's sign makes the upside-down IMU read anticlockwise positive
    assert np.mean(np.sign(np.array(yaw)[turning]) == np.sign(truth.at(yaw_t).yaw_rate[turning])) > 0.95
    assert settings.imu_sign in (1, -1)


@pytest.mark.parametrize("fixture", ["broadcast_dir", "obd_dir"])
def test_replay_runs_on_a_realistic_drive(
    fixture: str, request: pytest.FixtureRequest, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d: Path = request.getfixturevalue(fixture)
    out = tmp_path / "est.jsonl"
    argv = ["replay", str(d / "drive.log"), "--nmea", str(d / "drive.nmea"), "--config", str(d / "config.toml")]
    assert main([*argv, "--estimator", "ekf", "--out", str(out)]) == 0
    assert len(out.read_text(encoding="utf-8").splitlines()) > 50
    assert "replay: ekf" in capsys.readouterr().err


def test_a_replay_with_fixes_ahead_of_the_can_data_writes_every_can_rate_estimate(
    broadcast_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # the fixes' positions true 0.3 s after their stamps: the MHE's epoch estimates are stamped ahead of the CAN data;
    # written at once they dropped every CAN-rate estimate until their time (80 % of them on a 300 s drive)
    config = broadcast_dir / "offset.toml"
    config.write_text(
        (broadcast_dir / "config.toml").read_text(encoding="utf-8")
        + "\n[sensors.gnss]\ntime_offset_s = 0.3\nlearn_time_offset = false\n",
        encoding="utf-8",
    )
    out = tmp_path / "est.jsonl"
    argv = ["replay", str(broadcast_dir / "drive.log"), "--nmea", str(broadcast_dir / "drive.nmea")]
    assert main([*argv, "--config", str(config), "--out", str(out)]) == 0
    summary = capsys.readouterr().err
    made = int(re.search(r"(\d+) estimates;", summary).group(1))  # type: ignore[union-attr]
    times = [json.loads(line)["t"] for line in out.read_text(encoding="utf-8").splitlines()]
    assert len(times) >= 0.99 * made and all(b >= a for a, b in itertools.pairwise(times))


# --- command line and the real drive ---------------------------------------------------------------------------


def test_cli_profile_writes_a_replayable_drive(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "d"
    assert main(["simulate", "--out", str(out), "--profile", "realistic", "--seed", "4", "--duration", "30"]) == 0
    assert (out / "config.toml").is_file() and (out / "vehicle.dbc").is_file()
    assert load_settings(out / "scenario.toml") == profile_settings("realistic", 4, duration_s=30.0)
    assert (
        main(["simulate", "--out", str(tmp_path / "e"), "--settings", str(out / "scenario.toml"), "--profile", "kind"])
        == 1
    )
    assert "--profile" in capsys.readouterr().err


@pytest.mark.skipif(not REAL_DRIVE.is_dir(), reason=f"the real logger drive is not in {REAL_DRIVE}")
def test_study_real_measures_the_logger_drive(capsys: pytest.CaptureFixture[str]) -> None:
    logs = sorted(str(p) for p in REAL_DRIVE.glob("*.MF4"))
    pytest.importorskip("asammdf", reason="reading MF4 needs asammdf")
    argv = ["simulate", "--study-real", *logs[:2], "--gps-dbc", str(REAL_DRIVE / "canmod-gps.dbc")]
    assert main(argv) == 0
    rows = {line[:42].strip(): line[42:].split() for line in capsys.readouterr().out.splitlines()[2:]}
    assert rows["GNSS fix period p50"][0] == "1.000"
    assert rows["OBD speed quantum"][0] == "1"
    assert rows["OBD speed period p1/p50/p99"][2] == "0.500"
    assert rows["yaw rate (AngularRateX) quantum"][0] == "0.25"
    assert 1.0 < float(rows["OBD speed / GNSS speed"][0]) < 1.02


def test_obd_frames_are_single_frames_as_a_logger_sees_them(obd_dir: Path) -> None:
    frames = [m for m in read_log(obd_dir / "drive.log") if m.arbitration_id in (OBD_REQUEST_ID, OBD_REPLY_ID)]
    assert all(isinstance(m, can.Message) and len(m.data) == 8 and not m.is_extended_id for m in frames)
    replies = [bytes(m.data) for m in frames if m.arbitration_id == OBD_REPLY_ID]
    assert all(d[1] == 0x41 and d[0] in (3, 4) for d in replies)
    pads = {d[1 + d[0] :] for d in replies}
    assert len({p[:1] for p in pads}) == 1
