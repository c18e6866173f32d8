"""The README's main job: ``sumhe demo`` plays the bundled drive through the full live path."""

import re

import pytest

from sumhe.cli import main

pytestmark = pytest.mark.slow


def test_demo_runs_the_bundled_drive_and_beats_dead_reckoning(capsys, tmp_path):
    png = tmp_path / "demo.png"
    assert main(["demo", "--speed", "8", "--png", str(png)]) == 0  # 15x overloads 2 shared cores: epochs skipped
    out = capsys.readouterr().out
    rate = float(re.search(r"output rate ([\d.]+) Hz", out).group(1))
    assert rate >= 9.0
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
    assert ours[3] < dr[3], "mean error during the outages below dead reckoning's"
    assert ours[5] < 6.0, "max error during the outages"
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        assert "no plot" in out
    else:
        assert png.stat().st_size > 10_000
