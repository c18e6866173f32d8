"""The README's main job: ``sumhe demo`` plays the bundled drive through the full live path."""

import re
import subprocess
from pathlib import Path

import pytest

from sumhe.cli import main
from sumhe.commands.demo import DEFAULT_OUT

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]


LOAD_WARNINGS = (
    "sumhe.service.app: estimator behind",
    "sumhe.service.app: input",
    "sumhe.service.pipeline: samples dropped for their time",
    "sumhe.estimator.mhe.estimator: mhe: GNSS fix",
    "sumhe.estimator.mhe.estimator: mhe: valid GNSS fix without a speed over ground",
)
"""What a stall of the shared cores of more than ~0.1 s (at 4x: a few epochs) causes in the daemon, as it would in a
car's: counted and logged. Nothing else may warn. The player writes an epoch's GGA and RMC 1.5 ms apart (at 4x); a
stall between them longer than the serial source's idle gap (50 ms) ends the epoch at its GGA: a fix without a
speed, its RMC then dropped as late (:data:`LATE_ONLY`)."""

LATE_ONLY = re.compile(
    r"sumhe\.io\.serial: .*bad NMEA input so far: .*checksum_errors=0 garbled=0 late=\d+ .*backwards=0 .*implausible=0"
)
"""The serial source's report of bad NMEA input when its only bad input is RMCs of epochs a stall split."""


def load_caused(message: str) -> bool:
    """Whether a warning of the demo is one a stall of the machine causes (:data:`LOAD_WARNINGS`)."""
    return message.startswith(LOAD_WARNINGS) or LATE_ONLY.match(message) is not None


def test_demo_at_the_default_speed_runs_clean_and_beats_dead_reckoning(capsys, tmp_path):
    """A clean run logs no warning: no solver failure, no source timeout, no sample dropped for its time because of
    the demo's clocks (each had a cause, fixed in the demo, not hidden by the log level); only a stall of the
    machine may cost a few epochs (of 2100)."""
    png = tmp_path / "figures" / "demo.png"
    assert main(["demo", "--out", str(png)]) == 0
    out, err = capsys.readouterr()
    messages = re.findall(r"^\S+ \S+ (?:WARNING|ERROR|CRITICAL) (.*)$", err, re.M)
    assert [m for m in messages if not load_caused(m)] == [], err
    rate = float(re.search(r"output rate ([\d.]+) Hz", out).group(1))
    assert rate >= 9.0
    assert re.search(r"estimates sent degraded (\d+)", out)
    rows = {
        m.group(1).strip(): [float(x) for x in m.groups()[1:]]
        for m in re.finditer(
            r"^  (sumhe \S+|dead reckoning)\s+([\d.]+) / +([\d.]+) / +([\d.]+) +([\d.]+) / +([\d.]+) / +([\d.]+)",
            out,
            re.M,
        )
    }
    ours = next(v for k, v in rows.items() if k.startswith("sumhe"))
    dr = rows["dead reckoning"]
    assert ours[0] < 1.5, "mean error with GPS"
    assert ours[3] < dr[3], f"mean error during the outages below dead reckoning's:\n{out}\n{err}"
    assert ours[5] < 6.0, "max error during the outages"
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert "matplotlib is not installed" in out
    else:
        assert f"plot: {png}" in out and png.stat().st_size > 10_000


@pytest.mark.skipif(not (REPO / ".git").exists(), reason="not a git checkout")
def test_the_default_figure_is_written_where_git_does_not_track_it():
    ignored = subprocess.run(["git", "check-ignore", "-q", str(DEFAULT_OUT)], cwd=REPO, check=False)
    assert ignored.returncode == 0, f"{DEFAULT_OUT} is not ignored by git"
    tracked = subprocess.run(["git", "ls-files", "*.png"], cwd=REPO, capture_output=True, text=True, check=True)
    assert tracked.stdout == "", "no picture is tracked"
