"""Evaluation without a reference: outages cut into a recorded drive, errors against the removed fixes, the share
of epochs solved on widened bounds; and ``sumhe replay LOG... --outage`` end to end."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from sumhe.baseline.ekf import Ekf
from sumhe.bench.outages import FixCut, mode_shares, outage_errors, outage_windows
from sumhe.cli import main
from sumhe.estimator.registry import ESTIMATORS
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, GnssFix

from loggerframes import LOGGER_CONFIG, SPEED_KMH, T0, write_drive

FRAME = LocalFrame(56.1, 10.2, 0.0)


def fix(t: float, east: float = 0.0, north: float = 0.0, valid: bool = True) -> GnssFix:
    lat, lon, _ = FRAME.to_geodetic(east, north, 0.0)
    return GnssFix(t, None, float(lat) if valid else None, float(lon) if valid else None, None, int(valid), valid)


def test_outage_windows_are_absolute_sorted_and_checked():
    assert outage_windows([(60.0, 10.0), (10.0, 5.0)], 1000.0) == [(1010.0, 1015.0), (1060.0, 1070.0)]
    for bad, what in [((-1.0, 5.0), "start"), ((1.0, 0.0), "length"), ((1.0, math.nan), "length")]:
        with pytest.raises(ValueError, match=what):
            outage_windows([bad], 0.0)
    with pytest.raises(ValueError, match="overlaps"):
        outage_windows([(10.0, 5.0), (12.0, 5.0)], 0.0)


def test_fix_cut_removes_fixes_inside_the_windows_only():
    cut = FixCut([(10.0, 20.0)])
    samples = [fix(9.99), fix(10.0), CanSample(15.0, "speed", 1.0), fix(15.0, valid=False), fix(19.99), fix(20.0)]
    kept = [s for s in samples if cut.keep(s)]
    assert [s.t for s in kept] == [9.99, 15.0, 20.0]
    assert [f.t for f in cut.removed] == [10.0, 15.0, 19.99]
    assert all(FixCut([]).keep(s) for s in samples)


def test_errors_against_removed_fixes_interpolate_the_estimates():
    """Estimates every 0.5 s along north at 10 m/s, 3 m east of the truth; removed fixes on the truth."""
    t = np.arange(0.0, 40.0, 0.5)
    lat, lon = FRAME.to_geodetic(np.full_like(t, 3.0), 10.0 * t, 0.0)[:, :2].T
    windows = [(10.0, 15.0), (20.0, 25.0), (50.0, 55.0)]
    removed = [fix(tf, north=10.0 * tf) for tf in (10.25, 12.0, 14.75, 21.1, 22.0)] + [fix(23.0, valid=False)]
    removed.append(fix(52.0, north=520.0))  # beyond the estimates: not scored
    per_window, overall = outage_errors(windows, removed, t, lat, lon)
    assert [(w.fixes, w.scored) for w in per_window] == [(3, 3), (2, 2), (1, 0)]
    assert per_window[0].mean_m == pytest.approx(3.0, abs=1e-3) and per_window[0].max_m == pytest.approx(3.0, abs=1e-3)
    assert math.isnan(per_window[2].mean_m)
    assert (overall.fixes, overall.scored, overall.start, overall.end) == (6, 5, 10.0, 55.0)
    assert overall.p95_m == pytest.approx(3.0, abs=1e-3)


def test_errors_are_taken_at_the_fixes_time_on_the_estimates_clock():
    """Fixes stamped 0.5 s after the instant they refer to; the estimator learned that (offset -0.5 s): compared
    at the stamp the estimates are 5 m ahead along the track, at the stamp less 0.5 s on the truth but for 3 m east.
    The windows move with the fixes: a fix stamped just inside one is still counted in it."""
    t = np.arange(0.0, 40.0, 0.5)
    lat, lon = FRAME.to_geodetic(np.full_like(t, 3.0), 10.0 * t, 0.0)[:, :2].T
    removed = [fix(tf + 0.5, north=10.0 * tf) for tf in (10.0, 12.0, 14.0)]
    (on_stamp,), _ = outage_errors([(10.5, 15.0)], removed, t, lat, lon)
    (w,), overall = outage_errors([(10.5, 15.0)], removed, t, lat, lon, offset_s=-0.5)
    assert on_stamp.mean_m == pytest.approx(math.hypot(3.0, 5.0), abs=1e-3)
    assert (w.fixes, w.scored, w.start, w.end) == (3, 3, 10.5, 15.0)
    assert w.max_m == pytest.approx(3.0, abs=1e-3) and overall.mean_m == pytest.approx(3.0, abs=1e-3)


def test_errors_where_estimates_are_too_far_apart_are_not_scored():
    t = np.array([0.0, 5.0])
    lat, lon = FRAME.to_geodetic(np.zeros(2), np.zeros(2), 0.0)[:, :2].T
    (w,), overall = outage_errors([(1.0, 4.0)], [fix(2.0)], t, lat, lon)
    assert (w.fixes, w.scored) == (1, 0) and overall.scored == 0
    _, none = outage_errors([(1.0, 4.0)], [], [], [], [])
    assert (none.fixes, none.scored) == (0, 0) and math.isnan(none.max_m)


def test_mode_shares_count_epochs_widened_and_failed():
    shares = mode_shares(["init", "mhe", "can", "can", "mhe-widened", "mhe-widened", "predict", "mhe"])
    assert (shares.epochs, shares.widened, shares.failed) == (6, 2, 1)
    assert shares.widened_share == pytest.approx(2 / 6) and shares.failed_share == pytest.approx(1 / 6)
    assert shares.modes["can"] == 2 and math.isnan(mode_shares([]).widened_share)


# --- sumhe replay LOG ... --outage ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def logger_drive(tmp_path_factory):
    d = tmp_path_factory.mktemp("logger")
    logs = write_drive(d / "logs", 60.0, files=3)
    config = d / "logger.toml"
    config.write_text(LOGGER_CONFIG)
    return logs, config


def replay(capsys, logs, config, *args):
    code = main(["replay", *map(str, logs), "--config", str(config), *args])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    return [json.loads(line) for line in captured.out.splitlines()], captured.err


def unsolved(estimates: list[dict]) -> list[dict]:
    """The JSON estimates without their solve times (which vary from run to run)."""
    return [{k: v for k, v in e.items() if k != "solve_ms"} for e in estimates]


def test_replay_of_several_files_equals_the_same_drive_in_one(tmp_path, capsys, logger_drive):
    logs, config = logger_drive
    whole = write_drive(tmp_path / "one", 60.0, files=1)
    split, _ = replay(capsys, logs[::-1], config, "--estimator", "ekf")
    one, err = replay(capsys, whole, config, "--estimator", "ekf")
    assert len(one) > 100
    assert unsolved(split) == unsolved(one)
    assert "CAN: 1 files" in err and "GNSS from CAN: 60 fixes (58 valid)" in err


def test_replay_with_outages_reports_errors_against_the_removed_fixes(capsys, logger_drive):
    logs, config = logger_drive
    estimates, err = replay(capsys, logs, config, "--estimator", "ekf", "--outage", "40+10", "20+10")
    assert "ekf: 40 fixes (38 valid)" in err  # 20 of the 60 epochs removed
    outage = [e for e in estimates if T0 + 22.0 < e["t"] < T0 + 30.0]  # after the first missed epoch
    assert outage and all(e["gps"] == "outage" for e in outage)
    lines = dict(re.findall(r"^  (\S+): (.*)$", err, re.M))
    assert set(lines) == {"20+10", "40+10", "all"}
    assert lines["20+10"].startswith("10 of 10 fixes") and lines["all"].startswith("20 of 20 fixes")
    max_m = [float(m) for m in re.findall(r"max (\S+)", err)]
    assert max(max_m) < 3.0  # exact sensors on a circle: dead reckoning through 10 s stays close
    assert re.search(r"of \d+ epoch estimates 0\.0 % on widened bounds, 0\.0 % solver failures", err)
    assert "estimator: estimator ekf" in err


class OffsetEkf(Ekf):
    """The EKF, saying it learned a GNSS time offset of 0.5 s (the fixes' instant half a second after their stamp)."""

    def stats(self):
        return {**super().stats(), "gps_time_offset_s": 0.5}


def test_replay_compares_the_removed_fixes_at_the_estimators_learned_time_offset(capsys, logger_drive, monkeypatch):
    """``sumhe replay --outage`` scores as ``sumhe bench --drive`` does: the same estimates, each removed fix taken
    at its stamp plus the offset the estimator learned (half a second at the drive's speed: metres)."""
    monkeypatch.setitem(ESTIMATORS, "offset-ekf", (__name__, "OffsetEkf"))
    logs, config = logger_drive
    plain, err_plain = replay(capsys, logs, config, "--estimator", "ekf", "--outage", "20+10")
    moved, err_moved = replay(capsys, logs, config, "--estimator", "offset-ekf", "--outage", "20+10")
    assert unsolved(plain) == unsolved(moved)
    mean = [float(re.search(r"^  all: 10 of 10 fixes; mean (\S+),", e, re.M).group(1)) for e in (err_plain, err_moved)]
    speed = SPEED_KMH / 3.6
    assert mean[0] < 1.0 and mean[1] == pytest.approx(0.5 * speed, abs=1.0)


def test_replay_with_a_bad_outage_is_an_error(capsys, logger_drive):
    logs, config = logger_drive
    assert main(["replay", *map(str, logs), "--config", str(config), "--outage", "10+5", "12+5"]) == 1
    assert "error: --outage: outage 12+5 overlaps the one before it" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["replay", *map(str, logs), "--config", str(config), "--outage", "10"])


def test_replay_of_a_missing_or_unreadable_log_is_an_error(tmp_path, capsys, logger_drive):
    logs, config = logger_drive
    assert main(["replay", str(logs[0]), str(tmp_path / "gone.mf4"), "--config", str(config)]) == 1
    assert "gone.mf4: CAN log not found" in capsys.readouterr().err
    text = tmp_path / "notes.mf4"
    text.write_text("not an MDF file\n")
    assert main(["replay", str(text), "--config", str(config)]) == 1
    assert "notes.mf4: cannot read CAN log" in capsys.readouterr().err
