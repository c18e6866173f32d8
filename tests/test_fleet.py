"""Fleet reprocessing: drives and manifests, the worker (estimators reused across drives give the numbers of a fresh
``sumhe replay``), failures and re-runs, the summary table, and ``sumhe fleet`` on a local Ray of 2 workers."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import re
import subprocess
import sys

import pytest

from sumhe.bench.fleet import (
    FleetWorker,
    Task,
    find_drives,
    finished,
    format_table,
    make_tasks,
    run_local,
    table_row,
)
from sumhe.cli import main
from sumhe.config import load_config
from sumhe.errors import ConfigError
from sumhe.sim import profile_settings, simulate, write_drive

DURATION_S = 30.0


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """Three short simulated drives: two kind (NMEA + reference CAN), one realistic (its own DBC and config.toml)."""
    root = tmp_path_factory.mktemp("drives")
    out = []
    for name, profile, seed in (("kind1", "kind", 1), ("kind2", "kind", 2), ("real3", "realistic", 3)):
        settings = profile_settings(profile, seed, duration_s=DURATION_S, outages=((12.0, 6.0),))
        write_drive(simulate(settings), root / name)
        out.append(root / name)
    return out


def fleet(*args):
    """``sumhe fleet ...`` in a process of its own."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "sumhe", "fleet", *args], capture_output=True, text=True, env=env, timeout=600
    )


def replay_numbers(capsys, drive, estimator, *args):
    """``sumhe replay`` of a drive folder: its estimates (without solve times) and summary."""
    config = ["--config", str(drive / "config.toml")] if (drive / "config.toml").exists() else []
    argv = ["replay", str(drive / "drive.log"), "--nmea", str(drive / "drive.nmea"), *config]
    assert main([*argv, "--estimator", estimator, *args]) == 0
    captured = capsys.readouterr()
    return [_no_timing(json.loads(line)) for line in captured.out.splitlines()], captured.err


def _no_timing(estimate):
    return {k: v for k, v in estimate.items() if k != "solve_ms"}


TOLERANCE = {"lat": 2e-9, "lon": 2e-9}
"""lat/lon in degrees; every other number to 2e-3 in its unit: the JSON's last digit. A reused estimator is reset,
not rebuilt; a state the reset forgets (a datum, a bias, a learned offset) moves results far more."""


def assert_same_estimates(ours, theirs):
    assert len(ours) == len(theirs) > 10
    for a, b in zip(ours, theirs, strict=True):
        assert a.keys() == b.keys()
        for key, value in a.items():
            if isinstance(value, float) and isinstance(b[key], float):
                assert value == pytest.approx(b[key], rel=0, abs=TOLERANCE.get(key, 2e-3)), (key, a, b)
            else:
                assert value == b[key], (key, a, b)


def test_drive_folders_and_manifests(tmp_path, drives):
    manifest = tmp_path / "fleet.txt"
    files = " ".join(str(drives[1] / f) for f in ("drive.log", "drive.nmea", "truth.csv"))
    manifest.write_text(f"# two drives\n{drives[0]}\n\n{files}  # by its files\n{drives[0]}\n")
    specs = find_drives([drives[2], manifest])
    assert [s.name for s in specs] == ["real3", "kind1", "kind2", "kind1-2"]
    real, kind1, kind2, _ = specs
    assert real.config == str(drives[2] / "config.toml") and real.truth == str(drives[2] / "truth.csv")
    assert real.can_logs == (str(drives[2] / "drive.log"),) and real.nmea_logs == (str(drives[2] / "drive.nmea"),)
    assert kind1.config is None and kind2.config is None and kind2.truth is not None
    manifest.write_text(f"{tmp_path / 'gone'}\n")
    with pytest.raises(ConfigError, match=r"fleet.txt:1: not found: .*gone"):
        find_drives([manifest])
    with pytest.raises(ConfigError, match="no such drive folder or manifest"):
        find_drives([tmp_path / "nothing"])


def test_a_drive_config_is_merged_over_the_fleet_config(tmp_path, drives):
    fleet = tmp_path / "fleet.toml"
    fleet.write_text("[gps]\nlatency_s = 0.25\n\n[can]\ndbc_strict = false\n")
    config = load_config(fleet, layers=[drives[2] / "config.toml"])
    assert config.gps.latency_s == 0.25 and config.can.dbc_strict is False  # kept from the fleet's
    assert config.can.dbc == "vehicle.dbc" and config.can.signals  # the drive's own
    assert config.source == f"{fleet} + {drives[2] / 'config.toml'}"


@pytest.mark.parametrize("estimator", ["ekf", "mhe"])
def test_a_reused_estimator_gives_the_numbers_of_sumhe_replay(tmp_path, capsys, drives, estimator):
    tasks = make_tasks(find_drives(drives), [estimator], None, [(12.0, 6.0)], tmp_path)
    worker = FleetWorker()
    records = {t.drive.name: worker.run(t) for t in tasks}
    assert worker.built == 2  # the kind drives share one estimator; the realistic one has a config of its own
    for drive in drives:
        task = next(t for t in tasks if t.drive.name == drive.name)
        record = records[drive.name]
        assert record["status"] == "ok", record["reason"]
        estimates, err = replay_numbers(capsys, drive, estimator, "--outage", "12+6")
        written = [_no_timing(json.loads(line)) for line in task.estimates_path.read_text().splitlines()]
        assert_same_estimates(written, estimates)
        assert f"replay: {estimator}: {record['fixes']} fixes ({record['valid_fixes']} valid)" in err
        assert f"{record['estimates']} estimates" in err
        scored, fixes, mean = re.search(r"  all: (\d+) of (\d+) fixes; mean (\S+),", err).groups()
        outages = record["outages_all"]
        assert (int(scored), int(fixes)) == (outages["scored"], outages["fixes"])
        assert float(mean) == pytest.approx(outages["mean_m"], abs=0.011)
        assert record["truth"]["scored"] > 0 and record["truth"]["mean_m"] < 20.0
        assert record["distance_m"] > 100.0 and record["span_s"] == pytest.approx(DURATION_S, abs=0.5)


def test_a_failing_drive_is_reported_and_finished_drives_are_skipped(tmp_path, drives):
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "drive.log").write_text("(1.0) can0 123#00\n")
    (broken / "config.toml").write_text("[gps]\nsource = 'can'\n")
    empty = tmp_path / "empty"
    empty.mkdir()
    tasks = make_tasks(find_drives([drives[0], broken, empty]), ["dead-reckoning"], None, [], tmp_path / "out")
    records = {r["drive"]: r for r in run_local(tasks)}
    assert records["kind1"]["status"] == "ok"
    assert records["broken"]["status"] == "failed" and "gps.signals" in records["broken"]["reason"]
    assert records["empty"]["status"] == "failed" and "no CAN or NMEA logs" in records["empty"]["reason"]
    assert [finished(t) for t in tasks] == [t.drive.name == "kind1" for t in tasks]
    rows = [table_row(r) for r in records.values()]
    text = format_table(rows)
    assert text.splitlines()[0].startswith("drive") and "no CAN or NMEA logs" in text


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray is not installed (pip install 'sumhe[fleet]')")
def test_sumhe_fleet_on_a_local_ray_of_two_workers(tmp_path, capsys, drives):
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "drive.log").write_text("not a candump line\n")
    out = tmp_path / "out"
    options = ["--out", str(out), "--workers", "2", "--estimators", "ekf,dead-reckoning", "--outages", "12+6"]
    first = fleet(*map(str, drives), str(broken), *options)  # its own process: Ray's threads and sockets stay there
    assert first.returncode == 1, first.stderr  # the broken drive fails; the fleet goes on
    assert "6 of 8 tasks ok on 2 workers" in first.stderr
    with (out / "summary.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8
    ok = [r for r in rows if r["status"] == "ok"]
    assert {(r["drive"], r["estimator"]) for r in ok} == {
        (d.name, e) for d in drives for e in ("ekf", "dead-reckoning")
    }
    assert all(float(r["duration_s"]) == pytest.approx(DURATION_S, abs=0.5) and r["outages"] == "1" for r in ok)
    assert all(float(r["truth_mean_m"]) < 50.0 and float(r["speed_x"]) > 0 for r in ok)
    failed = [r for r in rows if r["status"] == "failed"]
    assert [r["drive"] for r in failed] == ["broken", "broken"] and all(r["reason"] for r in failed)
    kind1 = Task(find_drives([drives[0]])[0], "ekf", None, ((12.0, 6.0),), str(out))
    estimates, _ = replay_numbers(capsys, drives[0], "ekf", "--outage", "12+6")
    assert_same_estimates(
        [_no_timing(json.loads(line)) for line in kind1.estimates_path.read_text().splitlines()], estimates
    )
    again = fleet(*map(str, drives), *options)  # all finished: nothing runs, no Ray started
    assert again.returncode == 0, again.stderr
    assert "6 finished before, 0 to run" in again.stderr and "Ray" not in again.stderr
    assert again.stdout.splitlines()[0].startswith("drive") and len(again.stdout.splitlines()) == 7
