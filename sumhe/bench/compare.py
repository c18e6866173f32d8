"""Two benchmark results compared outage by outage (``sumhe bench compare``).

A change to an estimator moves a few outages by tens of metres and the rest by centimetres, so the mean over a
bench's outages can rise while most outages get better, or fall by one outage's luck: on the realistic profile the
first outage of a drive, 20 s after a standing start, is where the CAN calibration is youngest, and the MHE ended
one such outage 15 m off instead of 122 m with the drive's GNSS time offset configured rather than learned. This module
pairs the outages of two runs (the same drives, the same outages: ``sumhe bench --out`` writes them, the simulated
bench in ``peers.json``'s ``placements``, the recorded one in ``recorded.json``'s per-outage rows) and says how many
got better and how many worse beyond a tolerance, how likely that split is without a change (the two-sided sign
test), the mean change with its interval over the outages (the benches' seeded bootstrap,
:func:`~sumhe.bench.metrics.mean_interval`) and which outages moved most.
The error estimates are compared beside the errors, cell by cell as the benches report them (per simulator profile
with GPS and in outages, per recorded drive and outage length): the share of errors within ``eph`` and the median
``eph`` over the median error before and after, and which cells crossed a target (issue 13's, in
:mod:`sumhe.bench.metrics`): a change that makes the estimates better can move a share across one without the
error estimates changing at all, and a judgement needs both tables side by side.
Pure: plain data in (the JSON as read), plain data out.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from scipy.stats import binomtest

from sumhe.bench.metrics import EPH_OVER_ERROR_MAX, EPH_TARGET, coverage_met, mean_interval, ratio_met

OutageKey = tuple[str, float, float]
"""An outage: the drive's name, its length and its start (s from the drive's start)."""
Parsed = TypeVar("Parsed")
Cell = tuple[float | None, float | None]
"""One error-estimate cell: the share of errors within ``eph`` and the median ``eph`` over the median error (None:
the bench had no figure)."""


def outage_errors(result: Any) -> dict[str, dict[OutageKey, float]]:
    """Per estimator, each outage's mean error (m) in a benchmark result as ``sumhe bench --out`` writes it: the
    simulated bench's ``peers.json`` (a mapping with ``placements``) or the recorded bench's ``recorded.json`` (a
    list of drives). ValueError for anything else, a result without the fields it needs too."""
    return _parsed(_outage_errors, result)


def calibration_cells(result: Any) -> dict[str, dict[str, Cell]]:
    """Per estimator, its error-estimate cells by name (``realistic with GPS``, ``realistic in outages``; ``DRIVE
    10 s``) in a benchmark result (:func:`outage_errors`'s kinds; an estimator or cell without figures is left
    out). ValueError as :func:`outage_errors`."""
    return _parsed(_calibration_cells, result)


def _parsed(parse: Callable[[Any], Parsed], result: Any) -> Parsed:
    """``parse(result)``; a result without the fields it reads a ValueError that says so."""
    try:
        return parse(result)
    except (KeyError, TypeError, AttributeError) as e:
        raise ValueError(
            f"not a sumhe bench result (peers.json or recorded.json): a field missing or malformed ({e})"
        ) from e


def _cell(c: Any) -> Cell | None:
    if not isinstance(c, Mapping) or not c.get("n"):
        return None
    return c.get("eph_coverage"), c.get("eph_over_error")


def _calibration_cells(result: Any) -> dict[str, dict[str, Cell]]:
    out: dict[str, dict[str, Cell]] = {}

    def add(name: str, label: str, c: Any) -> None:
        cell = _cell(c)
        if cell is not None:
            out.setdefault(name, {})[label] = cell

    if isinstance(result, Mapping) and isinstance(result.get("placements"), list):
        for profile, rows in result.get("profiles", {}).items():
            for name, row in rows.items():
                calibration = row.get("calibration", {})
                add(name, f"{profile} with GPS", calibration.get("with_gps"))
                add(name, f"{profile} in outages", calibration.get("outage"))
        return out
    if isinstance(result, list):
        for drive in result:
            for length in drive["lengths"]:
                for name, row in length["rows"].items():
                    add(name, f"{drive['drive']} {float(length['length_s']):g} s", row.get("calibration"))
        return out
    raise ValueError("not a sumhe bench result (peers.json or recorded.json)")


def _cell_text(cell: Cell | None) -> str:
    if cell is None:
        return "–"
    share, ratio = cell
    text = "–" if share is None else f"{100 * share:.1f} %"
    return text + ("" if ratio is None else f" ({ratio:.2f}x)")


def _misses(cell: Cell | None) -> str:
    """Which targets ``cell`` misses ("share", "ratio", both, or "none"; "–" without figures)."""
    if cell is None:
        return "–"
    missed = [what for what, met in (("share", coverage_met(cell[0])), ("ratio", ratio_met(cell[1]))) if not met]
    return ", ".join(missed) or "none"


def calibration_lines(before: Mapping[str, Cell], after: Mapping[str, Cell], names: tuple[str, str]) -> list[str]:
    """The two runs' error-estimate cells side by side (Markdown): the share within ``eph`` (the median ``eph`` over
    the median error), the targets each run misses in the cell, and how many it misses in all."""
    labels = [label for label in before if label in after] + [label for label in after if label not in before]
    labels += [label for label in before if label not in after]
    if not labels:
        return []
    out = [
        f"error estimates, `{names[0]}` -> `{names[1]}`: the share of errors within `eph` (the median `eph` over the "
        f"median error) and the targets missed: a share outside {100 * EPH_TARGET[0]:g}-{100 * EPH_TARGET[1]:g} %, "
        f"a ratio above {EPH_OVER_ERROR_MAX:g}",
        "",
        "| cell | before | after | missed before -> after |",
        "|---|---|---|---|",
    ]
    total = [0, 0]
    for label in labels:
        b, a = before.get(label), after.get(label)
        missed = (_misses(b), _misses(a))
        total[0] += missed[0] not in ("none", "–")
        total[1] += missed[1] not in ("none", "–")
        out.append(f"| {label} | {_cell_text(b)} | {_cell_text(a)} | {missed[0]} -> {missed[1]} |")
    out.append(f"| cells missing a target | | | {total[0]} -> {total[1]} |")
    return out


def _outage_errors(result: Any) -> dict[str, dict[OutageKey, float]]:
    out: dict[str, dict[OutageKey, float]] = {}
    if isinstance(result, Mapping) and isinstance(result.get("placements"), list):
        for p in result["placements"]:
            key = (str(p["drive"]), float(p["length_s"]), float(p["start_s"]))
            for name, mean in p["mean_m"].items():
                if mean is not None:
                    out.setdefault(name, {})[key] = float(mean)
        return out
    if isinstance(result, list) and all(isinstance(d, Mapping) and "lengths" in d for d in result):
        for drive in result:
            for length in drive["lengths"]:
                for name, row in length["rows"].items():
                    for o in row.get("outages", []):
                        if o.get("mean_m") is not None:
                            key = (str(drive["drive"]), float(length["length_s"]), float(o["start_s"]))
                            out.setdefault(name, {})[key] = float(o["mean_m"])
        return out
    raise ValueError("not a sumhe bench result (peers.json or recorded.json)")


@dataclass(frozen=True)
class Split:
    """One group of paired outages: how many, how many got better / worse beyond the tolerance, the means before and
    after (m), the mean change (m) with its 90 % bootstrap interval, the median of after / before, and the sign
    test's two-sided p-value (better against worse; 1 where none moved)."""

    label: str
    n: int
    better: int
    worse: int
    mean_before: float
    mean_after: float
    change: float
    change_low: float
    change_high: float
    median_ratio: float
    p_value: float


@dataclass(frozen=True)
class Comparison:
    """Two runs' outages paired: the estimators compared, how many outages each run had and were paired, the
    groups (all, then per outage length) and the largest changes (key, before, after), largest first."""

    before_name: str
    after_name: str
    before_count: int
    after_count: int
    tolerance_m: float
    splits: list[Split]
    movers: list[tuple[OutageKey, float, float]]


def split(label: str, before: np.ndarray, after: np.ndarray, tolerance_m: float, seed: int = 0) -> Split:
    """The figures of one group of paired outage errors (m, same order)."""
    n = len(before)
    diff = after - before
    better, worse = int(np.sum(diff < -tolerance_m)), int(np.sum(diff > tolerance_m))
    p = binomtest(better, better + worse).pvalue if better + worse else 1.0
    if n:
        low, high = mean_interval(diff, np.arange(n), seed)
        ratios = after[before > 0] / before[before > 0]
        ratio = float(np.median(ratios)) if len(ratios) else math.nan
        return Split(label, n, better, worse, float(before.mean()), float(after.mean()), float(diff.mean()), low,
                     high, ratio, float(p))  # fmt: skip
    return Split(label, 0, 0, 0, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, 1.0)


def compare(
    before: Mapping[OutageKey, float],
    after: Mapping[OutageKey, float],
    names: tuple[str, str],
    tolerance_m: float = 0.05,
    top: int = 10,
) -> Comparison:
    """Pair the outages of ``before`` and ``after`` (each outage's mean error, m) by drive, length and start."""
    keys = sorted(set(before) & set(after))
    b = np.array([before[k] for k in keys])
    a = np.array([after[k] for k in keys])
    splits = [split("all", b, a, tolerance_m)]
    for length in sorted({k[1] for k in keys}):
        pick = np.array([k[1] == length for k in keys])
        splits.append(split(f"{length:g} s", b[pick], a[pick], tolerance_m))
    order = np.argsort(-np.abs(a - b), kind="stable")[:top] if keys else []
    movers = [(keys[i], float(b[i]), float(a[i])) for i in order]
    return Comparison(names[0], names[1], len(before), len(after), tolerance_m, splits, movers)


def lines(c: Comparison) -> list[str]:
    """The comparison as Markdown: the groups' table, then the largest changes."""

    def num(v: float, fmt: str = ".2f") -> str:
        return "–" if not math.isfinite(v) else format(v, fmt)

    out = [
        f"`{c.before_name}` (before) against `{c.after_name}` (after): {c.splits[0].n} outages paired (of "
        f"{c.before_count} and {c.after_count}); better or worse: the outage's mean error moved by more than "
        f"{c.tolerance_m:g} m",
        "",
        "| outages | paired | better | worse | mean of the outages' errors before -> after (m) | "
        "mean change [90 % interval] (m) | median after / before | sign test p |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in c.splits:
        out.append(
            f"| {s.label} | {s.n} | {s.better} | {s.worse} | {num(s.mean_before)} -> {num(s.mean_after)} | "
            f"{num(s.change, '+.2f')} [{num(s.change_low, '+.2f')}, {num(s.change_high, '+.2f')}] | "
            f"{num(s.median_ratio, '.3f')} | {num(s.p_value, '.2g')} |"
        )
    if c.movers:
        out += [
            "",
            "largest changes:",
            "",
            "| drive | length (s) | start (s) | before (m) | after (m) |",
            "|---|---|---|---|---|",
        ]
        out += [f"| {k[0]} | {k[1]:g} | {k[2]:g} | {b:.2f} | {a:.2f} |" for k, b, a in c.movers]
    return out


def pick_names(before: Mapping[str, Any], after: Mapping[str, Any], wanted: Sequence[str]) -> list[tuple[str, str]]:
    """The estimator pairs to compare: ``wanted`` = ``[NAME]`` (that one in both), ``[OLD, NEW]`` (OLD in ``before``
    against NEW in ``after``) or empty (every estimator in both). ValueError naming what is missing."""
    if len(wanted) > 2:
        raise ValueError(f"--estimators: one name, or two (before, after), got {len(wanted)}")
    if not wanted:
        pairs = [(n, n) for n in before if n in after]
        if not pairs:
            raise ValueError("no estimator is in both results")
        return pairs
    old, new = wanted[0], wanted[-1]
    for name, result, which in ((old, before, "before"), (new, after, "after")):
        if name not in result:
            raise ValueError(f"--estimators: {name!r} is not in the {which} result (it has {', '.join(result)})")
    return [(old, new)]
