"""The report of ``sumhe bench`` (``peers``): every run's figures summarised per estimator, as plain data (JSON)
and as Markdown tables (the README's table)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sumhe.bench import metrics
from sumhe.bench.metrics import BOX_TARGET, EPH_OVER_ERROR_MAX, EPH_TARGET
from sumhe.bench.peers import MEMORY_METHOD, BenchReport, DriveInfo, RunResult
from sumhe.service.histogram import histogram_percentile, latency_histogram

MOTION_ORDER = ("straight", "bend", "sharp", "stop")


# ---- summary -------------------------------------------------------------------------------------------------------


def _errors(values: Sequence[NDArray[np.float64]], unit: str = "m", scale: float = 1.0) -> dict[str, float]:
    pooled = np.concatenate(values) * scale if values else np.zeros(0)
    mean, p95, mx = metrics.mean_p95_max(pooled)
    return {"n": int(pooled.size), f"mean_{unit}": mean, f"p95_{unit}": p95, f"max_{unit}": mx}


def _rows(parts: Sequence[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The runs' calibration columns stacked, each run's groups (its outages, or its drive) apart from the others'."""
    if not parts:
        return np.zeros((0, len(metrics.CALIBRATION_COLUMNS)))
    rows, first = np.vstack(parts), 0
    groups = []
    for part in parts:
        index = np.unique(part[:, -1], return_inverse=True)[1]
        groups.append(index + first)
        first += int(index.max()) + 1 if index.size else 0
    rows[:, -1] = np.concatenate(groups)
    return rows


def _length_key(length_s: float) -> str:
    return f"{length_s:g}"


def summarise_estimator(name: str, results: Sequence[RunResult], drives_: Sequence[DriveInfo]) -> dict[str, Any]:
    """One estimator's figures over all its runs (plain data; NaN where nothing was measured). ``kind`` is
    ``live`` (answers as it goes), ``offline`` (answers only in ``finish()``) or ``failed`` (every run failed)."""
    outages = {d.name: d.outages for d in drives_}
    ok = [r for r in results if r.ok]
    by_length: dict[str, list[NDArray[np.float64]]] = {}
    by_motion: dict[str, list[NDArray[np.float64]]] = {}
    for r in ok:
        for outage, errs in zip(outages[r.drive], r.outage_errors, strict=True):
            by_length.setdefault(_length_key(outage.length_s), []).append(errs)
            by_motion.setdefault(outage.motion, []).append(errs)
    lengths = sorted({_length_key(o.length_s) for d in drives_ for o in d.outages}, key=float)
    empty = latency_histogram([])
    hists = {
        "sample": sum((r.sample_hist for r in ok), empty),
        "epoch": sum((r.epoch_hist for r in ok), empty),
    }
    live = sum(r.live_estimates for r in ok)
    offline = sum(r.finish_estimates for r in ok)
    return {
        "kind": "failed" if not ok else ("offline" if live == 0 and offline > 0 else "live"),
        "runs": len(results),
        "failed_runs": len(results) - len(ok),
        "estimates": live + offline,
        "nonfinite_estimates": sum(r.nonfinite for r in ok),
        "outage": {"all": _errors([e for r in ok for e in r.outage_errors])}
        | {L: _errors(by_length.get(L, [])) for L in lengths},
        "outage_by_motion": {m: _errors(by_motion[m]) for m in MOTION_ORDER if m in by_motion},
        "with_gps": _errors([r.gps_errors for r in ok]),
        "heading_deg": _errors([r.heading_errors for r in ok], "deg", math.degrees(1.0)),
        "calibration": {
            "with_gps": metrics.calibration(_rows([r.calib_gps for r in ok])),
            "outage": metrics.calibration(_rows([r.calib_outage for r in ok])),
        },
        "latency_ms": {
            kind: {
                "n": int(hist.sum()),
                "p50": histogram_percentile(hist, 50.0),
                "p99": histogram_percentile(hist, 99.0),
            }
            for kind, hist in hists.items()
        },
        "finish_s": sum(r.finish_s for r in ok),
        "build_s": max((r.build_s for r in ok), default=math.nan),
        "throughput_x": metrics.throughput(sum(r.span_s for r in ok), sum(r.push_s + r.finish_s for r in ok)),
        "peak_memory_mb": max((r.peak_mb for r in ok), default=math.nan),
    }


def summarise(report: BenchReport, command: str = "sumhe bench") -> dict[str, Any]:
    """The whole report as plain data, ready for JSON (NaN written as null): how it ran, the drives and outages,
    per profile per estimator its figures, per placement each estimator's mean and max error, and the failed
    runs."""
    names = list(dict.fromkeys(r.estimator for r in report.results))
    placements = []
    for d in report.drives:
        runs = {r.estimator: r for r in report.results if r.drive == d.name and r.ok}
        for i, o in enumerate(d.outages):
            stats = {n: metrics.mean_p95_max(r.outage_errors[i]) for n, r in runs.items()}
            placements.append(
                {
                    "drive": d.name,
                    "profile": d.profile,
                    "start_s": round(o.start_s - d.t0, 2),
                    "length_s": o.length_s,
                    "motion": o.motion,
                    "mean_m": {n: s[0] for n, s in stats.items()},
                    "max_m": {n: s[2] for n, s in stats.items()},
                }
            )
    profiles = {}
    for profile in dict.fromkeys(d.profile for d in report.drives):
        drives_ = [d for d in report.drives if d.profile == profile]
        on = {d.name for d in drives_}
        profiles[profile] = {
            n: summarise_estimator(n, [r for r in report.results if r.estimator == n and r.drive in on], drives_)
            for n in names
        }
    data = {
        "benchmark": "peers",
        "command": command,
        "environment": report.environment,
        "memory": MEMORY_METHOD,
        "settings": dataclasses.asdict(report.settings),
        "wall_s": report.wall_s,
        "drives": [
            {
                "name": d.name,
                "profile": d.profile,
                "span_s": d.span_s,
                "outages": [
                    {
                        "start_s": round(o.start_s - d.t0, 2),
                        "length_s": o.length_s,
                        "motion": o.motion,
                        "gps_back_s": round(o.scored_span[1] - d.t0, 2),
                    }
                    for o in d.outages
                ],
            }
            for d in report.drives
        ],
        "profiles": profiles,
        "placements": placements,
        "failures": [
            {"estimator": r.estimator, "drive": r.drive, "error": r.error} for r in report.results if not r.ok
        ],
    }
    return _json_ready(data)  # type: ignore[no-any-return]


def _json_ready(value: Any) -> Any:
    """NaN and infinities -> None (JSON has neither); tuples -> lists; numpy scalars -> Python numbers."""
    if isinstance(value, Mapping):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# ---- Markdown ------------------------------------------------------------------------------------------------------


def _num(value: float | None, digits: int = 2) -> str:
    if value is None:
        return "–"
    if digits < 0:  # significant figures (latencies span microseconds to seconds)
        return f"{value:.{-digits}g}"
    return f"{value:.{digits}f}"


def _cell(stats: Mapping[str, Any], keys: Sequence[str], digits: int = 2) -> str:
    if not stats or not stats.get("n"):
        return "–"
    return " / ".join(_num(stats.get(k), digits) for k in keys)


def _scaled(stats: Mapping[str, Any], scale: float) -> dict[str, Any]:
    return {k: v * scale if isinstance(v, float) and k != "n" else v for k, v in stats.items()}


def how_it_ran(summary: Mapping[str, Any]) -> list[str]:
    """Lines saying what ran where: drives, outages, estimators, versions, CPU, threads, wall time."""
    env = summary["environment"]
    drives_ = summary["drives"]
    counts: dict[str, int] = {}
    for d in drives_:
        for o in d["outages"]:
            key = _length_key(o["length_s"])
            counts[key] = counts.get(key, 0) + 1
    per_length = ", ".join(f"{n} of {L} s" for L, n in sorted(counts.items(), key=lambda kv: float(kv[0])))
    span = sum(d["span_s"] for d in drives_)
    return [
        f"`{summary['command']}`: {len(drives_)} drives ({span:.0f} s of data: "
        + ", ".join(d["name"] for d in drives_)
        + f"), {sum(counts.values())} outages ({per_length}); estimators: "
        + ", ".join(next(iter(summary["profiles"].values()), {}))
        + ".",
        f"Ran on {env['cpu']}; {env['python']}, numpy {env['numpy']}, casadi {env['casadi']}, sumhe "
        f"{env['sumhe']}; {env['blas_threads']}; one run at a time, each in its own forked process; "
        f"{summary['wall_s']:.0f} s wall.",
    ]


PROFILE_TITLES = {
    "kind": "kind profile (the simulator's clean sensors)",
    "realistic": "realistic profile (real-car sensor errors drawn per seed: docs/simulator.md)",
}


def profile_title(profile: str, summary: Mapping[str, Any]) -> str:
    """A heading for one profile's tables, with its drive count."""
    n = sum(d["profile"] == profile for d in summary["drives"])
    return f"### {PROFILE_TITLES.get(profile, profile)}: {n} drives"


def main_table(summary: Mapping[str, Any], profile: str) -> list[str]:
    """THE table of one profile: one row per estimator (Markdown)."""
    estimators = summary["profiles"][profile]
    lengths = [k for k in next(iter(estimators.values()))["outage"] if k != "all"] if estimators else []
    mpm = ("mean_m", "p95_m", "max_m")
    head = (
        ["estimator", "kind", "outages: mean / p95 / max (m)"]
        + [f"{L} s outages (m)" for L in lengths]
        + [
            "with GPS: mean / p95 / max (m)",
            "heading: mean / p95 (deg)",
            "latency per sample p50 / p99 (µs)",
            "per GNSS epoch p50 / p99 (ms)",
            "x real time",
            "peak memory (MB)",
            "failed runs",
        ]
    )
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for name, e in estimators.items():
        offline = e["kind"] == "offline"
        latency = [
            "offline" if offline else _cell(_scaled(e["latency_ms"][k], scale), ("p50", "p99"), -2)
            for k, scale in (("sample", 1e3), ("epoch", 1.0))
        ]
        row = (
            [f"`{name}`", e["kind"], _cell(e["outage"]["all"], mpm)]
            + [_cell(e["outage"].get(L, {}), mpm) for L in lengths]
            + [
                _cell(e["with_gps"], mpm),
                _cell(e["heading_deg"], ("mean_deg", "p95_deg")),
                *latency,
                _num(e["throughput_x"], 0),
                _num(e["peak_memory_mb"], 0),
                f"{e['failed_runs']} of {e['runs']}",
            ]
        )
        lines.append("| " + " | ".join(row) + " |")
    return lines


def calibration_table(summary: Mapping[str, Any], profile: str) -> list[str]:
    """Error estimates and bound boxes against the errors, with GPS and in outages (Markdown); each cell says
    whether it meets the targets (:data:`EPH_TARGET`, :data:`EPH_OVER_ERROR_MAX`, :data:`BOX_TARGET`)."""
    head = ["estimator"]
    for where in ("with GPS", "outages"):
        head += [
            f"{where}: error within eph [90 % interval over {'drives' if where == 'with GPS' else 'outages'}]",
            f"{where}: median eph / median error (m)",
            f"{where}: truth in bound box",
            f"{where}: median box half-width (m)",
        ]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for name, e in summary["profiles"][profile].items():
        cells = [f"`{name}`"]
        for where in ("with_gps", "outage"):
            cells += calibration_cells(e.get("calibration", {}).get(where, {}))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def calibration_cells(c: Mapping[str, Any]) -> list[str]:
    """Four cells of one :func:`~sumhe.bench.metrics.calibration`: eph coverage (with the target met or not, and
    its interval over the groups: :func:`~sumhe.bench.metrics.coverage_interval`),
    median eph / median error (ratio), box coverage, median box half-width."""
    if not c or not c.get("n"):
        return ["–", "–", *_box_cells(c)]
    cover, ratio = c.get("eph_coverage"), c.get("eph_over_error")
    return [
        f"{_num(100 * cover if cover is not None else None, 1)} % {_verdict(metrics.coverage_met(cover))}"
        f"{_interval(c)}",
        f"{_num(c.get('median_eph_m'))} / {_num(c.get('median_error_m'))} = {_num(ratio)}"
        f" {_verdict(metrics.ratio_met(ratio))}",
        *_box_cells(c),
    ]


def _verdict(met: bool) -> str:
    return "(met)" if met else "(missed)"


def _interval(c: Mapping[str, Any]) -> str:
    """`` [low-high]``: the coverage's bootstrap interval over the groups, in %, where it has one."""
    low, high = c.get("eph_coverage_low"), c.get("eph_coverage_high")
    if low is None or high is None or not (math.isfinite(low) and math.isfinite(high)):
        return ""
    return f" [{100 * low:.1f}-{100 * high:.1f}]"


def _box_cells(c: Mapping[str, Any]) -> list[str]:
    if not c or not c.get("box_n"):
        return ["no box", "–"]
    cover = c.get("box_coverage")
    met = cover is not None and cover >= BOX_TARGET
    return [
        f"{_num(100 * cover if cover is not None else None, 2)} % {'(≥ 99 %)' if met else '(< 99 %)'}",
        _num(c.get("median_box_half_m")),
    ]


def motion_table(summary: Mapping[str, Any], profile: str) -> list[str]:
    """Mean / max error during outages of one profile's drives by what the vehicle did (Markdown)."""
    placements = [p for p in summary["placements"] if p["profile"] == profile]
    motions = [m for m in MOTION_ORDER if any(p["motion"] == m for p in placements)]
    n = {m: sum(p["motion"] == m for p in placements) for m in motions}
    head = ["estimator", *(f"{m} ({n[m]} outages): mean / p95 / max (m)" for m in motions)]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for name, e in summary["profiles"][profile].items():
        cells = [_cell(e["outage_by_motion"].get(m, {}), ("mean_m", "p95_m", "max_m")) for m in motions]
        lines.append("| " + " | ".join([f"`{name}`", *cells]) + " |")
    return lines


def markdown(summary: Mapping[str, Any]) -> str:
    """The Markdown report: how it ran, the table, errors by motion, how each figure is measured, failures."""
    out = ["# sumhe bench: estimators side by side", "", *how_it_ran(summary), ""]
    for profile in summary["profiles"]:
        out += [profile_title(profile, summary), "", *main_table(summary, profile), ""]
    out += ["## Position error during outages by the truth's motion", ""]
    for profile in summary["profiles"]:
        out += [profile_title(profile, summary), "", *motion_table(summary, profile), ""]
    out += ["## Error estimates and bound boxes against the errors", ""]
    for profile in summary["profiles"]:
        out += [profile_title(profile, summary), "", *calibration_table(summary, profile), ""]
    out += [
        "## How the figures are measured",
        "",
        "- Position error: horizontal distance of every estimate (GNSS epochs and CAN rate; offline smoothers: "
        "every grid step) from the truth at its time, inside the outages (from the first missing fix to the first "
        "fix after) / outside them after a "
        f"{summary['settings']['warm_up_s']:g} s warm-up (with GPS).",
        f"- Heading: azimuth error, wrapped, while the truth moves faster than "
        f"{summary['settings']['heading_min_speed_mps']:g} m/s.",
        "- Latency: wall time of each `Pipeline.push` (time checks, frame conversion, estimator, geodetic "
        "output); per GNSS epoch = the pushes of a GNSS fix. Offline smoothers answer in `finish()`: their cost "
        "is in x real time.",
        "- x real time: seconds of data / seconds of `push` + `finish` (estimator construction left out).",
        f"- Peak memory: {summary['memory']}.",
        "- Error estimates: the share of estimates whose error (against the truth) lies within their `eph` (95 % "
        f"nominal; target {100 * EPH_TARGET[0]:g}-{100 * EPH_TARGET[1]:g} %), median `eph` over median error "
        f"(target <= {EPH_OVER_ERROR_MAX:g}); bound box: the share whose truth lies within `bound_east` and "
        f"`bound_north` of the estimate (target >= {100 * BOX_TARGET:g} % on bounded-noise drives), and the median "
        "of the box's larger half-width.",
    ]
    if summary["failures"]:
        out += ["", "## Failed runs", ""]
        out += [f"- `{f['estimator']}` on {f['drive']}: {f['error']}" for f in summary["failures"]]
    return "\n".join(out) + "\n"
