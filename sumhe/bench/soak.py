"""A day of data in bounded memory: a long simulated drive replayed with its memory printed as it goes.

The simulator makes drives of at most an hour (its ``duration_s`` cap keeps one drive's arrays in memory), so a long
drive is chained from hour-long segments, each written as the files of a logger that starts a new file every hour
(``hourNN/drive.log`` + ``drive.nmea``): segment k starts where and when segment k-1 ended (its datum is the last
true position, its start one second after the previous end, :data:`GAP_S`; a new seed gives a new route from there,
so the heading jumps once an hour, as after a stop). The segments stay on disk (``--dir``) and are reused by the
next run. The replay reads them as one multi-file drive (:class:`~sumhe.io.replay.RecordedDrive`) through
:func:`~sumhe.bench.reprocess.replay_drive`, writing the estimates to the null device (the JSON is made and written
all the same), and reads the process's resident memory (RSS) after every simulated hour of data. :func:`soak_daemon`
feeds the same drive to the daemon's service instead, paced faster than real time.

Memory figures: RSS from ``/proc/self/statm`` (Linux), peak from ``getrusage`` (the process's high-water mark).
"""

from __future__ import annotations

import asyncio
import dataclasses
import gc
import itertools
import json
import math
import os
import resource
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sumhe.bench.reprocess import DriveSummary, replay_drive
from sumhe.config import OutputSettings
from sumhe.estimator.registry import make_estimator
from sumhe.frontend.can import CAN_USED
from sumhe.io.can import reference_config
from sumhe.io.replay import RecordedDrive
from sumhe.messages import Sample
from sumhe.service.app import Service
from sumhe.sim import SimSettings, load_settings, simulate, write_drive
from sumhe.sim.settings import START_UNIX_S

SEGMENT_S = 3600.0
"""One segment: the simulator's longest drive."""
GAP_S = 1.0
"""Between segments (a logger opening its next file): the first epoch of a segment never repeats the last one's."""


def rss_mb() -> float:
    """The resident memory of this process now (MB; NaN where ``/proc`` is missing)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return math.nan
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def peak_rss_mb() -> float:
    """The most resident memory this process has had (MB; Linux counts it in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6


def segment_settings(hour: int, seed: int, datum: tuple[float, float], segment_s: float = SEGMENT_S) -> SimSettings:
    """Segment ``hour`` of a chained drive: ``segment_s`` from ``START_UNIX_S + hour * (segment_s + GAP_S)`` at
    ``datum`` (lat, lon)."""
    return SimSettings(
        seed=seed + hour,
        duration_s=segment_s,
        start_unix_s=START_UNIX_S + hour * (segment_s + GAP_S),
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
            write_drive(simulate(settings), folder)
            say(f"soak: simulated hour {hour + 1} of {hours} in {time.perf_counter() - started:.0f} s")
        datum = _last_position(folder / "truth.csv")  # as written: a second run finds the same settings
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
    """Memory after ``data_s`` seconds of data: RSS now and the peak so far (MB), wall time so far (s), and the
    objects the cyclic garbage collector tracks (``tracked``: outside the frozen generation, what its collections
    traverse; :mod:`sumhe.service.collector`)."""

    data_s: float
    rss_mb: float
    peak_mb: float
    wall_s: float
    tracked: int


def memory_point(data_s: float, wall_s: float) -> MemoryPoint:
    """The memory now, after ``data_s`` seconds of data and ``wall_s`` of wall time."""
    return MemoryPoint(data_s, rss_mb(), peak_rss_mb(), wall_s, len(gc.get_objects()))


@dataclass(frozen=True)
class SoakResult:
    """The replay's summary and its memory, read every ``every_s`` seconds of data and at the end."""

    summary: DriveSummary
    points: Sequence[MemoryPoint]
    every_s: float

    @property
    def growth_after_first_hour(self) -> float:
        """RSS at the end over RSS after the first ``every_s`` of data, minus 1 (NaN with less than two points)."""
        return growth(self.points, self.every_s)


def soak_replay(
    can_logs: Sequence[Path],
    nmea_logs: Sequence[Path],
    estimator: str,
    say: Callable[[str], None] = lambda _: None,
    every_s: float = SEGMENT_S,
) -> SoakResult:
    """Replay the drive, reading the memory every ``every_s`` seconds of data."""
    config = reference_config()
    drive = RecordedDrive(config, can_logs, nmea_logs, quantities=CAN_USED)
    est = make_estimator(estimator, drive.config)
    points: list[MemoryPoint] = []
    started = time.perf_counter()
    next_at = every_s

    def progress(data_s: float) -> None:
        nonlocal next_at
        if data_s >= next_at or not points:
            point = memory_point(data_s, time.perf_counter() - started)
            points.append(point)
            say(
                f"soak: {point.data_s / 3600:5.2f} h of data: RSS {point.rss_mb:6.1f} MB, peak {point.peak_mb:6.1f}"
                f" MB, {point.tracked} objects tracked by the collector, {point.wall_s:6.0f} s "
                f"({point.data_s / max(point.wall_s, 1e-9):.0f}x real time)"
            )
            if data_s >= next_at:
                next_at += every_s

    with open(os.devnull, "w", encoding="utf-8") as out:
        summary = replay_drive(drive, est, out=out, progress=progress)
    end = memory_point(summary.span_s, time.perf_counter() - started)
    return SoakResult(summary, [*points, end], every_s)


def growth(points: Sequence[MemoryPoint], after_s: float) -> float:
    """RSS at the last point over RSS at the first point from ``after_s`` of data on, minus 1 (NaN with fewer
    than two such points)."""
    later = [p for p in points if p.data_s >= after_s]
    return later[-1].rss_mb / later[0].rss_mb - 1.0 if len(later) >= 2 else math.nan


def format_daemon(status: dict[str, Any], points: Sequence[MemoryPoint], received: int) -> str:
    last = points[-1]
    first_part = points[-1].data_s / 12.0
    return (
        f"soak daemon: {last.data_s / 3600:.2f} h of data in {last.wall_s:.0f} s; {status['estimates']} estimates, "
        f"{received} datagrams received; RSS {last.rss_mb:.1f} MB at the end, peak {last.peak_mb:.1f} MB, growth "
        f"after the first twelfth {100 * growth(points, first_part):+.1f} %; objects tracked by the collector "
        f"{points[0].tracked} at the start, {last.tracked} at the end; status: {json.dumps(status)}"
    )


def format_result(result: SoakResult) -> list[str]:
    s, last = result.summary, result.points[-1]
    return [
        f"soak: {s.estimator}: {s.span_s / 3600:.2f} h of data, {s.estimates} estimates in {s.wall_s:.0f} s "
        f"({s.speed:.0f}x real time); RSS {last.rss_mb:.1f} MB at the end, peak {last.peak_mb:.1f} MB, growth after "
        f"the first hour {100 * result.growth_after_first_hour:+.1f} %; objects tracked by the collector "
        f"{result.points[0].tracked} at the start, {last.tracked} at the end",
        *s.lines(),
    ]


class _Counter(asyncio.DatagramProtocol):
    """Counts the datagrams the daemon sends (a UDP client on 127.0.0.1)."""

    def __init__(self) -> None:
        self.received = 0

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.received += 1


@dataclass
class _SourceStats:
    samples: int = 0
    last_t: float = math.nan


class _Paced:
    """The drive's samples at their times on the scaled service clock (waiting for each), counted; ``ended``
    once they are all given."""

    def __init__(self, samples: Iterator[Sample], clock: Callable[[], float], speed: float) -> None:
        self.samples, self.clock, self.speed = samples, clock, speed
        self.ended, self.stats = False, _SourceStats()

    def __aiter__(self) -> _Paced:
        return self

    async def __anext__(self) -> Sample:
        sample = next(self.samples, None)
        if sample is None:
            self.ended = True
            raise StopAsyncIteration
        await asyncio.sleep(max((sample.t - self.clock()) / self.speed, 0.0))
        self.stats.samples += 1
        self.stats.last_t = sample.t
        return sample


async def soak_daemon(
    can_logs: Sequence[Path],
    nmea_logs: Sequence[Path],
    estimator: str,
    speed: float,
    say: Callable[[str], None] = lambda _: None,
    every_s: float = 300.0,
) -> tuple[dict[str, Any], list[MemoryPoint], int]:
    """The daemon's service (:class:`~sumhe.service.app.Service`: inbox, estimator in a worker thread,
    UDP JSON output to a client on 127.0.0.1) fed by the drive's samples paced at ``speed`` times real time on one
    scaled service clock (as ``sumhe demo``), its memory read every ``every_s`` seconds of data. The fixes come
    stamped (with the reference config's ``gps.time = "utc"`` the service's stamping leaves them as they are).
    Returns the final status, the memory points and the datagrams received."""
    loop = asyncio.get_running_loop()
    transport, counter = await loop.create_datagram_endpoint(_Counter, local_addr=("127.0.0.1", 0))
    try:
        port = transport.get_extra_info("sockname")[1]
        config = dataclasses.replace(
            reference_config(), output=OutputSettings(json=(f"127.0.0.1:{port}",), status_interval_s=60.0)
        )
        samples = iter(RecordedDrive(config, can_logs, nmea_logs, quantities=CAN_USED).samples())
        head = next(samples, None)
        if head is None:
            raise ValueError(f"soak daemon: no usable sample in {', '.join(map(str, [*can_logs, *nmea_logs]))}")
        running = make_estimator(estimator, config)
    except BaseException:
        transport.close()  # a bad drive or estimator name: no socket left open
        raise
    first, wall0 = head.t, time.time()

    def clock() -> float:
        return first + (time.time() - wall0) * speed

    source = _Paced(itertools.chain([head], samples), clock, speed)
    service = Service(config, running, {"drive": source}, clock=clock, clock_rate=speed)
    stop = asyncio.Event()
    task = asyncio.create_task(service.run(stop))
    points: list[MemoryPoint] = []
    next_at = 0.0
    try:
        while not source.ended and not task.done():
            await asyncio.sleep(0.5)
            data_s = clock() - first
            if data_s >= next_at and not task.done():  # the service's memory while it runs
                point = memory_point(data_s, time.time() - wall0)
                points.append(point)
                say(
                    f"soak daemon: {data_s / 3600:5.2f} h of data: RSS {point.rss_mb:6.1f} MB, peak "
                    f"{point.peak_mb:6.1f} MB, {point.tracked} objects tracked by the collector, "
                    f"{service.pipeline.stats.estimates} estimates, {counter.received} datagrams received"
                )
                next_at += every_s
        await asyncio.sleep(1.0)
    finally:
        stop.set()
        await task
        deadline = time.monotonic() + 2.0
        while counter.received < service.status()["sent"] and time.monotonic() < deadline:
            await asyncio.sleep(0.05)  # the last datagrams are still on their way to the client
        transport.close()
    points.append(memory_point(source.stats.last_t - first, time.time() - wall0))
    return service.status(), points, counter.received
