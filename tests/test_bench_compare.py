"""``sumhe bench compare``: two benchmark results paired outage by outage."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest

from sumhe.bench.compare import (
    calibration_cells,
    calibration_lines,
    compare,
    lines,
    outage_errors,
    pick_names,
    split,
)
from sumhe.cli import main


def _peers(means: dict[str, list[float]]) -> dict:
    """A ``peers.json`` as ``sumhe bench --out`` writes it, reduced to its placements: outage k of drive ``d{k % 3}``
    is ``10 * (1 + k % 2)`` s long and starts at ``20 + k`` s; ``means`` its mean error per estimator."""
    n = len(next(iter(means.values())))
    placements = [
        {
            "drive": f"d{k % 3}",
            "profile": "realistic",
            "start_s": 20.0 + k,
            "length_s": 10.0 * (1 + k % 2),
            "motion": "straight",
            "mean_m": {name: values[k] for name, values in means.items()},
            "max_m": {name: values[k] for name, values in means.items()},
        }
        for k in range(n)
    ]
    return {"benchmark": "peers", "placements": placements}


def _recorded(means: dict[str, list[float]]) -> list:
    """A ``recorded.json``: one drive, 10 s outages at 150, 270, ... s."""
    n = len(next(iter(means.values())))
    rows = {
        name: {
            "outages": [{"start_s": 150.0 + 120 * k, "n": 10, "mean_m": v, "max_m": 2 * v} for k, v in enumerate(vs)]
        }
        for name, vs in means.items()
    }
    return [
        {"drive": "car", "lengths": [{"length_s": 10.0, "outages": [150.0 + 120 * k for k in range(n)], "rows": rows}]}
    ]


def test_both_kinds_of_result_give_each_outages_mean_error_by_drive_length_and_start() -> None:
    peers = outage_errors(_peers({"mhe": [1.0, 2.0, 3.0], "ekf": [4.0, None, 6.0]}))  # type: ignore[list-item]
    assert peers["mhe"] == {("d0", 10.0, 20.0): 1.0, ("d1", 20.0, 21.0): 2.0, ("d2", 10.0, 22.0): 3.0}
    assert peers["ekf"] == {("d0", 10.0, 20.0): 4.0, ("d2", 10.0, 22.0): 6.0}  # a failed run's outage: none
    recorded = outage_errors(_recorded({"mhe": [1.5, 2.5]}))
    assert recorded == {"mhe": {("car", 10.0, 150.0): 1.5, ("car", 10.0, 270.0): 2.5}}
    for bad in ({"benchmark": "mhe"}, [1, 2], "text", {"placements": [{"drive": "d0"}]}, [{"lengths": [{}]}]):
        with pytest.raises(ValueError, match="not a sumhe bench result"):
            outage_errors(bad)


def test_a_change_is_counted_outage_by_outage_with_the_sign_test_and_the_largest_first() -> None:
    before = np.array([5.0] * 10)
    after = before + np.array([-1.0] * 7 + [0.5, 0.5, 0.01])  # 7 better, 2 worse, 1 within the tolerance
    s = split("all", before, after, 0.05)
    assert (s.n, s.better, s.worse) == (10, 7, 2)
    assert s.mean_before == 5.0 and s.change == pytest.approx(-0.599)
    assert s.p_value == pytest.approx(binomtest(7, 9).pvalue) and s.change_low <= s.change <= s.change_high
    assert s.median_ratio == pytest.approx(0.8)
    keys = [("d", 10.0, float(k)) for k in range(10)]
    c = compare(dict(zip(keys, before, strict=True)), dict(zip(keys[:9], after, strict=False)), ("a", "b"), top=3)
    assert (c.before_count, c.after_count, c.splits[0].n) == (10, 9, 9)  # only the outages of both are paired
    assert [k for k, _, _ in c.movers] == keys[:3] and c.movers[0][1:] == (5.0, 4.0)
    text = "\n".join(lines(c))
    assert "9 outages paired (of 10 and 9)" in text and "| 10 s | 9 | 7 | 2 |" in text


def test_nothing_moved_says_so_rather_than_a_p_value_of_nothing() -> None:
    s = split("all", np.array([1.0, 2.0]), np.array([1.0, 2.0]), 0.05)
    assert (s.better, s.worse, s.change, s.p_value) == (0, 0, 0.0, 1.0)
    empty = split("all", np.zeros(0), np.zeros(0), 0.05)
    assert empty.n == 0 and math.isnan(empty.mean_before)


def test_which_estimators_are_compared() -> None:
    a, b = {"mhe": {}, "ekf": {}}, {"mhe": {}, "pf": {}}
    assert pick_names(a, b, ()) == [("mhe", "mhe")]
    assert pick_names(a, a, ("ekf", "mhe")) == [("ekf", "mhe")]
    with pytest.raises(ValueError, match="'pf' is not in the before result"):
        pick_names(a, b, ("pf",))
    with pytest.raises(ValueError, match="one name, or two"):
        pick_names(a, b, ("mhe", "ekf", "pf"))
    with pytest.raises(ValueError, match="no estimator is in both"):
        pick_names({"ekf": {}}, {"pf": {}}, ())


def test_the_command_reads_files_or_their_folders_and_names_what_is_wrong(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "peers.json").write_text(json.dumps(_peers({"mhe": [1.0, 2.0, 3.0, 4.0]})))
    new = tmp_path / "new.json"
    new.write_text(json.dumps(_peers({"mhe": [1.0, 1.0, 5.0, 2.0], "ekf": [9.0, 9.0, 9.0, 9.0]})))
    assert main(["bench", "compare", str(tmp_path / "old"), str(new)]) == 0
    out = capsys.readouterr().out
    assert "`mhe` (before) against `mhe` (after): 4 outages paired" in out and "| all | 4 | 2 | 1 |" in out
    assert main(["bench", "compare", str(new), "--estimators", "ekf,mhe", "--top", "1"]) == 0
    out = capsys.readouterr().out
    assert "| all | 4 | 4 | 0 |" in out and len(re.findall(r"^\| d\d ", out, re.M)) == 1
    assert "error estimates" not in out  # results without the figures: the outages alone
    with_cells = _peers({"mhe": [1.0, 2.0, 3.0, 4.0]})
    with_cells["profiles"] = {"realistic": {"mhe": {"calibration": {"with_gps": _calibration(0.99, 2.0)}}}}
    (tmp_path / "cells.json").write_text(json.dumps(with_cells))
    assert main(["bench", "compare", str(tmp_path / "old"), str(tmp_path / "cells.json")]) == 0
    out = capsys.readouterr().out
    assert "| realistic with GPS | – | 99.0 % (2.00x) | – -> share |" in out
    assert main(["bench", "compare", str(tmp_path), str(new)]) != 0
    assert "no peers.json or recorded.json" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text("{")
    assert main(["bench", "compare", str(tmp_path / "bad.json")]) != 0
    assert "bad.json" in capsys.readouterr().err
    assert main(["bench", "compare", str(new), "--estimators", "pf"]) != 0
    assert "'pf' is not in the before result" in capsys.readouterr().err
    for option in ("--top", "--tolerance"):
        assert main(["bench", "compare", str(new), option, "-1"]) != 0
        assert f"{option}: must be 0 or more" in capsys.readouterr().err


def _calibration(share: float, ratio: float, n: int = 100) -> dict:
    """A bench's calibration entry: ``share`` of the errors within ``eph``, median ``eph`` ``ratio`` times the error."""
    return {"n": n, "eph_coverage": share, "eph_over_error": ratio, "median_eph_m": 3.0 * ratio, "median_error_m": 3.0}


def test_the_error_estimate_cells_of_both_kinds_of_result() -> None:
    peers = _peers({"mhe": [1.0], "ekf": [2.0]})
    peers["profiles"] = {
        "realistic": {
            "mhe": {"calibration": {"with_gps": _calibration(0.989, 2.87), "outage": _calibration(0.95, 2.5)}},
            "ekf": {"calibration": {"with_gps": _calibration(0.9, 2.0), "outage": _calibration(0.0, 0.0, n=0)}},
            "dr": {},
        }
    }
    cells = calibration_cells(peers)
    assert cells["mhe"] == {"realistic with GPS": (0.989, 2.87), "realistic in outages": (0.95, 2.5)}
    assert cells["ekf"] == {"realistic with GPS": (0.9, 2.0)}  # a cell of no estimates is left out
    assert "dr" not in cells
    recorded = _recorded({"mhe": [1.0, 2.0]})
    recorded[0]["lengths"][0]["rows"]["mhe"]["calibration"] = _calibration(0.951, 3.22)
    assert calibration_cells(recorded) == {"mhe": {"car 10 s": (0.951, 3.22)}}
    assert calibration_cells(_peers({"mhe": [1.0]})) == {}  # an older result without the figures
    for bad in ({"placements": [], "profiles": {"realistic": {"mhe": 3}}}, {"profiles": {}}, "text", [{"drive": 1}]):
        with pytest.raises(ValueError, match="not a sumhe bench result"):
            calibration_cells(bad)


def test_the_error_estimate_cells_side_by_side_say_which_targets_each_run_misses() -> None:
    before = {"A with GPS": (0.989, 2.87), "A in outages": (0.95, 2.5), "B 10 s": (0.951, 3.22)}
    after = {"A with GPS": (0.969, 4.2), "A in outages": (0.95, 2.5), "B 60 s": (0.898, 2.4)}
    text = calibration_lines(before, after, ("mhe", "mhe2"))
    assert text[0].startswith("error estimates, `mhe` -> `mhe2`")
    rows = {line.split(" | ")[0].lstrip("| "): line for line in text if line.startswith("| ")}
    assert rows["A with GPS"] == "| A with GPS | 98.9 % (2.87x) | 96.9 % (4.20x) | share -> ratio |"
    assert rows["A in outages"].endswith("| none -> none |")
    assert rows["B 10 s"] == "| B 10 s | 95.1 % (3.22x) | – | ratio -> – |"  # only in the run before
    assert rows["B 60 s"] == "| B 60 s | – | 89.8 % (2.40x) | – -> share |"
    assert rows["cells missing a target"].endswith("| 2 -> 2 |")
    assert calibration_lines({}, {}, ("a", "b")) == []
    assert "none -> share, ratio" in "\n".join(calibration_lines({"c": (0.95, 2.0)}, {"c": (0.99, 3.5)}, ("a", "b")))
