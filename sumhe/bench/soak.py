"""A day of data in bounded memory: a long simulated drive replayed with its memory printed as it goes.

The simulator makes drives of at most an hour (its ``duration_s`` cap keeps one drive's arrays in memory), so a
long drive is chained from hour-long segments, each written as the files of a logger that starts a new file
every hour (``hourNN/drive.log`` + ``drive.nmea``): segment k starts where and when segment k-1 ended (its
datum is the last true position, its start time one hour later; a new seed gives a new route from there, so the
heading jumps once an hour, as after a stop). The segments stay on disk (``--dir``) and are reused by the next
run. The replay reads them as one multi-file drive (:class:`~sumhe.io.replay.RecordedDrive`) through
:func:`~sumhe.bench.reprocess.replay_drive`, writing the estimates to the null device (the JSON is made and
written all the same), and reads the process's resident memory (RSS) after every simulated hour of data.

Memory figures: RSS from ``/proc/self/statm`` (Linux), peak from ``getrusage`` (the process's high-water mark).
"""

from __future__ import annotations

import math
import os
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from sumhe.bench.reprocess import CAN_INPUTS, DriveSummary, replay_drive
from sumhe.estimator.registry import make_estimator
from sumhe.io.can import reference_config
from sumhe.io.replay import RecordedDrive
from sumhe.sim import SimSettings, load_settings, simulate, write_drive
from sumhe.sim.settings import START_UNIX_S

SEGMENT_S = 3600.0
"""One segment: the simulator's longest drive."""


def rss_mb() -> float:
    """The resident memory of this process now (MB; NaN where ``/proc`` is missing)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return math.nan
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def peak_rss_mb() -> float:
    """The most resident memory this process has had (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def segment_settings(hour: int, seed: int, datum: tuple[float, float], segment_s: float = SEGMENT_S) -> SimSettings:
    """Segment ``hour`` of a chained drive: ``segment_s`` from ``START_UNIX_S + hour * segment_s`` at ``datum``
    (lat, lon)."""
    return SimSettings(
        seed=seed + hour,
        duration_s=segment_s,
        start_unix_s=START_UNIX_S + hour * segment_s,
        datum_lat_deg=datum[0],
        datum_lon_deg=datum[1],
        truth_rate_hz=10.0,
    )


def chained_drive(
    directory: Path,
    hours: int,
    seed: int = 0,
    say: Callable[[str], None] = lambda _: None,
    segment_s: float = SEGMENT_S,
) -> tuple[list[Path], list[Path]]:
    """Write (or reuse) the ``hours`` segments (of ``segment_s``) of a chained drive in ``directory``; its CAN and
    NMEA logs."""
    datum = (SimSettings().datum_lat_deg, SimSettings().datum_lon_deg)
    can_logs, nmea_logs = [], []
    for hour in range(hours):
        folder = directory / f"hour{hour:02d}"
        settings = segment_settings(hour, seed, datum, segment_s)
        done = folder / "scenario.toml"
        if not (done.is_file() and load_settings(done) == settings):
            started = time.perf_counter()
            drive = simulate(settings)
            write_drive(drive, folder)
            say(f"soak: simulated hour {hour + 1} of {hours} in {time.perf_counter() - started:.0f} s")
            end = (float(drive.truth.lat[-1]), float(drive.truth.lon[-1]))
        else:
            end = _last_position(folder / "truth.csv")
        datum = end
        can_logs.append(folder / "drive.log")
        nmea_logs.append(folder / "drive.nmea")
    return can_logs, nmea_logs


def _last_position(truth_csv: Path) -> tuple[float, float]:
    """Latitude and longitude of the last row of a ``truth.csv`` (read from its tail only)."""
    with truth_csv.open("rb") as f:
        f.seek(max(0, truth_csv.stat().st_size - 4096))
        last = f.read().decode().strip().splitlines()[-1].split(",")
    header = truth_csv.open(encoding="utf-8").readline().strip().split(",")
    return float(last[header.index("lat")]), float(last[header.index("lon")])


@dataclass(frozen=True, slots=True)
class MemoryPoint:
    """Memory after ``data_s`` seconds of data: RSS now and the peak so far (MB), wall time so far (s)."""

    data_s: float
    rss_mb: float
    peak_mb: float
    wall_s: float


@dataclass(frozen=True)
class SoakResult:
    """The replay's summary and its memory, read every ``every_s`` seconds of data and at the end."""

    summary: DriveSummary
    points: Sequence[MemoryPoint]
    every_s: float

    @property
    def growth_after_first_hour(self) -> float:
        """RSS at the end over RSS after the first ``every_s`` of data, minus 1 (NaN with less than two points)."""
        after = [p for p in self.points if p.data_s >= self.every_s]
        if len(after) < 2:
            return math.nan
        return after[-1].rss_mb / after[0].rss_mb - 1.0


def soak_replay(
    can_logs: Sequence[Path],
    nmea_logs: Sequence[Path],
    estimator: str,
    say: Callable[[str], None] = lambda _: None,
    every_s: float = SEGMENT_S,
) -> SoakResult:
    """Replay the drive, reading the memory every ``every_s`` seconds of data."""
    config = reference_config()
    drive = RecordedDrive(config, can_logs, nmea_logs, quantities=CAN_INPUTS)
    est = make_estimator(estimator, drive.config)
    points: list[MemoryPoint] = []
    started = time.perf_counter()
    next_at = every_s

    def progress(data_s: float) -> None:
        nonlocal next_at
        if data_s >= next_at or not points:
            point = MemoryPoint(data_s, rss_mb(), peak_rss_mb(), time.perf_counter() - started)
            points.append(point)
            say(
                f"soak: {point.data_s / 3600:5.2f} h of data: RSS {point.rss_mb:6.1f} MB, peak {point.peak_mb:6.1f}"
                f" MB, {point.wall_s:6.0f} s ({point.data_s / max(point.wall_s, 1e-9):.0f}x real time)"
            )
            if data_s >= next_at:
                next_at += every_s

    with open(os.devnull, "w", encoding="utf-8") as out:
        summary = replay_drive(drive, est, out=out, progress=progress)
    end = MemoryPoint(summary.span_s, rss_mb(), peak_rss_mb(), time.perf_counter() - started)
    return SoakResult(summary, [*points, end], every_s)


def format_result(result: SoakResult) -> list[str]:
    s, last = result.summary, result.points[-1]
    return [
        f"soak: {s.estimator}: {s.span_s / 3600:.2f} h of data, {s.estimates} estimates in {s.wall_s:.0f} s "
        f"({s.speed:.0f}x real time); RSS {last.rss_mb:.1f} MB at the end, peak {last.peak_mb:.1f} MB, growth after "
        f"the first hour {100 * result.growth_after_first_hour:+.1f} %",
        *s.lines(),
    ]
