"""The paper's protocol on a simulated drive: windows, dead reckoning, the summary, the CLI."""

import numpy as np
import pytest

from sumhe.bench.protocol import (
    ProtocolSettings,
    Run,
    dead_reckoning,
    format_report,
    label_motion,
    make_windows,
    method_settings,
    run_protocol,
    summarise,
)
from sumhe.cli import main
from sumhe.settings import EstimationSettings, with_changes
from sumhe.sim import SimSettings, simulate

SHORT = ProtocolSettings(duration_s=40.0, placements=2, methods=("nlp", "lp", "dr"))


@pytest.fixture(scope="module")
def drive():
    return simulate(SimSettings(scenario="offroad", seed=1, duration_s=40.0, gps_error="rtk"))


def test_windows_cut_the_outage(drive) -> None:
    est = EstimationSettings()
    windows = make_windows(drive, SHORT, est)
    assert len(windows) == 2
    for w in windows:
        assert len(w.epoch_t) == 70 and w.outage.sum() == 50
        fixes = [s for s in w.samples if hasattr(s, "lat_deg")]
        assert len(fixes) == 20
        times = [s.t for s in w.samples]
        assert times == sorted(times)
        assert w.label in ("stop", "sharp", "bend", "straight")


def test_dead_reckoning_is_exact_at_fixes_and_drifts_in_the_outage(drive) -> None:
    est = with_changes(EstimationSettings(), {"can.delay_s": drive.settings.can_sensor_delay_s})
    w = make_windows(drive, SHORT, est)[1]
    east, north = dead_reckoning(w, est, drive.frame)
    truth = drive.truth.at(w.epoch_t)
    err = np.hypot(east - truth.east, north - truth.north)
    assert err[~w.outage].max() < 0.1  # the fixes themselves (cm-level)
    assert err[w.outage].max() > err[~w.outage].max()  # CAN scale and bias make it drift


def test_label_motion() -> None:
    assert label_motion(np.array([0.2, 3.0]), np.array([0.0, 0.0])) == "stop"
    assert label_motion(np.array([5.0, 6.0]), np.array([0.0, 0.5])) == "sharp"
    assert label_motion(np.array([5.0, 6.0]), np.array([0.1, -0.1])) == "bend"
    assert label_motion(np.array([5.0, 6.0]), np.array([0.01, -0.01])) == "straight"


def test_summary_and_table() -> None:
    runs = [
        Run("nlp", k, "bend", mx, mx / 2, mx / 4, mx / 8, True, 0.05, 0.1) for k, mx in enumerate([0.1, 0.2, 0.6, 0.3])
    ]
    runs.append(Run("dr", 0, "bend", np.inf, np.inf, np.inf, np.inf, False, 0.0, 0.0))
    (nlp, dr) = summarise(runs, 0.5)
    assert nlp["under_bar"] == 0.75
    assert nlp["max_worst_m"] == 0.6
    assert nlp["failed"] == 0 and dr["failed"] == 1
    assert dr["max_p95_m"] == np.inf
    text = format_report(runs[:4], ProtocolSettings(methods=("nlp",)))
    assert "nlp" in text and "0.600" in text


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="methods"):
        ProtocolSettings(methods=("kalman",))
    with pytest.raises(ValueError, match="placements"):
        ProtocolSettings(placements=0)
    paper = method_settings("paper", EstimationSettings())
    b = paper.estimator.batch
    assert (b.objective, b.centre, b.derived_floors, paper.estimator.yaw_rate_bias) == ("log", "none", False, False)


@pytest.mark.slow
def test_protocol_on_a_short_drive_meets_the_bar() -> None:
    runs = run_protocol(SHORT)
    nlp = [r for r in runs if r.method == "nlp"]
    assert len(nlp) == 2 and all(r.success for r in nlp)
    assert max(r.max_m for r in nlp) < 0.5
    assert all(np.isfinite(r.max_m) for r in runs)


@pytest.mark.slow
def test_cli_prints_the_table(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["protocol", "--duration", "40", "--placements", "1", "--methods", "lp,dr"])
    out = capsys.readouterr().out
    assert code == 0
    assert "max med" in out and "lp" in out and "dr" in out
    assert main(["protocol", "--methods", "kalman"]) == 1
    assert "unknown method" in capsys.readouterr().err
