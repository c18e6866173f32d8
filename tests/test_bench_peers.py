"""``sumhe bench`` (peers): outage placement, isolation of runs, failures recorded, the profiles, the CLI."""

import dataclasses
import itertools
import json
import math
import os
import time

import numpy as np
import pytest

from sumhe.bench import drives, report
from sumhe.bench.drives import Outage, PeersSettings, outage_plan
from sumhe.bench.peers import BenchRunError, call_isolated, run_bench
from sumhe.bench.report import summarise
from sumhe.cli import main
from sumhe.commands.candump import reference_config
from sumhe.estimator.registry import ESTIMATORS, estimator_names
from sumhe.frontend.fixes import LocalFix
from sumhe.messages import CanSample, GnssFix
from sumhe.sim import SimSettings, profile_settings, simulate

SHORT = PeersSettings(
    scenarios=("urban",),
    profiles=("kind",),
    gps_errors=("gaussian",),
    seeds=(3,),
    duration_s=60.0,
    outage_lengths_s=(5.0, 10.0),
    recover_s=5.0,
    warm_up_s=10.0,
    timeout_s=120.0,
)


class BrokenEstimator:
    """An estimator that raises at the first valid fix (the bench must record it and go on)."""

    name = "broken"

    @classmethod
    def from_config(cls, config):
        return cls()

    def reset(self):
        pass

    def push(self, sample):
        if isinstance(sample, LocalFix) and sample.valid:
            raise RuntimeError("broken on purpose")
        return []

    def stats(self):
        return {}


def finite_numbers(node):
    """Every number in a JSON tree (None counts as not finite)."""
    if isinstance(node, dict):
        return all(finite_numbers(v) for v in node.values())
    if isinstance(node, list):
        return all(finite_numbers(v) for v in node)
    if node is None:
        return False
    if isinstance(node, float):
        return math.isfinite(node)
    return True


# ---- placing outages ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_outage_plan_places_every_length_once_after_the_warm_up_with_gps_between(seed):
    lengths = (5.0, 10.0, 30.0, 55.0)
    plan = outage_plan(240.0, lengths, 15.0, 20.0, np.random.default_rng(seed))
    assert sorted(length for _, length in plan) == sorted(lengths)
    starts = [s for s, _ in plan]
    assert starts == sorted(starts)
    assert starts[0] >= 20.0
    for (s0, l0), (s1, _) in itertools.pairwise(plan):
        assert s1 - (s0 + l0) >= 15.0 - 1e-6
    assert plan[-1][0] + plan[-1][1] <= 240.0 - 15.0 + 1e-6


def test_outage_plan_varies_with_the_seed_and_drops_what_does_not_fit_longest_first():
    plans = {tuple(outage_plan(240.0, (5.0, 10.0, 30.0, 55.0), 15.0, 20.0, np.random.default_rng(s))) for s in range(4)}
    assert len(plans) == 4
    short = outage_plan(90.0, (5.0, 10.0, 30.0, 55.0), 10.0, 10.0, np.random.default_rng(0))
    assert sorted(length for _, length in short) == [5.0, 10.0, 30.0]
    assert outage_plan(10.0, (30.0,), 5.0, 5.0, np.random.default_rng(0)) == []


def test_outages_are_labelled_by_the_truths_motion_and_remove_only_the_fixes_inside():
    drive = simulate(SimSettings(scenario="urban", seed=5, duration_s=90.0))
    t0 = drive.settings.start_unix_s
    speed = drive.truth.speed
    assert speed.min() < 0.2, "an urban drive has a stop"
    stopped = drive.truth.t[np.argmax(speed < 0.2)] - t0
    outages = drives.place_outages(drive.truth, [(max(stopped - 1.0, 0.0), 2.0)], t0)
    assert outages[0].motion == "stop"
    fix = GnssFix(t=t0 + 10.0, time_utc=None, lat_deg=50.0, lon_deg=14.0, alt_m=0.0, quality=1, valid=True)
    samples = [fix, dataclasses.replace(fix, t=t0 + 20.0), CanSample(t0 + 10.5, "speed", 1.0)]
    outage = Outage(t0 + 10.0, 5.0, "straight")
    kept = drives.without_fixes_in(samples, [outage])
    assert kept == samples[1:]
    # the outage lasts, for the scores, until the first valid fix after it
    assert outage.scored_span == (t0 + 10.0, t0 + 15.0)
    no_fix = dataclasses.replace(fix, t=t0 + 15.05, valid=False)
    (back,) = drives.with_gps_back([outage], [CanSample(t0 + 15.0, "speed", 1.0), no_fix, *kept])
    assert back.gps_back_s == t0 + 20.0 and back.scored_span == (t0 + 10.0, t0 + 20.0)
    assert drives.with_gps_back([outage], samples[:1])[0].scored_span == (t0 + 10.0, t0 + 15.0)


def test_settings_are_validated():
    with pytest.raises(ValueError, match="scenarios"):
        PeersSettings(scenarios=("moon",))
    with pytest.raises(ValueError, match="duration_s"):
        PeersSettings(duration_s=60.0)
    with pytest.raises(ValueError, match="at most 3600"):
        PeersSettings(duration_s=4000.0)
    with pytest.raises(ValueError, match="seeds"):
        PeersSettings(seeds=(-1,))
    assert PeersSettings().names() == estimator_names(available_only=True)


# ---- isolation ----------------------------------------------------------------------------------------------------


def test_a_run_in_its_own_process_returns_its_value_or_a_failure():
    big = np.arange(10.0)
    assert call_isolated(lambda: big.sum(), 30.0) == 45.0
    with pytest.raises(BenchRunError, match="ZeroDivisionError"):
        call_isolated(lambda: 1 / 0, 30.0)
    with pytest.raises(BenchRunError, match="exit code 7"):
        call_isolated(lambda: os._exit(7), 30.0)
    t = time.monotonic()
    with pytest.raises(BenchRunError, match=r"no result within 0\.5 s"):
        call_isolated(lambda: time.sleep(30.0), 0.5)
    assert time.monotonic() - t < 10.0


class Progress:
    def __init__(self):
        self.started, self.done = [], []

    def starting(self, label):
        self.started.append(label)

    def finished(self, result):
        self.done.append(result)


def test_a_failing_estimator_is_recorded_and_the_others_still_run(monkeypatch):
    monkeypatch.setitem(ESTIMATORS, "broken", (__name__, "BrokenEstimator"))
    ps = PeersSettings(**{**{f: getattr(SHORT, f) for f in SHORT.__slots__}, "estimators": ("broken", "ekf")})
    progress = Progress()
    bench = run_bench(ps, reference_config(), progress)
    assert progress.started == ["urban-gaussian-3 broken", "urban-gaussian-3 ekf"]
    broken, ekf = progress.done
    assert not broken.ok and "RuntimeError: broken on purpose" in broken.error
    assert ekf.ok and len(ekf.outage_errors) == 2
    summary = summarise(bench, "test")
    json.dumps(summary, allow_nan=False)
    assert summary["failures"] == [{"estimator": "broken", "drive": "urban-gaussian-3", "error": broken.error}]
    assert list(summary["profiles"]) == ["kind"]
    estimators = summary["profiles"]["kind"]
    assert estimators["broken"]["kind"] == "failed"
    assert estimators["broken"]["outage"]["all"]["mean_m"] is None
    e = estimators["ekf"]
    assert e["kind"] == "live" and e["failed_runs"] == 0
    assert 0.0 < e["outage"]["all"]["mean_m"] < 20.0
    assert 0.0 < e["with_gps"]["mean_m"] < 5.0
    assert e["latency_ms"]["epoch"]["n"] > 0 and e["throughput_x"] > 1.0
    text = report.markdown(summary)
    assert "## Failed runs" in text and "RuntimeError: broken on purpose" in text
    assert "| `broken` | failed | – |" in text


# ---- profiles and the command line ---------------------------------------------------------------------------------


def test_a_realistic_drive_gets_its_own_quanta_and_delay():
    ps = dataclasses.replace(SHORT, profiles=("realistic",), seeds=(2,))
    (drive,) = drives.drives(ps, reference_config())
    sim = profile_settings("realistic", 2, scenario="urban", duration_s=60.0)
    assert sim.speed_source == "obd" and drive.profile == "realistic" and drive.name == "realistic-urban-2"
    can = drive.config.sensors.can
    assert can.speed_resolution_mps == pytest.approx(1 / 3.6)  # OBD-II: whole km/h
    assert can.yaw_rate_resolution_rps == pytest.approx(math.radians(sim.yaw_rate_quantum_dps))
    assert can.delay_s == sim.can_sensor_delay_s
    assert can.delay_of("speed") == pytest.approx(sim.obd_delay_s)  # the OBD-II reply's age, beyond the yaw rate's
    assert drive.config.datum.mode == "fixed" and drive.outages
    assert PeersSettings().drive_count() == 27 + 9 and dataclasses.replace(SHORT, profiles=()).drive_count() == 0


def test_bad_bench_input_is_an_error_not_a_crash(tmp_path, capsys):
    assert main(["bench", "--drive", str(tmp_path)]) == 1
    assert "no drive.log" in capsys.readouterr().err
    (tmp_path / "drive.log").write_text("")
    assert main(["bench", "--drive", str(tmp_path)]) == 1
    assert "no valid GNSS fix" in capsys.readouterr().err
    assert main(["bench", "--estimators", "ekf,nosuch"]) == 1
    assert "unknown nosuch" in capsys.readouterr().err
    assert main(["bench", "--profile", "cruel"]) == 1
    assert "profiles: unknown 'cruel'" in capsys.readouterr().err
    assert main(["bench", "--seeds", "x"]) == 1
    assert main(["bench", "--scenarios", "moon"]) == 1
    assert "scenarios" in capsys.readouterr().err
    assert main(["bench", "--drive", str(tmp_path), "--lengths", "200"]) == 1
    assert "lengths_s" in capsys.readouterr().err


QUICK_NAMES = ("mhe", "ekf", "dead-reckoning", "su-batch")
"""One estimator of each kind for the quick bench's test: the SU estimators live and offline, a Kalman filter and the
floor (every estimator, the default, took 2.5 min; each live one meets outages and jumps in
test_estimator_contract.py and replays a drive in test_golden_replay.py, the default list is checked above)."""


@pytest.mark.slow
def test_quick_bench_writes_the_table_as_json_and_markdown(tmp_path, capsys):
    out = tmp_path / "tmp"
    assert main(["bench", "--quick", "--estimators", ",".join(QUICK_NAMES), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "peers.json").read_text())
    markdown = (out / "peers.md").read_text()
    assert list(summary["profiles"]) == ["kind", "realistic"]
    assert all(f["drive"].startswith("realistic-") for f in summary["failures"])  # recorded, not fatal
    assert {"python", "numpy", "casadi", "cpu", "blas_threads"} <= set(summary["environment"])
    assert "getrusage" in summary["memory"]
    lengths = {o["length_s"] for d in summary["drives"] for o in d["outages"]}
    assert lengths == {5.0, 10.0, 30.0}
    for profile, estimators in summary["profiles"].items():
        assert list(estimators) == list(QUICK_NAMES), profile
        for name, e in estimators.items():
            if profile == "realistic" and e["kind"] == "failed":
                assert f"| `{name}` | failed |" in markdown
                continue
            assert e["kind"] in ("live", "offline"), name
            assert e["failed_runs"] == 0 and e["nonfinite_estimates"] == 0
            assert set(e["outage"]) == {"all", "5", "10", "30"}
            for stats in [*e["outage"].values(), e["with_gps"], e["heading_deg"]]:
                assert stats["n"] > 0 and finite_numbers(stats), (profile, name)
                assert (
                    0.0
                    <= stats[next(k for k in stats if k.startswith("mean"))]
                    <= stats[next(k for k in stats if k.startswith("max"))]
                )
            assert finite_numbers([e["throughput_x"], e["peak_memory_mb"], e["finish_s"]]), name
            if e["kind"] == "live":
                assert finite_numbers(e["latency_ms"]), name
                assert e["latency_ms"]["sample"]["p50"] <= e["latency_ms"]["sample"]["p99"]
            assert f"| `{name}` | {e['kind']} |" in markdown
    kind = summary["profiles"]["kind"]
    assert kind["mhe"]["kind"] == "live" and kind["su-batch"]["kind"] == "offline"
    dr = kind["dead-reckoning"]["outage"]["30"]["mean_m"]
    assert kind["mhe"]["outage"]["30"]["mean_m"] < dr, "GPS before and CAN during beat CAN alone"
    assert "### kind profile" in printed and "### realistic profile" in printed
    header = next(line for line in printed.splitlines() if line.startswith("| estimator"))
    assert "outages: mean / p95 / max (m)" in header and "x real time" in header and "peak memory" in header
    assert header in markdown and "by the truth's motion" in markdown
