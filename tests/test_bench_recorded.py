"""``sumhe bench --drive``: outages placed on a recorded drive, the estimators against the fixes removed, the two
dead-reckoning floors, an estimator's learned GNSS time offset, the report."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sumhe.baseline.ekf import Ekf
from sumhe.bench.floors import CanTrack, Fixes, calibrated_floor, fit_before, plain_floor
from sumhe.bench.recorded import (
    FLOORS,
    RecordedBenchSettings,
    floor_errors,
    load_recording,
    place_outages,
    run_estimator,
)
from sumhe.cli import main
from sumhe.commands.candump import reference_config
from sumhe.estimator.registry import ESTIMATORS
from sumhe.sim import SimSettings, simulate, write_drive
from sumhe.sim.measure import true_antenna

from loggerframes import write_drive as write_logger_drive


class OffsetEkf(Ekf):
    """The EKF, saying it learned a GNSS time offset of 0.5 s."""

    def stats(self):
        return {**super().stats(), "gps_time_offset_s": 0.5}


@pytest.fixture(scope="module")
def drive_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("recorded")
    write_drive(simulate(SimSettings(scenario="highway", seed=4, duration_s=330.0)), d)
    return d


def weave(duration_s: float = 120.0, scale: float = 1.03, bias_rps: float = math.radians(0.5)):
    """A car weaving at 15 m/s (truth at 100 Hz), its CAN reading ``scale`` x the speed and the yaw rate plus
    ``bias_rps``, and exact fixes at 1 Hz with their courses."""
    t = np.arange(0.0, duration_s, 0.01)
    speed = 15.0 + 2.0 * np.sin(2 * math.pi * t / 40.0)
    yaw = 0.1 * np.sin(2 * math.pi * t / 25.0)
    truth = CanTrack(t, speed, yaw)
    east, north, azimuth = truth.reckon(0.0, 0.0, 0.0, 0.3, t)
    track = CanTrack(t, scale * speed, yaw + bias_rps)
    k = np.arange(0, len(t), 100)
    fixes = Fixes(t[k], east[k], north[k], azimuth[k], np.full(len(k), math.nan))
    return track, fixes


def test_the_calibrated_floor_fits_scale_bias_and_heading_and_beats_the_plain_one():
    track, fixes = weave()
    fit = fit_before(track, fixes, 90.0)
    assert fit is not None and fit.fixes == 30
    assert fit.speed_scale == pytest.approx(1 / 1.03, rel=1e-3)
    assert fit.bias_rps == pytest.approx(math.radians(0.5), abs=math.radians(0.02))
    assert fit.rms_m < 0.05
    inside = (fixes.t >= 90.0) & (fixes.t < 120.0)
    ref = np.column_stack([fixes.east[inside], fixes.north[inside]])
    plain = np.hypot(*(plain_floor(track, fixes, 90.0, fixes.t[inside]) - ref).T)
    calibrated = np.hypot(*(calibrated_floor(track, fixes, 90.0, fixes.t[inside]) - ref).T)
    assert calibrated.max() < 0.5 < 5.0 < plain.max()  # 3 % of speed and 0.5 deg/s over 30 s
    assert fit_before(track, fixes, 3.0) is None  # no 5 fixes before: no fit, NaN positions
    assert np.isnan(calibrated_floor(track, fixes, 3.0, fixes.t[5:8])).all()


def test_without_a_course_the_floor_takes_the_direction_between_fixes():
    _, fixes = weave(scale=1.0, bias_rps=0.0)
    bare = Fixes(fixes.t, fixes.east, fixes.north, np.full(len(fixes.t), math.nan), fixes.heading)
    assert bare.azimuth_at(50) == pytest.approx(fixes.course[50], abs=0.06)  # the chord of the last second
    assert math.isnan(bare.azimuth_at(0))


def test_outages_are_placed_while_moving_and_reproducibly(drive_dir):
    rec = load_recording([str(drive_dir)], None, reference_config)
    bs = RecordedBenchSettings()
    windows = place_outages(rec, 10.0, bs)
    assert windows == place_outages(rec, 10.0, bs)
    assert [round(a - rec.t0) for a, _ in windows][:1] == [150] and len(windows) == 2
    for a, b in windows:
        assert b - a == 10.0
        inside = (rec.track.t >= a) & (rec.track.t < b)
        assert rec.track.speed[inside].mean() >= bs.min_speed_mps


def test_the_environments_overrides_reach_the_config_given_not_the_defaults(tmp_path, monkeypatch, capsys):
    """``SUMHE_...`` overrides are meant for the config in use: ``gps.signals`` set for a CAN-GNSS config had stopped
    ``sumhe bench --drive ... --config FILE`` at the defaults it never used (``<defaults>: gps.signals: read only
    with gps.source = 'can'``)."""
    logs = write_logger_drive(tmp_path, 40.0)
    rated = '{ signal = "GNSS_MOTION.HEADING_ACC", valid = "HEADING_VALID", channel = 2 }'
    monkeypatch.setenv("SUMHE_GPS__SIGNALS__HEADING_ACCURACY", rated)
    args = ["--config", str(tmp_path / "logger.toml"), "--estimators", "dead-reckoning", "--lengths", "10"]
    assert main(["bench", "--drive", *map(str, logs), *args]) == 0
    assert "| `dead-reckoning` |" in capsys.readouterr().out


def test_an_estimators_learned_time_offset_moves_the_fixes_it_is_compared_with(drive_dir, monkeypatch):
    monkeypatch.setitem(ESTIMATORS, "offset-ekf", (__name__, "OffsetEkf"))
    rec = load_recording([str(drive_dir)], None, reference_config)
    windows = place_outages(rec, 10.0, RecordedBenchSettings())
    plain, shifted = run_estimator("ekf", rec, windows), run_estimator("offset-ekf", rec, windows)
    assert abs(plain.offset_s) < 0.05 and shifted.offset_s == 0.5  # the simulated fixes are on time
    assert plain.fix_errors.scored > 0 and plain.fix_errors.mean_m < 3.0
    assert shifted.fix_errors.mean_m > plain.fix_errors.mean_m + 5.0  # half a second at highway speed
    np.testing.assert_array_equal(plain.truth_errors, shifted.truth_errors)  # the same estimates


def test_the_command_reports_every_estimator_and_both_floors(drive_dir, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["bench", "--drive", str(drive_dir), "--estimators", "ekf,dead-reckoning", "--lengths", "10,30"]
    assert main([*argv, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    (data,) = json.loads((out / "recorded.json").read_text())
    assert data["drive"] == drive_dir.name and [r["length_s"] for r in data["lengths"]] == [10.0, 30.0]
    for length in data["lengths"]:
        assert list(length["rows"]) == ["ekf", "dead-reckoning", *FLOORS]
        for name, row in length["rows"].items():
            f = row["fixes"]
            assert f["n"] > 0 and 0.0 <= f["mean_m"] <= f["p95_m"] <= f["max_m"], name
            # each outage's errors: the same fixes, the pooled mean their weighed mean, the pooled max their max
            each = row["outages"]
            assert [o["start_s"] for o in each] == length["outages"], name
            assert sum(o["n"] for o in each) == f["n"], name
            scored = [o for o in each if o["n"]]
            weighed = sum(o["n"] * o["mean_m"] for o in scored) / f["n"]
            assert weighed == pytest.approx(f["mean_m"]) and max(o["max_m"] for o in scored) == f["max_m"], name
        ekf = length["rows"]["ekf"]
        assert ekf["truth"]["n"] > 0 and ekf["truth"]["mean_m"] < 10.0
        assert ekf["widened_share"] == 0.0 and ekf["x_real_time"] > 1.0
        for name in FLOORS:  # a simulated drive: the floors against the true antenna too
            assert length["rows"][name]["truth"]["n"] == length["rows"][name]["fixes"]["n"]
        # the error estimates against the removed fixes: every scored fix has an eph; the EKF has no bound box
        c = ekf["calibration"]
        assert c["n"] == ekf["fixes"]["n"] and 0.0 <= c["eph_coverage"] <= 1.0 and c["median_eph_m"] > 0.0
        assert c["box_n"] == 0 and c["box_coverage"] is None
        # its interval resamples the outages (a group each), and holds the share itself
        assert 1 < c["groups"] <= len(length["outages"])
        assert c["eph_coverage_low"] <= c["eph_coverage"] <= c["eph_coverage_high"]
    assert "| floor: calibrated dead reckoning |" in printed and "vs truth" in printed
    assert "| removed fix within eph [90 % interval over outages] |" in printed and "| `ekf` |" in printed
    assert printed.count("| outage start (s) | `ekf` | `dead-reckoning` | floor: dead reckoning |") == 2
    assert (out / "recorded.md").read_text().startswith(f"## {drive_dir.name}")


def test_the_floors_are_scored_against_where_the_antenna_truly_was(tmp_path):
    # near-exact fixes of an antenna 1.5 m ahead, tagged 0.2 s early on the CAN clock: they lie on the true antenna,
    # metres from the reference point at their tags
    settings = SimSettings(
        scenario="highway",
        seed=4,
        duration_s=200.0,
        antenna_forward_m=1.5,
        gps_time_offset_s=0.2,
        gps_error="uniform",
        gps_error_m=0.02,
    )
    write_drive(simulate(settings), tmp_path)
    rec = load_recording([str(tmp_path)], None, reference_config)
    assert rec.sim is not None and rec.sim.antenna_forward_m == 1.5
    fixes = np.column_stack([rec.fixes.east, rec.fixes.north])
    at = rec.truth.at(rec.fixes.t)
    assert np.median(np.hypot(*(fixes - true_antenna(rec.truth, rec.fixes.t, rec.sim)).T)) < 0.1
    assert np.median(np.hypot(*(fixes - np.column_stack([at.east, at.north])).T)) > 1.5
    windows = place_outages(rec, 10.0, RecordedBenchSettings(first_s=60.0))
    vs_fixes, vs_truth = floor_errors(rec, windows)
    for name in FLOORS:
        assert len(vs_fixes[name]) == len(vs_truth[name]) == len(windows)  # one array per outage
        truth, fixes = np.concatenate(vs_truth[name]), np.concatenate(vs_fixes[name])
        assert truth.size == fixes.size > 0
        assert abs(truth.mean() - fixes.mean()) < 0.1, name


def test_without_the_simulators_settings_the_floors_have_no_truth(drive_dir):
    rec = load_recording([str(drive_dir / "drive.log"), str(drive_dir / "drive.nmea")], None, reference_config)
    assert rec.truth is None and rec.sim is None
    vs_fixes, vs_truth = floor_errors(rec, place_outages(rec, 10.0, RecordedBenchSettings()))
    assert vs_truth == {} and all(np.concatenate(vs_fixes[name]).size for name in FLOORS)
