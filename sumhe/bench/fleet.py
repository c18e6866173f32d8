"""Fleet reprocessing without the scheduler: drives, tasks, the worker that runs them, and the summary table.

A drive is a folder holding one drive's logs: CAN logs (``*.log`` candump, ``*.mf4``, ``*.asc``, ``*.blf``,
``*.trc``, optionally gzipped), NMEA logs (``*.nmea``; a simulated second antenna's ``drive2.nmea`` is left out),
its config override ``config.toml`` (merged over the fleet's config, key by key) and an optional ``truth.csv``.
A manifest (a text file given instead of a folder) lists drives one a line: a folder, or the files of one drive
separated by blanks (relative to the manifest); ``#`` starts a comment.

One :class:`Task` is one drive through one estimator. :class:`FleetWorker` runs tasks one after the other,
keeping each estimator it builds and resetting it for the next drive (a solver built once serves a worker's
whole share of the fleet); a task never raises: a failing drive gives a record with its reason. Each task writes
``OUT/<drive>/<estimator>.jsonl`` (the estimates, as ``sumhe replay`` writes them) and, last, its record
``OUT/<drive>/<estimator>.json`` (:meth:`DriveSummary.to_json` plus the task's names): a task whose record says
``ok`` is finished and skipped when the fleet runs again. ``sumhe fleet`` (:mod:`sumhe.commands.fleet`) runs the
workers as Ray actors; :func:`run_local` runs them here, in order.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import os
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sumhe.bench.reprocess import replay_drive
from sumhe.config import Config, load_config
from sumhe.errors import ConfigError, SumheError
from sumhe.estimator.base import Estimator
from sumhe.estimator.registry import make_estimator
from sumhe.frontend.can import CAN_USED
from sumhe.io.can import reference_config
from sumhe.io.replay import RecordedDrive, check_gps_source
from sumhe.sim.drive import SECOND_ANTENNA_FILE
from sumhe.sim.truth import load_truth

log = logging.getLogger(__name__)

CAN_LOG_SUFFIXES = (".log", ".mf4", ".asc", ".blf", ".trc")
"""CAN log formats a drive folder's files are recognised by (each also ``.gz``, but ``.mf4``)."""
NMEA_SUFFIX = ".nmea"
DRIVE_CONFIG = "config.toml"
TRUTH_FILE = "truth.csv"
MAX_CACHED_ESTIMATORS = 4
"""Estimators a worker keeps for reuse (one per estimator name and settings; the oldest goes first)."""


@dataclass(frozen=True)
class DriveSpec:
    """One drive's files: ``name`` (unique in the fleet: the output folder), CAN and NMEA logs, the config
    override and the truth (None when absent)."""

    name: str
    can_logs: tuple[str, ...]
    nmea_logs: tuple[str, ...] = ()
    config: str | None = None
    truth: str | None = None

    @property
    def size(self) -> int:
        """Bytes of its logs (the longest drives are handed out first)."""
        return sum(os.path.getsize(p) for p in (*self.can_logs, *self.nmea_logs) if os.path.isfile(p))


def _is_can_log(path: Path) -> bool:
    name = path.name.lower()
    return name.endswith(CAN_LOG_SUFFIXES) or name.endswith(tuple(s + ".gz" for s in CAN_LOG_SUFFIXES if s != ".mf4"))


def drive_from_files(paths: Iterable[Path], name: str) -> DriveSpec:
    """The drive of these files, sorted into logs, config and truth by name (see the module docstring)."""
    files = sorted(paths)
    return DriveSpec(
        name=name,
        can_logs=tuple(str(p) for p in files if _is_can_log(p)),
        nmea_logs=tuple(str(p) for p in files if p.suffix.lower() == NMEA_SUFFIX and p.name != SECOND_ANTENNA_FILE),
        config=next((str(p) for p in files if p.name == DRIVE_CONFIG), None),
        truth=next((str(p) for p in files if p.name == TRUTH_FILE), None),
    )


def drive_from_folder(folder: Path, name: str | None = None) -> DriveSpec:
    """The drive in ``folder`` (its files, not its subfolders)."""
    return drive_from_files((p for p in folder.iterdir() if p.is_file()), name or folder.name)


def find_drives(arguments: Sequence[str | os.PathLike[str]]) -> list[DriveSpec]:
    """The drives of the command line: folders, and manifests (files listing drives); names made unique by a
    ``-2``, ``-3``, ... suffix. ConfigError for a path that does not exist or a manifest line naming none."""
    found: list[DriveSpec] = []
    for arg in arguments:
        path = Path(arg)
        if path.is_dir():
            found.append(drive_from_folder(path))
        elif path.is_file():
            found += _manifest(path)
        else:
            raise ConfigError(f"{path}: no such drive folder or manifest")
    seen: dict[str, int] = {}
    out = []
    for spec in found:
        n = seen[spec.name] = seen.get(spec.name, 0) + 1
        out.append(spec if n == 1 else dataclasses.replace(spec, name=f"{spec.name}-{n}"))
    return out


def _manifest(path: Path) -> list[DriveSpec]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the manifest: {e}") from e
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        paths = [p if p.is_absolute() else path.parent / p for p in map(Path, words)]
        missing = [str(p) for p in paths if not p.exists()]
        if missing:
            raise ConfigError(f"{path}:{n}: not found: {', '.join(missing)}")
        if len(paths) == 1 and paths[0].is_dir():
            out.append(drive_from_folder(paths[0]))
        else:
            out.append(drive_from_files(paths, paths[0].parent.name or paths[0].stem))
    return out


@dataclass(frozen=True)
class Task:
    """One drive through one estimator, with the fleet's config (``base_config``, a TOML file or None for the
    defaults), outages (``(start_s, length_s)`` from each drive's first frame) and output folder."""

    drive: DriveSpec
    estimator: str
    base_config: str | None
    outages: tuple[tuple[float, float], ...]
    out_dir: str

    @property
    def folder(self) -> Path:
        return Path(self.out_dir) / _safe(self.drive.name)

    @property
    def estimates_path(self) -> Path:
        return self.folder / f"{_safe(self.estimator)}.jsonl"

    @property
    def record_path(self) -> Path:
        return self.folder / f"{_safe(self.estimator)}.json"

    def config(self) -> Config:
        """The fleet's config with the drive's override merged over it; neither: the reference vehicle's (as
        ``sumhe replay`` without ``--config``)."""
        layers = [self.drive.config] if self.drive.config else []
        if self.base_config is None and not layers:
            return reference_config()
        return load_config(self.base_config, layers=layers)


def _safe(name: str) -> str:
    """A name usable as one file name."""
    return re.sub(r"[^A-Za-z0-9._+-]", "_", name) or "_"


def read_record(task: Task) -> dict[str, Any] | None:
    """The record a task wrote, None when there is none (or it is unreadable: the task runs again)."""
    try:
        record: dict[str, Any] = json.loads(task.record_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record


def finished(task: Task) -> bool:
    """Whether the task ran to the end before (its record says ``ok``)."""
    record = read_record(task)
    return record is not None and record.get("status") == "ok"


def failure_record(task: Task, reason: str) -> dict[str, Any]:
    """The record of a task that failed."""
    return {"drive": task.drive.name, "estimator": task.estimator, "status": "failed", "reason": reason}


def write_record(task: Task, record: Mapping[str, Any]) -> None:
    """Write the task's record (atomically: a record on disk is always whole)."""
    task.folder.mkdir(parents=True, exist_ok=True)
    tmp = task.record_path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    tmp.replace(task.record_path)


class FleetWorker:
    """Runs tasks, reusing the estimators it has built (``reset()`` between drives). One per process: a Ray actor
    in ``sumhe fleet``, or :func:`run_local`."""

    def __init__(self) -> None:
        self._estimators: list[tuple[str, Config, Estimator]] = []
        self.built = 0

    def run(self, task: Task) -> dict[str, Any]:
        """Run one task and write its estimates and record; the record (status ``ok`` or ``failed`` with the
        reason). Never raises for a bad drive."""
        try:
            record = self._run(task)
        except (SumheError, OSError, ValueError) as e:
            record = failure_record(task, str(e))
        except Exception as e:  # a drive that breaks a decoder or estimator must not stop the fleet
            log.exception("%s / %s failed", task.drive.name, task.estimator)
            record = failure_record(task, f"{type(e).__name__}: {e}")
        try:
            write_record(task, record)
        except OSError as e:
            record = failure_record(task, f"cannot write {task.record_path}: {e}")
        return record

    def _run(self, task: Task) -> dict[str, Any]:
        spec = task.drive
        if not spec.can_logs and not spec.nmea_logs:
            raise ConfigError(f"{spec.name}: no CAN or NMEA logs")
        config = task.config()
        nmea = spec.nmea_logs if config.gps.source == "nmea" else ()
        check_gps_source(config, nmea)
        truth = load_truth(spec.truth) if spec.truth else None
        drive = RecordedDrive(config, spec.can_logs, nmea, quantities=CAN_USED)
        estimator = self.estimator(task.estimator, drive.config)
        task.folder.mkdir(parents=True, exist_ok=True)
        tmp = task.estimates_path.with_suffix(".jsonl.tmp")
        with tmp.open("w", encoding="utf-8") as out:
            summary = replay_drive(drive, estimator, task.outages, out, truth)
        tmp.replace(task.estimates_path)
        return {"drive": spec.name, "estimator": task.estimator, "status": "ok", "reason": "", **summary.to_json()}

    def estimator(self, name: str, config: Config) -> Estimator:
        """The estimator ``name`` for ``config``: a kept one, reset, when one was built for the same settings
        (everything but where the files are: drives of one car share it), else a new one."""
        key = dataclasses.replace(config, source="", base_dir=Path("."), log_dirs=())
        for i, (n, k, estimator) in enumerate(self._estimators):
            if n == name and k == key:
                self._estimators.append(self._estimators.pop(i))
                estimator.reset()
                return estimator
        estimator = make_estimator(name, config)
        self.built += 1
        self._estimators = [*self._estimators, (name, key, estimator)][-MAX_CACHED_ESTIMATORS:]
        return estimator


def make_tasks(
    drives: Sequence[DriveSpec],
    estimators: Sequence[str],
    base_config: str | None,
    outages: Sequence[tuple[float, float]],
    out_dir: str | os.PathLike[str],
) -> list[Task]:
    """One task per drive and estimator, the biggest drives first."""
    ordered = sorted(drives, key=lambda d: -d.size)
    return [Task(d, e, base_config, tuple(outages), str(out_dir)) for d in ordered for e in estimators]


def run_local(tasks: Iterable[Task], done: Callable[[dict[str, Any]], None] | None = None) -> list[dict[str, Any]]:
    """Run the tasks here, one after the other, with one worker (no Ray)."""
    worker = FleetWorker()
    out = []
    for task in tasks:
        out.append(worker.run(task))
        if done is not None:
            done(out[-1])
    return out


COLUMNS: tuple[tuple[str, str], ...] = (
    ("drive", "drive"),
    ("estimator", "estimator"),
    ("status", "status"),
    ("duration_s", "duration s"),
    ("distance_km", "km"),
    ("fixes_used", "fixes used"),
    ("outages", "outages"),
    ("outage_mean_m", "outage mean m"),
    ("outage_max_m", "outage max m"),
    ("truth_mean_m", "truth mean m"),
    ("truth_p95_m", "truth p95 m"),
    ("truth_max_m", "truth max m"),
    ("widened_pct", "widened %"),
    ("failed_pct", "solver fail %"),
    ("solve_p50_ms", "solve p50 ms"),
    ("solve_p99_ms", "solve p99 ms"),
    ("speed_x", "x real time"),
    ("reason", "failure reason"),
)
"""The fleet summary table: (key, heading)."""


def table_row(record: Mapping[str, Any]) -> dict[str, Any]:
    """One line of the fleet summary table from a task's record (None where a value does not apply)."""
    outages_all = record.get("outages_all") or {}
    truth = record.get("truth") or {}
    modes = record.get("modes") or {}
    epochs = modes.get("epochs") or 0
    distance = record.get("distance_m")
    return {
        "drive": record.get("drive"),
        "estimator": record.get("estimator"),
        "status": record.get("status"),
        "duration_s": record.get("span_s"),
        "distance_km": None if distance is None else distance / 1000.0,
        "fixes_used": record.get("fixes_used"),
        "outages": len(record.get("outages") or []),
        "outage_mean_m": outages_all.get("mean_m"),
        "outage_max_m": outages_all.get("max_m"),
        "truth_mean_m": truth.get("mean_m"),
        "truth_p95_m": truth.get("p95_m"),
        "truth_max_m": truth.get("max_m"),
        "widened_pct": 100.0 * modes["widened"] / epochs if epochs else None,
        "failed_pct": 100.0 * modes["failed"] / epochs if epochs else None,
        "solve_p50_ms": record.get("solve_p50_ms"),
        "solve_p99_ms": record.get("solve_p99_ms"),
        "speed_x": record.get("speed"),
        "reason": record.get("reason") or "",
    }


def _cell(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 100 else f"{value:.0f}"
    return str(value)


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The summary table as aligned text."""
    cells = [[heading for _, heading in COLUMNS]] + [[_cell(row[key]) for key, _ in COLUMNS] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(COLUMNS))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in cells)


def write_table(rows: Sequence[Mapping[str, Any]], path: Path) -> None:
    """The summary table as CSV (empty cells where a value does not apply)."""
    with path.open("w", encoding="utf-8", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[key for key, _ in COLUMNS])
        writer.writeheader()
        for row in rows:
            writer.writerow({k: "" if v is None else v for k, v in row.items()})
