"""``sumhe calibrate``: a simulated drive with known installation parameters recovered within issue 12's targets,
sign checks with a flipped mapping, parameters a drive cannot determine (null with a reason), bad input, the JSON
keys, and a TOML snippet the config accepts."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import tomllib

from sumhe.bench.calibrate import (
    TARGETS,
    CalibrateBenchSettings,
    DriveResult,
    comparable_truth,
    error,
    online_rounding,
    report,
)
from sumhe.calibration import (
    KEYS,
    DriveSignals,
    calibrate,
    combined_bias,
    jackknife_std,
    read_signals,
    speed_scale_fit,
    time_offset_key,
    toml_snippet,
)
from sumhe.cli import main
from sumhe.config import load_config
from sumhe.sim import simulate_profile, write_drive

KNOWN = {
    "scenario": "urban",
    "duration_s": 600.0,
    "gps_rate_hz": 1.0,
    "speed_source": "obd",
    "obd_rate_hz": 2.0,
    "obd_rounding": "floor",
    "obd_delay_s": 0.1,
    "can_sensor_delay_s": 0.03,
    "gps_time_offset_s": 0.2,
    "speed_scale": 1.02,
    "yaw_rate_bias_dps": 0.4,
    "yaw_rate_scale": 1.08,
    "imu_sign": -1,
}
"""A drive like the real logger's (OBD-II speed in truncated whole km/h, 1 Hz GNSS, an upside-down IMU) with
every other error of the realistic profile drawn."""


@pytest.fixture(scope="module")
def known(tmp_path_factory):
    drive = simulate_profile("realistic", 1, **KNOWN)
    directory = tmp_path_factory.mktemp("known")
    write_drive(drive, directory)
    return drive, directory


@pytest.fixture(scope="module")
def known_signals(known):
    _, d = known
    return read_signals(load_config(d / "config.toml", env={}), d / "drive.log", d / "drive.nmea")


def run_cli(capsys, *argv):
    rc = main(["calibrate", *map(str, argv)])
    out, err = capsys.readouterr()
    return rc, out, err


def drive_args(d: Path, config: Path | None = None) -> list[str]:
    return [d / "drive.log", "--nmea", d / "drive.nmea", "--config", config or d / "config.toml"]


def test_a_simulated_drive_gives_its_parameters_within_the_targets(known, capsys):
    drive, d = known
    rc, out, err = run_cli(capsys, *drive_args(d), "--json")
    assert rc == 0, err
    result = json.loads(out)
    assert list(result) == [name for key in KEYS for name in (key, f"{key}_std")]
    truth = comparable_truth(drive.settings, drive.calibration, 0.0)
    assert truth["gps_time_offset_s"] == pytest.approx(0.3)  # the fix's 0.2 s and the OBD reply's age
    for key, (tolerance, _) in TARGETS.items():
        assert result[key] is not None, key
        assert abs(error(key, result[key], truth[key])) <= tolerance, (key, result[key], truth[key])
        assert 0.0 < result[f"{key}_std"] < tolerance, key
    assert result["can_delay_s"] == pytest.approx(truth["can_delay_s"], abs=3 * result["can_delay_s_std"] + 0.02)
    assert "sign of the CAN speed: ok" in err and "sign of the CAN yaw rate: ok" in err


def test_the_time_offset_is_taken_against_the_speeds_configured_age(known_signals):
    """The drive's OBD-II speed is 0.07 s older than its yaw rate: with ``speed_delay_s`` configured so, the time
    offset is taken against a speed that much older (the fixes' own against the yaw rate), and the snippet says
    what it measured of that age beside the key as configured, without setting it."""
    plain, told = calibrate(known_signals), calibrate(known_signals, 0.0, 0.07)
    assert told.gps_time_offset_s.value == pytest.approx(plain.gps_time_offset_s.value - 0.07)
    assert told.can_delay_s == plain.can_delay_s
    snippet = toml_snippet(told, load_config(None, env={}))
    assert "speed_delay_s = 0.07 as configured" in snippet
    assert "speed_delay_s" not in tomllib.loads(snippet)["sensors"]["can"]


def test_the_benchmark_reports_the_rounding_written_and_said_against_the_simulated_one(known, known_signals):
    drive, d = known
    cal = calibrate(known_signals)
    online = online_rounding(load_config(d / "config.toml", env={}), d)
    assert online == "truncate"  # said 300 s into the drive
    truth = comparable_truth(drive.settings, drive.calibration, 0.0)
    results = [
        DriveResult("known", "obd speed", cal, truth, "truncate", online),
        DriveResult("wrong", "obd", cal, truth, "round", None),
    ]
    lines = report(results, CalibrateBenchSettings())
    assert "| truncate / truncate (truncate) |" in lines[4] and "| truncate / - (round) |" in lines[5]
    assert lines[-1].endswith(
        "on the 2 drives whose speed is OBD-II's whole km/h: right on 1, wrong on 1, not told (no key written) on 0; "
        "the on-line check (the config's 'round'): right on 1, wrong on 0, not told on 1"
    )


def test_the_output_is_a_config_that_loads_and_merges(known, capsys):
    _, d = known
    rc, out, _ = run_cli(capsys, *drive_args(d))
    assert rc == 0
    snippet = d / "calibration.toml"
    snippet.write_text(out)
    alone = load_config(snippet, env={})
    table = tomllib.loads(out)
    merged = load_config(d / "config.toml", env={}, overrides=_dotted(table))
    base = load_config(d / "config.toml", env={})
    for quantity in ("speed", "yaw_rate"):
        spec, before = merged.can.signals[quantity], base.can.signals[quantity]
        assert (spec.message, spec.signal) == (before.message, before.signal)
        assert alone.can.signals[quantity].scale == spec.scale
    assert merged.can.signals["speed"].scale == pytest.approx(0.98, abs=0.01)
    assert merged.sensors.can.speed_rounding == "truncate"  # whole km/h, truncated: taken at their middles
    assert merged.can.signals["yaw_rate"].scale == pytest.approx(-1 / 1.08, abs=0.02)  # the IMU's sign kept
    assert ("time_offset_s = 0.3" in out or "time_offset_s = 0.2" in out) and "delay_s" in out
    if time_offset_key():
        assert merged.sensors.gnss.time_offset_s == pytest.approx(0.3, abs=0.03)


def _dotted(table: dict, prefix: str = "") -> dict:
    """A TOML document as load_config's dotted overrides (signal specs stay tables)."""
    out = {}
    for key, value in table.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and not name.startswith("can.signals."):
            out |= _dotted(value, name + ".")
        else:
            out[name] = value
    return out


def test_a_flipped_mapping_is_reported_with_its_fix(known, tmp_path, capsys):
    _, d = known
    config = (d / "config.toml").read_text()
    yaw = 'yaw_rate = { signal = "IMU_RATES.RATE_Z", scale = -1.0 }'
    assert 'speed = "OBD2.VehicleSpeed"' in config and yaw in config
    flipped = config.replace(yaw, yaw.replace("-1.0", "1.0"))
    flipped = flipped.replace('speed = "OBD2.VehicleSpeed"', 'speed = { signal = "OBD2.VehicleSpeed", scale = -1.0 }')
    path = tmp_path / "flipped.toml"  # vehicle.dbc is found beside the logs
    path.write_text(flipped)
    rc, out, err = run_cli(capsys, *drive_args(d, path), "--json")
    assert rc == 0, err
    result = json.loads(out)
    assert result["speed_scale"] < 0 and result["yaw_rate_scale"] < 0
    assert "sign of the CAN speed: WRONG SIGN" in err and "scale = -1" in err
    assert "sign of the CAN yaw rate: WRONG SIGN" in err
    rc, out, err = run_cli(capsys, *drive_args(d, path))
    fixed = load_config(path, env={}, overrides=_dotted(tomllib.loads(out)))
    assert fixed.can.signals["speed"].scale > 0  # the snippet's mapping undoes the flip
    assert fixed.can.signals["yaw_rate"].scale < 0  # as the drive's own config: the IMU is upside down


def test_without_speed_over_ground_the_positions_give_the_speed(known, known_signals):
    drive, _ = known
    nan = np.full(len(known_signals.t_fix), math.nan)
    cal = calibrate(dataclasses.replace(known_signals, gnss_speed=nan, course=nan, heading=nan))
    truth = comparable_truth(drive.settings, drive.calibration, 0.0)
    assert "between fix positions" in cal.gps_time_offset_s.method
    assert "course between fix positions" in cal.yaw_rate_bias_dps.method
    for key in ("gps_time_offset_s", "speed_scale", "yaw_rate_bias_dps"):  # noisier, and says so
        p = cal.parameters()[key]
        assert abs(error(key, p.value, truth[key])) <= 3 * p.std, (key, p)
    assert cal.gps_time_offset_s.std < 0.1 and cal.speed_scale.std < 0.01


def synthetic(duration_s: float = 600.0, turns: bool = True, speed_changes: bool = True, lag_s: float = 0.3):
    """Signals of a drive at 1 Hz GNSS, 50 Hz CAN: the fixes ``lag_s`` behind the CAN data, CAN speed x 1.01,
    yaw rate 1.05 x true + 0.4 deg/s; with ``turns`` the car weaves, else it drives straight north."""
    rng = np.random.default_rng(3)
    t_can = np.arange(0.0, duration_s, 0.02)

    def speed(t):
        return 12.0 + (5.0 * np.sin(2 * math.pi * t / 60.0) if speed_changes else 0.0 * t)

    def yaw(t):
        return 0.15 * np.sin(2 * math.pi * t / 30.0) if turns else 0.0 * t

    fine = np.arange(-5.0, duration_s + 5.0, 0.01)
    azimuth = -np.cumsum(yaw(fine)) * 0.01
    east, north = np.cumsum(speed(fine) * np.sin(azimuth)) * 0.01, np.cumsum(speed(fine) * np.cos(azimuth)) * 0.01
    t_fix = np.arange(5.0, duration_s - 5.0, 1.0)
    true_t = t_fix - lag_s
    n = len(t_fix)
    return DriveSignals(
        t_fix=t_fix,
        east=np.interp(true_t, fine, east) + rng.normal(0, 0.3, n),
        north=np.interp(true_t, fine, north) + rng.normal(0, 0.3, n),
        gnss_speed=speed(true_t) + rng.normal(0, 0.05, n),
        course=np.mod(np.interp(true_t, fine, azimuth) + rng.normal(0, 0.005, n), 2 * math.pi),
        heading=np.full(n, math.nan),
        t_speed=t_can,
        speed=1.01 * speed(t_can) + rng.normal(0, 0.02, len(t_can)),
        t_yaw=t_can,
        yaw=1.05 * yaw(t_can) + math.radians(0.4) + rng.normal(0, 0.002, len(t_can)),
        speed_quantum_mps=0.01,
        fixes=n,
    )


def test_synthetic_drive_gives_its_parameters():
    cal = calibrate(synthetic())
    # the speed lag's error over 40 draws of this drive's noise: 8 ms root mean square (-0.318 s in this one)
    assert cal.gps_time_offset_s.value == pytest.approx(-0.3, abs=0.025)
    assert cal.speed_scale.value == pytest.approx(1 / 1.01, rel=0.001)
    assert cal.yaw_rate_bias_dps.value == pytest.approx(0.4, abs=0.02)
    assert cal.yaw_rate_scale.value == pytest.approx(1 / 1.05, rel=0.01)
    assert cal.can_delay_s.value == pytest.approx(0.0, abs=3 * cal.can_delay_s.std)
    assert [s.ok for s in cal.signs] == [True, True]


def test_a_drive_without_turns_has_no_yaw_rate_scale_but_a_bias():
    cal = calibrate(synthetic(turns=False))
    assert cal.yaw_rate_scale.value is None and cal.yaw_rate_scale.std is None
    assert "hardly turns" in cal.yaw_rate_scale.method
    assert cal.yaw_rate_bias_dps.value == pytest.approx(0.4, abs=0.02)  # at scale 1: CAN minus true
    assert "the scale at 1" in cal.yaw_rate_bias_dps.method
    assert cal.signs[1].ok is None
    assert cal.to_json()["yaw_rate_scale"] is None and cal.to_json()["yaw_rate_scale_std"] is None
    assert cal.speed_scale.value == pytest.approx(1 / 1.01, rel=0.001)


def test_a_constant_speed_gives_no_time_offset():
    cal = calibrate(synthetic(speed_changes=False, turns=False))
    assert cal.gps_time_offset_s.value is None
    assert "not determined" in cal.gps_time_offset_s.method
    assert cal.speed_scale.value == pytest.approx(1 / 1.01, rel=0.002)  # the ratio needs no timing
    assert cal.can_delay_s.value is None


def test_a_flipped_speed_and_yaw_rate_in_the_signals():
    sig = synthetic()
    cal = calibrate(dataclasses.replace(sig, speed=-sig.speed, yaw=-sig.yaw))
    assert cal.speed_scale.value == pytest.approx(-1 / 1.01, rel=0.001)
    assert cal.yaw_rate_scale.value == pytest.approx(-1 / 1.05, rel=0.01)
    assert [s.ok for s in cal.signs] == [False, False]
    assert all("scale = -1" in s.fix for s in cal.signs)


def test_the_snippet_without_a_mapping_loads(tmp_path):
    cal = calibrate(synthetic())
    path = tmp_path / "snippet.toml"
    path.write_text(toml_snippet(cal, load_config(None, env={})))
    config = load_config(path, env={})
    assert config.can.signals == {}  # the default config maps nothing: there is no scale to fold into


def test_speed_scale_fit_tells_rounded_from_truncated_steps():
    rng = np.random.default_rng(5)
    true = np.concatenate([np.full(200, 13.37), rng.uniform(3.0, 25.0, 800)])  # a cruise and the rest
    q = 1 / 3.6
    can = 1.02 * true + rng.normal(0, 0.02, len(true))
    gnss = true + rng.normal(0, 0.1, len(true))
    for rounding, offset in ((np.round, 0.0), (np.floor, q / 2)):
        k, found, std = speed_scale_fit(gnss, rounding(can / q) * q, q)
        assert found == offset
        assert k == pytest.approx(1 / 1.02, rel=max(3 * std, 0.001))
    k, found, _ = speed_scale_fit(gnss, np.round(can, 2), 0.01)  # a fine quantum: no offset tried
    assert found == 0.0 and k == pytest.approx(1 / 1.02, rel=0.001)


@pytest.mark.parametrize(
    ("seed", "rounding"),
    [(2, "round"), (20, None)],  # 20: fits best as truncated by a hair, which the drive does not tell apart
)
def test_a_rounded_obd_speed_is_never_written_truncated(tmp_path, seed, rounding):
    drive = simulate_profile("realistic", seed, scenario="urban", duration_s=600.0)
    assert (drive.settings.speed_source, drive.settings.obd_rounding) == ("obd", "round")
    write_drive(drive, tmp_path)
    config = load_config(tmp_path / "config.toml", env={})
    cal = calibrate(read_signals(config, tmp_path / "drive.log", tmp_path / "drive.nmea"))
    assert cal.speed_rounding == rounding
    truth = comparable_truth(drive.settings, drive.calibration, 0.0)["speed_scale"]
    assert cal.speed_factor == pytest.approx(truth, rel=0.004)  # the factor as rounded: what the mapping gets
    snippet = toml_snippet(cal, config)
    assert "truncate" not in snippet
    assert any("does not tell rounded from truncated" in n for n in cal.notes) == (rounding is None)


def test_the_bias_combines_the_moving_fit_and_the_standstill_by_their_variances():
    # a moving fit of 0.53 +- 0.046 and 44 s at standstill reading 0.463 +- 0.014 (deg/s; a realistic offroad drive
    # whose true bias is 0.466): the standstill carries most of the weight
    value, std = combined_bias((0.530, 0.046), (0.463, 0.014), 0.0)
    assert value == pytest.approx(0.4687, abs=1e-4) and std == pytest.approx(0.0134, abs=1e-4)
    # a sensor that read one quantum all along: its rounding bounds what the standstill can say
    value, std = combined_bias((0.530, 0.046), (0.463, 0.0), 0.244)
    assert std == pytest.approx((0.046**-2 + 12 / 0.244**2) ** -0.5) and 0.463 < value < 0.530
    # disagreeing (more than 3 combined standard errors) or an unusable fit: nothing combined
    assert combined_bias((0.70, 0.046), (0.463, 0.014), 0.0) is None
    assert combined_bias((0.530, math.inf), (0.463, 0.014), 0.0) is None


def test_jackknife_of_a_mean():
    rng = np.random.default_rng(2)
    x = rng.normal(5.0, 2.0, 5000)
    t = np.arange(len(x), dtype=float)
    std = jackknife_std(lambda keep: (float(np.mean(x[keep])),), t)
    assert std is not None and std[0] == pytest.approx(2.0 / math.sqrt(len(x)), rel=0.5)
    assert jackknife_std(lambda keep: None, t) is None


def test_missing_gnss_is_a_clear_error(known, tmp_path, capsys):
    _, d = known
    empty = tmp_path / "empty.nmea"
    empty.write_text("")
    rc, out, err = run_cli(capsys, d / "drive.log", "--nmea", empty, "--config", d / "config.toml")
    assert rc == 1 and out == "" and "no valid GNSS fix" in err


def test_missing_can_speed_is_a_clear_error(known, tmp_path, capsys):
    _, d = known
    lines = (d / "drive.log").read_text().splitlines()
    without = [line for line in lines if " 7E8#" not in line]  # the OBD-II replies carry the speed
    assert 0 < len(without) < len(lines)
    log = tmp_path / "drive.log"
    log.write_text("\n".join(without) + "\n")
    rc, out, err = run_cli(capsys, log, "--nmea", d / "drive.nmea", "--config", d / "config.toml")
    assert rc == 1 and out == "" and "no CAN speed" in err


@pytest.mark.parametrize("content", [None, "this is not a CAN log\n", b"\x00\x01\x02garbage"])
def test_unreadable_logs_are_a_clear_error(known, tmp_path, capsys, content):
    _, d = known
    log = tmp_path / "drive.log"
    if isinstance(content, str):
        log.write_text(content)
    elif isinstance(content, bytes):
        log.write_bytes(content)
    rc, out, err = run_cli(capsys, log, "--nmea", d / "drive.nmea", "--config", d / "config.toml")
    assert rc == 1 and out == "" and err.splitlines()[-1].startswith("error: ")
    assert "not found" in err if content is None else "0 CAN frames" in err


def test_headings_weigh_as_the_receiver_rates_them():
    """Two minutes of headings wandering by up to 8.6 deg (a GNSS + IMU module not settled yet), rated so: weighed
    by their ratings the yaw-rate scale is the drive's within 0.1 % (as from clean headings); weighed alike it is
    0.5 % off, its standard error ten times wider."""
    sig = synthetic()
    bad = (sig.t_fix > 100.0) & (sig.t_fix < 220.0)
    heading = np.mod(sig.course + 0.15 * np.sin(2 * math.pi * sig.t_fix / 50.0) * bad, 2 * math.pi)
    rated = calibrate(dataclasses.replace(sig, heading=heading, heading_sigma=np.where(bad, 0.15, 0.005)))
    alike = calibrate(dataclasses.replace(sig, heading=heading))
    assert "heading" in rated.yaw_rate_scale.method
    assert rated.yaw_rate_scale.value == pytest.approx(1 / 1.05, rel=0.001) and rated.yaw_rate_scale.std < 0.001
    assert abs(alike.yaw_rate_scale.value * 1.05 - 1.0) > 0.003 and alike.yaw_rate_scale.std > 0.005


REAL_DRIVE = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_drives" / "canedge_obd_2021-07-26_a"


@pytest.mark.skipif(not REAL_DRIVE.is_dir(), reason=f"the real CANedge drive is not in {REAL_DRIVE}")
def test_the_real_drives_heading_accuracy_narrows_its_yaw_rate_calibration():
    """The shared drive's module rates its headings (2-40 deg unsettled, about 0.5-1 deg after): with the rating
    mapped the yaw-rate scale's standard error is a fifth of what it is without, and the lag's too."""
    repo = Path(__file__).resolve().parents[1]
    logs = sorted(REAL_DRIVE.glob("*.MF4"))
    plain = load_config(repo / "configs" / "canedge-obd.toml", env={})
    rated_spec = '{ signal = "gnss_attitude.HeadingAccuracy", valid = "AttitudeValid", channel = 2 }'
    mapped = load_config(
        repo / "configs" / "canedge-obd.toml", env={"SUMHE_GPS__SIGNALS__HEADING_ACCURACY": rated_spec}
    )
    alike, rated = (calibrate(read_signals(c, logs)) for c in (plain, mapped))
    assert alike.speed_rounding == "truncate"  # the OBD-II speed in whole km/h reads 0.14 m/s low
    assert rated.yaw_rate_scale.std < 0.2 * alike.yaw_rate_scale.std
    assert rated.can_delay_s.std < 0.5 * alike.can_delay_s.std  # the yaw rate's lag, less the speed's
    assert rated.yaw_rate_scale.value == pytest.approx(1.0, abs=0.02)
