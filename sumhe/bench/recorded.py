"""``sumhe bench --drive DIR_OR_LOGS ...``: every live estimator on recorded drives without a reference, against the
fixes it was not given, next to two dead-reckoning floors (:mod:`sumhe.bench.floors`).

A drive is a folder (``drive.log``, ``drive.nmea`` if there is one, ``config.toml`` unless ``--config`` is given,
``truth.csv`` if there is one: the simulator's folders) or log files (candump, MF4, ...; ``*.nmea`` files among them
are NMEA logs), read as ``sumhe replay`` reads them. Outages of each length (10, 30, 60 s) are placed every
``spacing_s`` from ``first_s`` after the first CAN frame, each moved later in 5 s steps (up to the room before the
next one) until the car moves through it (mean CAN speed of at least ``min_speed_mps``) with a fix just before it
and fixes inside it: reproducible, spread over the drive, while moving. Each estimator runs once per length,
pushed through :class:`~sumhe.service.pipeline.Pipeline` with the fixes inside that length's outages removed (in a
forked process with a time limit, as ``sumhe bench`` runs); its estimates, interpolated to each removed fix's time,
are compared with the fix (:func:`~sumhe.bench.outages.outage_errors`). An estimator that reports a learned GNSS
time offset in ``stats()`` as ``gps_time_offset_s`` is compared with the fixes at their stamped time plus that
offset (its estimates are on that clock); others, and the floors, at the stamped time. With ``truth.csv`` the
estimates inside the outages are also compared with the truth at their own times, and, where the folder has the
simulator's ``scenario.toml`` too, the floors (which dead-reckon the antenna from the last fix) with where the
antenna truly was at the removed fixes' times (:func:`~sumhe.sim.measure.true_antenna`: the GNSS clock's offset and
the lever arm applied): each is scored on the point it estimates.

Per length: mean / p95 / max of the errors for each estimator and both floors, the share of epochs on widened
bounds and of solver failures (:func:`~sumhe.bench.outages.mode_shares`), x real time (seconds of data over
seconds of pushing), the error estimates' calibration, and each outage's mean / max for every estimator and floor
(which outages an estimator loses, and where every one of them does).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sumhe.bench import outages
from sumhe.bench.floors import CanTrack, Fixes, calibrated_floor, plain_floor
from sumhe.bench.metrics import calibration, calibration_columns, interval_index, mean_p95_max
from sumhe.bench.peers import BenchRunError, call_isolated
from sumhe.bench.report import calibration_cells
from sumhe.calibration import signals_of
from sumhe.config import Config, load_config
from sumhe.errors import ConfigError
from sumhe.estimator.registry import estimator_names, make_estimator
from sumhe.geo import LocalFrame
from sumhe.io.replay import RecordedDrive
from sumhe.messages import Estimate, Sample
from sumhe.service.pipeline import Pipeline
from sumhe.sim import SimSettings, Truth, load_settings, load_truth
from sumhe.sim.measure import true_antenna

FLOORS = ("floor: dead reckoning", "floor: calibrated dead reckoning")
"""The floors' names in the report (:func:`~sumhe.bench.floors.plain_floor`, ``calibrated_floor``)."""
SHIFT_STEP_S = 5.0
MAX_FIX_GAP_BEFORE_S = 2.0


@dataclass(frozen=True, slots=True)
class RecordedBenchSettings:
    """Outage lengths and placement (s, m/s), the estimators (empty: every live one) and a run's time limit."""

    lengths_s: tuple[float, ...] = (10.0, 30.0, 60.0)
    spacing_s: float = 120.0
    first_s: float = 150.0
    min_speed_mps: float = 3.0
    estimators: tuple[str, ...] = ()
    timeout_s: float = 1800.0

    def __post_init__(self) -> None:
        if not self.lengths_s or any(not 0.0 < L < self.spacing_s for L in self.lengths_s):
            raise ValueError(f"lengths_s: need lengths within (0, spacing_s), got {self.lengths_s!r}")
        for name in ("spacing_s", "first_s", "timeout_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)!r}")

    def names(self) -> tuple[str, ...]:
        return self.estimators or estimator_names(live_only=True)


@dataclass(frozen=True, eq=False)
class Recording:
    """A recorded drive as the bench runs it: its samples (every fix kept), its valid fixes in a local frame, its
    CAN track, the first CAN frame's time (s), its truth if it has one (east/north in ``frame``) and the simulator's
    settings of a simulated drive."""

    name: str
    config: Config
    samples: list[Sample]
    frame: LocalFrame
    fixes: Fixes
    track: CanTrack
    t0: float
    truth: Truth | None
    sim: SimSettings | None = None

    @property
    def span_s(self) -> float:
        return self.samples[-1].t - self.samples[0].t if self.samples else 0.0


def load_recording(spec: Sequence[str], config_path: str | None, fallback: Callable[[], Config]) -> Recording:
    """One drive from a folder or log files (see the module docstring), with the config of ``config_path``, else
    the folder's ``config.toml``, else the one ``fallback`` makes (only then: the environment's overrides,
    ``SUMHE_...``, are meant for the config in use, and one that only a CAN-GNSS config takes stopped the defaults
    from loading); ConfigError naming what is missing."""
    paths = [Path(p) for p in spec]
    truth_path = scenario = None
    if len(paths) == 1 and paths[0].is_dir():
        d = paths[0]
        if not (d / "drive.log").is_file():
            raise ConfigError(f"--drive {d}: no drive.log in it")
        can_logs, nmea_logs = [d / "drive.log"], [d / "drive.nmea"] if (d / "drive.nmea").is_file() else []
        config_path = config_path or (str(d / "config.toml") if (d / "config.toml").is_file() else None)
        truth_path = d / "truth.csv" if (d / "truth.csv").is_file() else None
        scenario = d / "scenario.toml" if truth_path and (d / "scenario.toml").is_file() else None
        name = d.name or str(d)
    else:
        can_logs = [p for p in paths if p.suffix.lower() != ".nmea"]
        nmea_logs = [p for p in paths if p.suffix.lower() == ".nmea"]
        name = paths[0].parent.name or paths[0].name
    config = load_config(config_path) if config_path else fallback()
    drive = RecordedDrive(config, can_logs, nmea_logs or None)
    samples = list(drive.samples())
    sig = signals_of(drive, samples)
    frame = LocalFrame(*sig.origin_deg, 0.0)
    truth = load_truth(truth_path) if truth_path else None
    if truth is not None:
        en = frame.to_enu(truth.lat, truth.lon)
        truth = dataclasses.replace(truth, east=en[:, 0], north=en[:, 1])
    try:
        sim = load_settings(scenario) if scenario else None
    except (OSError, ValueError) as e:
        raise ConfigError(f"--drive {name}: {scenario}: {e}") from e
    if len(sig.t_yaw) < 2:
        raise ConfigError(f"--drive {name}: no CAN yaw rate decoded (can.signals.yaw_rate in {drive.config.source})")
    return Recording(
        name,
        drive.config,
        samples,
        frame,
        Fixes(sig.t_fix, sig.east, sig.north, sig.course, sig.heading),
        CanTrack.of(sig.t_speed, sig.speed, sig.t_yaw, sig.yaw, drive.config.sensors.can.delay_s),
        drive.first_t if math.isfinite(drive.first_t) else samples[0].t,
        truth,
        sim,
    )


def place_outages(rec: Recording, length_s: float, bs: RecordedBenchSettings) -> list[tuple[float, float]]:
    """Absolute windows ``[start, start + length)`` of one length (see the module docstring)."""
    room = max(bs.spacing_s - length_s - 30.0, 0.0)
    out: list[tuple[float, float]] = []
    t_last = float(rec.fixes.t[-1])
    nominal = rec.t0 + bs.first_s
    while nominal + length_s < t_last:
        for shift in np.arange(0.0, room + 1e-9, SHIFT_STEP_S):
            start = nominal + float(shift)
            if start + length_s < t_last and _usable(rec, start, length_s, bs.min_speed_mps):
                out.append((start, start + length_s))
                break
        nominal += bs.spacing_s
    return out


def _usable(rec: Recording, start: float, length_s: float, min_speed_mps: float) -> bool:
    track, t = rec.track, rec.fixes.t
    inside = (track.t >= start) & (track.t < start + length_s)
    if not inside.any() or float(np.mean(track.speed[inside])) < min_speed_mps:
        return False
    i = rec.fixes.last_before(start)
    fixes_inside = np.count_nonzero((t >= start) & (t < start + length_s))
    return i >= 0 and start - t[i] <= MAX_FIX_GAP_BEFORE_S and fixes_inside > 0


@dataclass(frozen=True)
class RunOutcome:
    """One estimator on one drive with the outages of one length: the errors (m) against the removed fixes
    (pooled over the outages, and each outage's) and, with a truth, every estimate's inside them against the truth;
    its epochs' modes; seconds of data and of pushing; the GNSS time offset its estimates were compared at (s); how
    its ``eph`` and bound box describe its errors against the removed fixes
    (:func:`~sumhe.bench.metrics.calibration`)."""

    fix_errors: outages.OutageErrors
    per_outage: list[outages.OutageErrors]
    truth_errors: np.ndarray
    shares: outages.ModeShares
    span_s: float
    wall_s: float
    offset_s: float
    calibration: dict[str, float | int]


def run_estimator(name: str, rec: Recording, windows: Sequence[tuple[float, float]]) -> RunOutcome:
    """Push the drive without the fixes in ``windows`` through a Pipeline with the estimator ``name``; score it."""
    pipeline = Pipeline(rec.config, make_estimator(name, rec.config))
    cut = outages.FixCut(windows)
    margin = outages.MAX_INTERPOLATION_GAP_S
    near = [(a - margin, b + margin) for a, b in windows]
    kept: list[tuple[float, ...]] = []
    modes: Counter[str] = Counter()
    wall0 = time.perf_counter()
    for sample in rec.samples:
        if not cut.keep(sample):
            continue
        for est in pipeline.push(sample):
            modes[est.mode] += 1
            if interval_index([est.t], near)[0] >= 0:
                kept.append(_row(est))
    for est in pipeline.finish():
        modes[est.mode] += 1
        kept.append(_row(est))
    wall = time.perf_counter() - wall0
    offset = float(pipeline.estimator.stats().get("gps_time_offset_s", 0.0))
    est = np.array(kept, dtype=float).reshape(-1, 6)
    per_outage, errors = outages.outage_errors(windows, cut.removed, est[:, 0], est[:, 1], est[:, 2], offset)
    t_fix, d_east, d_north, (eph, bound_east, bound_north) = outages.residuals_at_fixes(
        cut.removed, est[:, 0], est[:, 1], est[:, 2], (est[:, 3], est[:, 4], est[:, 5]), offset
    )
    outage = outages.window_index(t_fix, windows, offset)
    calib = calibration(calibration_columns(d_east, d_north, eph, bound_east, bound_north, outage)[outage >= 0])
    truth_errors = np.zeros(0)
    if rec.truth is not None and len(est):
        inside = interval_index(est[:, 0], windows) >= 0
        en = rec.frame.to_enu(est[inside, 1], est[inside, 2])
        at = rec.truth.at(est[inside, 0])
        truth_errors = np.hypot(en[:, 0] - at.east, en[:, 1] - at.north)
    shares = outages.mode_shares(modes.elements())
    return RunOutcome(errors, per_outage, truth_errors, shares, rec.span_s, wall, offset, calib)


def _row(est: Estimate) -> tuple[float, ...]:
    """What the bench keeps of an estimate: time, latitude, longitude, eph, bound half-widths (NaN: none)."""
    eph = est.error.eph_m if est.error is not None else math.nan
    be = est.bound_east_m if est.bound_east_m is not None else math.nan
    bn = est.bound_north_m if est.bound_north_m is not None else math.nan
    return est.t, est.lat_deg, est.lon_deg, eph, be, bn


@dataclass(frozen=True)
class LengthResult:
    """One length on one drive: the outages placed, each estimator's outcome (or its failure), each floor's errors
    (m, one array per outage) against the removed fixes and, on a simulated drive, against the true antenna (else
    empty)."""

    length_s: float
    windows: list[tuple[float, float]]
    runs: dict[str, RunOutcome | str]
    floors: dict[str, list[np.ndarray]]
    floors_truth: dict[str, list[np.ndarray]]


def floor_errors(
    rec: Recording, windows: Sequence[tuple[float, float]]
) -> tuple[dict[str, list[np.ndarray]], dict[str, list[np.ndarray]]]:
    """Both floors' errors (m) at the fixes inside each of ``windows`` (NaN-free; one array per window, empty
    where it has no fix): against the removed fixes, and against the true antenna at their times where the drive
    is simulated (else no entries)."""
    scored = (False, True) if rec.truth is not None and rec.sim is not None else (False,)
    out: dict[bool, dict[str, list[np.ndarray]]] = {key: {name: [] for name in FLOORS} for key in scored}
    f = rec.fixes
    for a, b in windows:
        inside = (f.t >= a) & (f.t < b)
        t_eval = f.t[inside]
        if not len(t_eval):
            for by_name in out.values():
                for parts in by_name.values():
                    parts.append(np.zeros(0))
            continue
        refs = {False: np.column_stack([f.east[inside], f.north[inside]])}
        if True in scored:
            assert rec.truth is not None and rec.sim is not None
            refs[True] = true_antenna(rec.truth, t_eval, rec.sim)
        for name, floor in zip(FLOORS, (plain_floor, calibrated_floor), strict=True):
            pos = floor(rec.track, f, a, t_eval)
            for key, ref in refs.items():
                err = np.hypot(*(pos - ref).T)
                out[key][name].append(err[np.isfinite(err)])
    return out[False], out.get(True, {})


def run_recording(
    rec: Recording, bs: RecordedBenchSettings, progress: Callable[[str], None] | None = None
) -> list[LengthResult]:
    """Every length on one drive: the floors, then every estimator (each run isolated)."""
    say = progress or (lambda _msg: None)
    results = []
    for length in bs.lengths_s:
        windows = place_outages(rec, length, bs)
        runs: dict[str, RunOutcome | str] = {}
        for name in bs.names():
            say(f"{rec.name}: {len(windows)} outages of {length:g} s, {name}")
            try:
                runs[name] = call_isolated(lambda n=name, w=windows: run_estimator(n, rec, w), bs.timeout_s)
            except BenchRunError as e:
                runs[name] = str(e)
        results.append(LengthResult(length, windows, runs, *floor_errors(rec, windows)))
    return results


def summary(rec: Recording, results: Sequence[LengthResult]) -> dict[str, Any]:
    """Plain data (JSON-ready; NaN as None) of one drive's results."""

    def stats(values: np.ndarray) -> dict[str, float | int | None]:
        return {"n": int(values.size), **_stats3(*mean_p95_max(values))}

    def per_outage(starts: list[float], errors: Sequence[outages.OutageErrors]) -> list[dict[str, Any]]:
        return [
            {"start_s": start, "n": e.scored, "mean_m": _finite(e.mean_m), "max_m": _finite(e.max_m)}
            for start, e in zip(starts, errors, strict=True)
        ]

    lengths = []
    for r in results:
        starts = [round(a - rec.t0, 1) for a, _ in r.windows]
        rows: dict[str, Any] = {}
        for name, run in r.runs.items():
            if isinstance(run, str):
                rows[name] = {"failed": run}
                continue
            e = run.fix_errors
            rows[name] = {
                "fixes": {
                    "n": e.scored,
                    "mean_m": _finite(e.mean_m),
                    "p95_m": _finite(e.p95_m),
                    "max_m": _finite(e.max_m),
                },
                "truth": stats(run.truth_errors) if rec.truth is not None else None,
                "widened_share": _finite(run.shares.widened_share),
                "failed_share": _finite(run.shares.failed_share),
                "x_real_time": run.span_s / run.wall_s if run.wall_s > 0 else None,
                "gps_time_offset_s": run.offset_s,
                "calibration": {k: _finite(float(v)) for k, v in run.calibration.items()},
                "outages": per_outage(starts, run.per_outage),
            }
        for name, parts in r.floors.items():
            truth_parts = r.floors_truth.get(name)
            rows[name] = {
                "fixes": stats(_pooled(parts)),
                "truth": stats(_pooled(truth_parts)) if truth_parts is not None else None,
                "outages": per_outage(
                    starts, [outages.outage_stats(a, b, e) for (a, b), e in zip(r.windows, parts, strict=True)]
                ),
            }
        lengths.append({"length_s": r.length_s, "outages": starts, "rows": rows})
    return {"drive": rec.name, "config": rec.config.source, "span_s": rec.span_s, "lengths": lengths}


def _pooled(parts: Sequence[np.ndarray]) -> np.ndarray:
    """Errors of every outage in one array."""
    return np.concatenate(parts) if len(parts) else np.zeros(0)


def _stats3(mean: float, p95: float, mx: float) -> dict[str, float | None]:
    return {"mean_m": _finite(mean), "p95_m": _finite(p95), "max_m": _finite(mx)}


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _num(value: float | None, fmt: str = ".2f") -> str:
    return "–" if value is None else format(value, fmt)


def markdown(data: dict[str, Any]) -> list[str]:
    """One table per outage length: rows are the estimators and the floors."""
    lines = [f"## {data['drive']} ({data['span_s']:.0f} s, config {data['config']})", ""]
    truth = any(row.get("truth") for length in data["lengths"] for row in length["rows"].values())
    for length in data["lengths"]:
        lines.append(
            f"{len(length['outages'])} outages of {length['length_s']:g} s, starting at "
            + ", ".join(f"{s:g}" for s in length["outages"])
            + " s (from the first CAN frame)"
        )
        lines.append("")
        head = ["estimator", "vs removed fixes: mean / p95 / max (m)", "fixes scored"]
        head += ["vs truth: mean / p95 / max (m)"] if truth else []
        head += ["widened", "solver failures", "x real time", "GNSS time offset (s)"]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for name, row in length["rows"].items():
            if "failed" in row:
                lines.append(f"| `{name}` | failed: {row['failed']} |" + " |" * (len(head) - 2))
                continue
            f = row["fixes"]
            cells = [f"`{name}`" if not name.startswith("floor") else name]
            cells += [" / ".join(_num(f[k]) for k in ("mean_m", "p95_m", "max_m")), str(f["n"])]
            if truth:
                t = row.get("truth")
                cells.append(" / ".join(_num(t[k]) for k in ("mean_m", "p95_m", "max_m")) if t else "–")
            if "widened_share" in row:
                cells += [
                    _num(100 * row["widened_share"] if row["widened_share"] is not None else None, ".1f") + " %",
                    _num(100 * row["failed_share"] if row["failed_share"] is not None else None, ".1f") + " %",
                    _num(row["x_real_time"], ".0f"),
                    _num(row["gps_time_offset_s"], "+.3f"),
                ]
            else:
                cells += ["–", "–", "–", "–"]
            lines.append("| " + " | ".join(cells) + " |")
        lines += ["", *calibration_lines(length["rows"]), "", *outage_lines(length), ""]
    return lines


def outage_lines(length: dict[str, Any]) -> list[str]:
    """Each outage's errors against its removed fixes, mean / max (m), for every estimator and floor (Markdown)."""
    names = [name for name, row in length["rows"].items() if "outages" in row]
    head = ["outage start (s)", *(f"`{n}`" if not n.startswith("floor") else n for n in names)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, start in enumerate(length["outages"]):
        cells = [f"{start:g}"]
        for name in names:
            e = length["rows"][name]["outages"][i]
            cells.append(f"{_num(e['mean_m'])} / {_num(e['max_m'])}")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def calibration_lines(rows: dict[str, Any]) -> list[str]:
    """The estimators' error estimates and bound boxes against the removed fixes (Markdown)."""
    head = [
        "estimator",
        "removed fix within eph [90 % interval over outages]",
        "median eph / median error (m)",
        "removed fix in bound box",
        "median box half-width (m)",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, row in rows.items():
        if "calibration" in row:
            lines.append("| " + " | ".join([f"`{name}`", *calibration_cells(row["calibration"])]) + " |")
    return lines
