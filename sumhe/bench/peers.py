"""``sumhe bench`` (``peers``): every estimator on the same drives by the same code path, side by side.

Drives (:mod:`sumhe.bench.drives`): simulated ones of the ``kind`` profile (scenarios x GPS error models x seeds;
the seeds are test seeds, never the training seeds 100-105 the baselines were tuned on) and of the ``realistic``
one (scenarios x seeds), with outages placed on them; the report keeps the profiles apart. Every estimator gets
exactly the same samples, pushed one by one through :class:`~sumhe.service.pipeline.Pipeline` (the code path of
the service and of ``sumhe replay``), then ``pipeline.finish()``; the report is :mod:`sumhe.bench.report`'s.

Figures, per estimator over all drives: position error of every estimate (GNSS epochs and CAN rate) inside the
outages (all, per length, per motion; an outage lasts until the first fix after it) and outside them after the
warm-up (with GPS); azimuth error while the truth moves faster than ``heading_min_speed_mps``; the time of each
``pipeline.push`` (per pushed sample, and for pushes of a GNSS fix: per epoch); throughput = seconds of data /
seconds of push + finish; peak memory (see :data:`MEMORY_METHOD`). Each run (one estimator on one drive) runs in a
forked process with a time limit: an estimator that raises, crashes or hangs is recorded as a failed run and the
bench goes on.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import platform
import resource
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from sumhe import __version__
from sumhe.bench import metrics
from sumhe.bench.drives import BenchDrive, Outage, PeersSettings, drives
from sumhe.config import Config
from sumhe.errors import ConfigError, SumheError
from sumhe.estimator.registry import estimator_class, make_estimator
from sumhe.messages import Estimate, GnssFix
from sumhe.service.histogram import latency_histogram
from sumhe.service.pipeline import Pipeline

log = logging.getLogger(__name__)

T = TypeVar("T")

MEMORY_METHOD = (
    "peak RSS growth of one run: resource.getrusage(RUSAGE_SELF).ru_maxrss of the forked process that runs the "
    "estimator on one drive, minus its RSS before the estimator is built (max over drives; includes all the run "
    "allocates: the estimator, its solver libraries' heap, the estimates collected; not the drive's samples, which "
    "the process inherits)"
)


class BenchRunError(SumheError):
    """One run of the bench failed (raised, crashed or ran out of time); recorded, never fatal."""


# ---- one run -------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RunResult:
    """One estimator on one drive. Errors in m, heading errors in rad; latency histograms of
    :func:`~sumhe.service.histogram.latency_histogram` (ms); times in s; memory in MB. ``error`` when it failed."""

    estimator: str
    drive: str
    error: str | None = None
    live_estimates: int = 0
    finish_estimates: int = 0
    nonfinite: int = 0
    outage_errors: tuple[NDArray[np.float64], ...] = ()
    gps_errors: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    heading_errors: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    calib_gps: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, len(metrics.CALIBRATION_COLUMNS))))
    calib_outage: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, len(metrics.CALIBRATION_COLUMNS))))
    sample_hist: NDArray[np.int64] = field(default_factory=lambda: latency_histogram([]))
    epoch_hist: NDArray[np.int64] = field(default_factory=lambda: latency_histogram([]))
    span_s: float = 0.0
    push_s: float = 0.0
    finish_s: float = 0.0
    build_s: float = 0.0
    peak_mb: float = math.nan

    @property
    def ok(self) -> bool:
        return self.error is None


def _rss_mb() -> float:
    """The process's resident set now (MB; Linux ``/proc``, NaN elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return math.nan
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def _max_rss_mb() -> float:
    """Peak resident set of this process so far (MB; ``ru_maxrss`` is KiB on Linux, bytes on macOS)."""
    scale = 2**20 if platform.system() == "Darwin" else 2**10
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / scale


def run_estimator(name: str, drive: BenchDrive, heading_min_speed_mps: float = 2.0) -> RunResult:
    """Build ``name`` from the drive's config, push every sample through a :class:`Pipeline` (timing each push),
    call ``finish()``, and score the estimates against the truth. Exceptions propagate (see :func:`call_isolated`)."""
    rss0 = _rss_mb()
    tb = time.perf_counter()
    pipeline = Pipeline(drive.config, make_estimator(name, drive.config))
    build_s = time.perf_counter() - tb
    samples = drive.samples
    push_ms = np.empty(len(samples))
    is_fix = np.fromiter((isinstance(s, GnssFix) for s in samples), dtype=bool, count=len(samples))
    estimates = []
    clock = time.perf_counter
    for i, sample in enumerate(samples):
        ta = clock()
        out = pipeline.push(sample)
        push_ms[i] = clock() - ta
        estimates.extend(out)
    push_ms *= 1e3
    tf = clock()
    finished = pipeline.finish()
    finish_s = clock() - tf
    live = len(estimates)
    estimates.extend(finished)
    t = np.array([e.t for e in estimates])
    east = np.array([e.east_m for e in estimates])
    north = np.array([e.north_m for e in estimates])
    track = np.array([e.track_rad for e in estimates])
    finite = np.isfinite(t) & np.isfinite(east) & np.isfinite(north) & np.isfinite(track)
    t, east, north, track = t[finite], east[finite], north[finite], track[finite]
    err = metrics.horizontal_errors(t, east, north, drive.truth)
    spans = [o.scored_span for o in drive.outages]
    inside, with_gps = metrics.split_by_interval(t, err, spans, after=drive.scored_from)
    calib_gps, calib_outage = _calibration(estimates, finite, t, east, north, drive, spans)
    moving = (t >= drive.scored_from) & (drive.truth.at(t).speed >= heading_min_speed_mps)
    heading = metrics.heading_errors(t[moving], track[moving], drive.truth)
    return RunResult(
        estimator=name,
        drive=drive.name,
        live_estimates=live,
        finish_estimates=len(finished),
        nonfinite=int(np.count_nonzero(~finite)),
        outage_errors=tuple(inside),
        gps_errors=with_gps,
        heading_errors=heading,
        calib_gps=calib_gps,
        calib_outage=calib_outage,
        sample_hist=latency_histogram(push_ms),
        epoch_hist=latency_histogram(push_ms[is_fix]),
        span_s=drive.span_s,
        push_s=float(push_ms.sum() / 1e3),
        finish_s=finish_s,
        build_s=build_s,
        peak_mb=_max_rss_mb() - rss0,
    )


def _calibration(
    estimates: list[Estimate],
    finite: NDArray[np.bool_],
    t: NDArray[np.float64],
    east: NDArray[np.float64],
    north: NDArray[np.float64],
    drive: BenchDrive,
    spans: list[tuple[float, float]],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The calibration columns (:func:`~sumhe.bench.metrics.calibration_columns`) of the finite estimates against
    the truth: with GPS (after the warm-up; one group) and inside the outages (a group each)."""
    kept = [e for e, ok in zip(estimates, finite, strict=True) if ok]

    def column(get: Callable[[Estimate], float | None]) -> NDArray[np.float64]:
        return np.array([math.nan if (v := get(e)) is None else v for e in kept], dtype=float)

    at = drive.truth.at(t)
    index = metrics.interval_index(t, spans)
    cols = metrics.calibration_columns(
        east - at.east,
        north - at.north,
        column(lambda e: e.error.eph_m if e.error is not None else None),
        column(lambda e: e.bound_east_m),
        column(lambda e: e.bound_north_m),
        index,
    )
    return cols[(index < 0) & (t >= drive.scored_from)], cols[index >= 0]


def _child(send: Any, fn: Callable[[], Any]) -> None:
    try:
        result: tuple[str, Any] = ("ok", fn())
    except BaseException as e:  # report anything (a bug in an estimator included) to the parent, which goes on
        frames = traceback.extract_tb(e.__traceback__)
        where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
        result = ("error", f"{type(e).__name__}: {e}{where}")
    send.send(result)
    send.close()


def call_isolated(fn: Callable[[], T], timeout_s: float) -> T:
    """``fn()`` in a forked process (it sees this process's memory as it is now); its result comes back pickled.
    BenchRunError when it raises, dies (e.g. a crash in a C library) or takes longer than ``timeout_s``."""
    ctx = multiprocessing.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    process = ctx.Process(target=_child, args=(send, fn), daemon=True)
    process.start()
    send.close()
    try:
        if not recv.poll(timeout_s):
            raise BenchRunError(f"no result within {timeout_s:g} s")
        try:
            status, value = recv.recv()
        except EOFError:
            process.join(5.0)
            raise BenchRunError(f"the run's process died (exit code {process.exitcode})") from None
    finally:
        recv.close()
        if process.is_alive():
            process.kill()
        process.join(5.0)
    if status != "ok":
        raise BenchRunError(value)
    return value  # type: ignore[no-any-return]


# ---- the bench -----------------------------------------------------------------------------------------------------


class Progress(Protocol):
    """What the runner reports as it goes (the command shows a progress bar)."""

    def starting(self, label: str) -> None: ...

    def finished(self, result: RunResult) -> None: ...


@dataclass(frozen=True, slots=True)
class DriveInfo:
    """What the report keeps of a drive: name, simulator profile, start (s, its clock), span of its samples (s) and
    the outages placed."""

    name: str
    profile: str
    t0: float
    span_s: float
    outages: tuple[Outage, ...]


@dataclass(frozen=True, eq=False)
class BenchReport:
    """Everything one bench produced: the drives and every run's result."""

    settings: PeersSettings
    drives: list[DriveInfo]
    results: list[RunResult]
    environment: dict[str, str]
    wall_s: float


def run_bench(ps: PeersSettings, base: Config, progress: Progress | None = None) -> BenchReport:
    """Run every estimator of ``ps`` on every drive, each run isolated (:func:`call_isolated`)."""
    t0 = time.perf_counter()
    names = ps.names()
    for name in names:  # import each estimator's module here, once: every run (a fork) uses the same code
        try:
            estimator_class(name)
        except ConfigError as e:
            log.warning("%s", e)  # each of its runs records the failure
    results: list[RunResult] = []
    seen: list[DriveInfo] = []
    for drive in drives(ps, base):
        seen.append(DriveInfo(drive.name, drive.profile, float(drive.truth.t[0]), drive.span_s, drive.outages))
        for name in names:
            if progress is not None:
                progress.starting(f"{drive.name} {name}")
            try:
                result = call_isolated(
                    lambda n=name, d=drive: run_estimator(n, d, ps.heading_min_speed_mps), ps.timeout_s
                )
            except BenchRunError as e:
                log.warning("%s on %s failed: %s", name, drive.name, e)
                result = RunResult(estimator=name, drive=drive.name, error=str(e), span_s=drive.span_s)
            results.append(result)
            if progress is not None:
                progress.finished(result)
    return BenchReport(ps, seen, results, environment(), time.perf_counter() - t0)


def environment() -> dict[str, str]:
    """How the bench ran: Python, library versions, CPU, BLAS threads."""
    import casadi

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "sumhe": __version__,
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "numpy": np.__version__,
        "casadi": casadi.__version__,
        "platform": platform.platform(),
        "cpu": f"{cpu}, {os.cpu_count()} CPUs",
        "blas_threads": ", ".join(
            f"{v}={os.environ.get(v, 'unset')}" for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")
        ),
    }
