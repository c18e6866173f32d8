"""``sumhe bench`` (``peers``): every estimator on the same drives by the same code path, side by side.

Drives: simulated ones (scenarios x GPS error models x seeds; the seeds are test seeds, never the training seeds
100-105 the baselines were tuned on) and recorded ones given by the user (a directory with ``drive.log``,
``drive.nmea`` and a ``truth.csv`` in the simulator's format, replayed through :func:`sumhe.io.replay.log_samples`).
On each drive the bench places one outage of every length (5, 10, 30, 55 s) in an order and at gaps drawn from
the drive's seed, after a warm-up, with GNSS for at least ``recover_s`` between them; the fixes whose measurement
time falls inside an outage are removed (a silent receiver). Each placement is labelled by the truth's motion
during it (:func:`sumhe.bench.protocol.label_motion`: stop, sharp turn, bend, straight).

Every estimator gets exactly the same samples: fixes stamped once with their measurement time
(:func:`~sumhe.io.fixtime.stamp_fix`), CAN samples in log order, merged by time as a replay merges them, pushed one
by one through :class:`~sumhe.service.pipeline.Pipeline` (the code path of the service and of ``sumhe replay``),
then ``pipeline.finish()``. The config has a fixed datum at the truth's frame; on simulated drives the CAN sensor
delay is calibrated (``sensors.can.delay_s`` = the simulator's delay) for every estimator alike.

Figures, per estimator over all drives: position error of every estimate (GNSS epochs and CAN rate) inside the
outages (all, per length, per motion; an outage lasts until the first fix after it) and outside them after the
warm-up (with GPS); azimuth error while the truth moves faster than ``heading_min_speed_mps``; the time of each
``pipeline.push`` (per pushed sample, and for pushes of a GNSS fix: per epoch); throughput = seconds of data /
seconds of push + finish; peak memory (see :data:`MEMORY_METHOD`). Each run (one estimator on one drive) runs in a
forked process with a time limit: an estimator that raises, crashes or hangs is recorded as a failed run and the
bench goes on.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import multiprocessing
import os
import platform
import resource
import time
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from sumhe import __version__
from sumhe.bench import metrics
from sumhe.bench.protocol import label_motion
from sumhe.config import Config, DatumSettings
from sumhe.errors import ConfigError, SumheError
from sumhe.estimator.registry import estimator_class, estimator_names, make_estimator
from sumhe.geo import LocalFrame
from sumhe.io.fixtime import stamp_fix
from sumhe.io.replay import log_samples, merge_by_time
from sumhe.messages import GnssFix, Sample
from sumhe.service.pipeline import Pipeline
from sumhe.settings import with_changes
from sumhe.sim import SimSettings, Truth, load_settings, load_truth, simulate
from sumhe.sim.settings import GPS_ERROR_MODELS, SCENARIO_NAMES

log = logging.getLogger(__name__)

T = TypeVar("T")

MEMORY_METHOD = (
    "peak RSS growth of one run: resource.getrusage(RUSAGE_SELF).ru_maxrss of the forked process that runs the "
    "estimator on one drive, minus its RSS before the estimator is built (max over drives; includes all the run "
    "allocates: the estimator, its solver libraries' heap, the estimates collected; not the drive's samples, which "
    "the process inherits)"
)
RECORDED_FILES = ("drive.log", "drive.nmea", "truth.csv")
MOTION_ORDER = ("straight", "bend", "sharp", "stop")
MAX_DURATION_S = 3600.0


class BenchRunError(SumheError):
    """One run of the bench failed (raised, crashed or ran out of time); recorded, never fatal."""


@dataclass(frozen=True, slots=True)
class PeersSettings:
    """What ``sumhe bench`` runs. Times in s. ``estimators`` empty: every registered estimator.
    ``recordings``: directories of recorded drives (see the module docstring)."""

    scenarios: tuple[str, ...] = SCENARIO_NAMES
    gps_errors: tuple[str, ...] = ("uniform", "gaussian", "walk")
    seeds: tuple[int, ...] = (1, 2, 3)
    duration_s: float = 240.0
    outage_lengths_s: tuple[float, ...] = (5.0, 10.0, 30.0, 55.0)
    recover_s: float = 15.0
    warm_up_s: float = 20.0
    estimators: tuple[str, ...] = ()
    recordings: tuple[str, ...] = ()
    timeout_s: float = 1800.0
    heading_min_speed_mps: float = 2.0

    def __post_init__(self) -> None:
        for name, value in (("scenarios", self.scenarios), ("gps_errors", self.gps_errors)):
            known = SCENARIO_NAMES if name == "scenarios" else GPS_ERROR_MODELS
            for v in value:
                if v not in known:
                    raise ValueError(f"{name}: unknown {v!r} (known: {', '.join(known)})")
        if any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in self.seeds):
            raise ValueError(f"seeds: must be integers >= 0, got {self.seeds!r}")
        if not self.outage_lengths_s or any(not 0.0 < L < 600.0 for L in self.outage_lengths_s):
            raise ValueError(f"outage_lengths_s: need lengths within (0, 600) s, got {self.outage_lengths_s!r}")
        for name in ("duration_s", "recover_s", "warm_up_s", "timeout_s"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name}: must be positive, got {getattr(self, name)!r}")
        if self.duration_s > MAX_DURATION_S:
            raise ValueError(
                f"duration_s: at most {MAX_DURATION_S:g} s (the simulator's limit), got {self.duration_s!r}"
            )
        needed = self.warm_up_s + sum(self.outage_lengths_s) + self.recover_s * len(self.outage_lengths_s)
        if (self.scenarios and self.gps_errors and self.seeds) and self.duration_s < needed:
            raise ValueError(f"duration_s: {self.duration_s:g} s cannot hold the outages, need {needed:g} s")

    @classmethod
    def quick(cls) -> PeersSettings:
        """About a minute on two cores: one 120 s urban drive (walk GPS errors), outages of 5, 10 and 30 s."""
        return cls(
            scenarios=("urban",),
            gps_errors=("walk",),
            seeds=(1,),
            duration_s=120.0,
            outage_lengths_s=(5.0, 10.0, 30.0),
            recover_s=10.0,
            timeout_s=300.0,
        )

    def names(self) -> tuple[str, ...]:
        """The estimators to run."""
        return self.estimators or estimator_names()

    def drive_count(self) -> int:
        return len(self.scenarios) * len(self.gps_errors) * len(self.seeds) + len(self.recordings)


@dataclass(frozen=True, slots=True)
class Outage:
    """One placed outage: ``start_s`` (s, the drive's clock), ``length_s`` and the truth's motion during it;
    ``gps_back_s``: the time of the first fix after it (NaN until known, see :func:`with_gps_back`)."""

    start_s: float
    length_s: float
    motion: str
    gps_back_s: float = math.nan

    @property
    def end_s(self) -> float:
        return self.start_s + self.length_s

    @property
    def scored_span(self) -> tuple[float, float]:
        """Where estimates count as made without GPS: from the start until the first fix after the outage (the
        CAN-rate estimates between the outage's end and that fix have no fix yet either)."""
        return self.start_s, self.gps_back_s if math.isfinite(self.gps_back_s) else self.end_s


@dataclass(frozen=True, eq=False)
class BenchDrive:
    """A drive as the bench runs it: the samples every estimator gets (outage fixes removed), the truth (its
    east/north in the frame of ``config.datum``), the config, the outages placed, and the time (s) from which
    estimates are scored (the end of the warm-up)."""

    name: str
    kind: str
    samples: list[Sample]
    truth: Truth
    config: Config
    outages: tuple[Outage, ...]
    scored_from: float

    @property
    def span_s(self) -> float:
        return self.samples[-1].t - self.samples[0].t if self.samples else 0.0


# ---- drives --------------------------------------------------------------------------------------------------------


def outage_plan(
    duration_s: float, lengths_s: Sequence[float], recover_s: float, warm_up_s: float, rng: np.random.Generator
) -> list[tuple[float, float]]:
    """(start_s, length_s) of one outage per length, relative to the drive's start: in a random order, after
    ``warm_up_s``, at least ``recover_s`` apart and ``recover_s`` before the end, the slack spread at random over
    the gaps. Lengths that do not fit (a short recording) are left out, longest first."""
    order = [float(lengths_s[i]) for i in rng.permutation(len(lengths_s))]
    while order and warm_up_s + sum(order) + recover_s * len(order) > duration_s:
        order.remove(max(order))
    if not order:
        return []
    slack = duration_s - warm_up_s - sum(order) - recover_s * len(order)
    gaps = slack * rng.dirichlet(np.ones(len(order) + 1))
    plan = []
    t = warm_up_s
    for length, gap in zip(order, gaps, strict=False):
        t += gap
        plan.append((round(t, 2), length))
        t += length + recover_s
    return plan


def place_outages(truth: Truth, plan: Iterable[tuple[float, float]], t0: float) -> tuple[Outage, ...]:
    """The planned outages (relative to ``t0``, s) labelled by the truth's motion during each."""
    out = []
    for start, length in plan:
        grid = np.arange(t0 + start, t0 + start + length, 0.1)
        at = truth.at(grid)
        out.append(Outage(t0 + start, length, label_motion(at.speed, at.yaw_rate)))
    return tuple(out)


def without_fixes_in(samples: Iterable[Sample], outages: Sequence[Outage]) -> list[Sample]:
    """``samples`` without the GNSS fixes whose time lies inside an outage (a receiver gone silent)."""
    spans = [(o.start_s, o.end_s) for o in outages]
    return [s for s in samples if not (isinstance(s, GnssFix) and metrics.interval_index([s.t], spans)[0] >= 0)]


def with_gps_back(outages: Sequence[Outage], samples: Sequence[Sample]) -> tuple[Outage, ...]:
    """The outages with ``gps_back_s`` set from the valid fixes of ``samples`` (the outage's end when none follows)."""
    fix_t = np.array(sorted(s.t for s in samples if isinstance(s, GnssFix) and s.valid))
    out = []
    for o in outages:
        k = int(np.searchsorted(fix_t, o.end_s))
        out.append(dataclasses.replace(o, gps_back_s=float(fix_t[k]) if k < len(fix_t) else o.end_s))
    return tuple(out)


def drive_config(base: Config, frame: LocalFrame, can_delay_s: float | None = None) -> Config:
    """``base`` with the datum fixed at ``frame`` (estimates come out in the truth's frame) and, when given, the
    calibrated CAN sensor delay."""
    datum = DatumSettings(mode="fixed", lat=frame.lat0_deg, lon=frame.lon0_deg, alt=frame.alt0_m)
    sensors = base.sensors
    if can_delay_s is not None:
        sensors = with_changes(sensors, {"can.delay_s": can_delay_s})
    return dataclasses.replace(base, datum=datum, sensors=sensors)


def simulated_drive(scenario: str, gps_error: str, seed: int, ps: PeersSettings, base: Config) -> BenchDrive:
    """A simulated drive (no outages simulated: the bench places them) and its outages."""
    sim = SimSettings(scenario=scenario, seed=seed, duration_s=ps.duration_s, gps_error=gps_error)
    drive = simulate(sim)
    config = drive_config(base, drive.frame, sim.can_sensor_delay_s)
    rng = np.random.default_rng([seed, SCENARIO_NAMES.index(scenario), GPS_ERROR_MODELS.index(gps_error)])
    plan = outage_plan(ps.duration_s, ps.outage_lengths_s, ps.recover_s, ps.warm_up_s, rng)
    outages = place_outages(drive.truth, plan, sim.start_unix_s)
    fixes = [stamp_fix(f, config.gps) for f in drive.fixes()]
    samples = without_fixes_in(merge_by_time(drive.can_samples(), fixes), outages)
    name = f"{scenario}-{gps_error}-{seed}"
    scored_from = sim.start_unix_s + ps.warm_up_s
    return BenchDrive(name, "simulated", samples, drive.truth, config, with_gps_back(outages, samples), scored_from)


def recorded_drive(directory: str | Path, ps: PeersSettings, base: Config) -> BenchDrive:
    """A recorded drive (``drive.log``, ``drive.nmea``, ``truth.csv``; ``scenario.toml`` for the datum if there)
    replayed as ``sumhe replay`` reads it; ConfigError naming what is missing or unreadable."""
    d = Path(directory)
    missing = [name for name in RECORDED_FILES if not (d / name).is_file()]
    if missing:
        raise ConfigError(f"--drive {d}: missing {', '.join(missing)}")
    try:
        truth = load_truth(d / "truth.csv")
        frame = _recorded_frame(d, truth)
    except ValueError as e:
        raise ConfigError(f"--drive {d}: {e}") from e
    enu = frame.to_enu(truth.lat, truth.lon, frame.alt0_m)
    truth = dataclasses.replace(truth, east=enu[:, 0], north=enu[:, 1])
    config = drive_config(base, frame)
    samples = list(log_samples(config, d / "drive.log", d / "drive.nmea"))
    if not samples:
        raise ConfigError(f"--drive {d}: no samples decoded from drive.log and drive.nmea")
    t0 = float(truth.t[0])
    duration = float(min(truth.t[-1], samples[-1].t) - t0)
    rng = np.random.default_rng(len(truth))
    outages = place_outages(truth, outage_plan(duration, ps.outage_lengths_s, ps.recover_s, ps.warm_up_s, rng), t0)
    if len(outages) < len(ps.outage_lengths_s):
        log.warning("%s: %.0f s of truth hold only %d of the outages", d, duration, len(outages))
    kept = without_fixes_in(samples, outages)
    outages = with_gps_back(outages, kept)
    return BenchDrive(d.name or str(d), "recorded", kept, truth, config, outages, t0 + ps.warm_up_s)


def _recorded_frame(directory: Path, truth: Truth) -> LocalFrame:
    scenario = directory / "scenario.toml"
    if scenario.is_file():
        sim = load_settings(scenario)
        return LocalFrame(sim.datum_lat_deg, sim.datum_lon_deg, sim.datum_alt_m)
    return LocalFrame(float(truth.lat[0]), float(truth.lon[0]), 0.0)


def drives(ps: PeersSettings, base: Config) -> Iterable[BenchDrive]:
    """Every drive of the bench, built when needed: the recorded ones first (a bad recording stops the bench
    before it has run for long), then the simulated ones."""
    for directory in ps.recordings:
        yield recorded_drive(directory, ps, base)
    for scenario in ps.scenarios:
        for gps_error in ps.gps_errors:
            for seed in ps.seeds:
                yield simulated_drive(scenario, gps_error, seed, ps, base)


# ---- one run -------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RunResult:
    """One estimator on one drive. Errors in m, heading errors in rad; latency histograms of
    :func:`~sumhe.bench.metrics.latency_histogram` (ms); times in s; memory in MB. ``error`` when it failed."""

    estimator: str
    drive: str
    error: str | None = None
    live_estimates: int = 0
    finish_estimates: int = 0
    nonfinite: int = 0
    outage_errors: tuple[NDArray[np.float64], ...] = ()
    gps_errors: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    heading_errors: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    sample_hist: NDArray[np.int64] = field(default_factory=lambda: metrics.latency_histogram([]))
    epoch_hist: NDArray[np.int64] = field(default_factory=lambda: metrics.latency_histogram([]))
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
        sample_hist=metrics.latency_histogram(push_ms),
        epoch_hist=metrics.latency_histogram(push_ms[is_fix]),
        span_s=drive.span_s,
        push_s=float(push_ms.sum() / 1e3),
        finish_s=finish_s,
        build_s=build_s,
        peak_mb=_max_rss_mb() - rss0,
    )


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
    """What the report keeps of a drive: name, kind (simulated/recorded), start (s, its clock), span of its
    samples (s) and the outages placed."""

    name: str
    kind: str
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
        seen.append(DriveInfo(drive.name, drive.kind, float(drive.truth.t[0]), drive.span_s, drive.outages))
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


# ---- summary -------------------------------------------------------------------------------------------------------


def _errors(values: Sequence[NDArray[np.float64]], unit: str = "m", scale: float = 1.0) -> dict[str, float]:
    pooled = np.concatenate(values) * scale if values else np.zeros(0)
    mean, p95, mx = metrics.mean_p95_max(pooled)
    return {"n": int(pooled.size), f"mean_{unit}": mean, f"p95_{unit}": p95, f"max_{unit}": mx}


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
    empty = metrics.latency_histogram([])
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
        "latency_ms": {
            kind: {
                "n": int(hist.sum()),
                "p50": metrics.histogram_percentile(hist, 50.0),
                "p99": metrics.histogram_percentile(hist, 99.0),
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
    per estimator its figures, per placement each estimator's mean and max error, and the failed runs."""
    names = list(dict.fromkeys(r.estimator for r in report.results))
    placements = []
    for d in report.drives:
        runs = {r.estimator: r for r in report.results if r.drive == d.name and r.ok}
        for i, o in enumerate(d.outages):
            stats = {n: metrics.mean_p95_max(r.outage_errors[i]) for n, r in runs.items()}
            placements.append(
                {
                    "drive": d.name,
                    "start_s": round(o.start_s - d.t0, 2),
                    "length_s": o.length_s,
                    "motion": o.motion,
                    "mean_m": {n: s[0] for n, s in stats.items()},
                    "max_m": {n: s[2] for n, s in stats.items()},
                }
            )
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
                "kind": d.kind,
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
        "estimators": {
            n: summarise_estimator(n, [r for r in report.results if r.estimator == n], report.drives) for n in names
        },
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
        + f"), {sum(counts.values())} outages ({per_length}); estimators: {', '.join(summary['estimators'])}.",
        f"Ran on {env['cpu']}; {env['python']}, numpy {env['numpy']}, casadi {env['casadi']}, sumhe "
        f"{env['sumhe']}; {env['blas_threads']}; one run at a time, each in its own forked process; "
        f"{summary['wall_s']:.0f} s wall.",
    ]


def main_table(summary: Mapping[str, Any]) -> list[str]:
    """THE table: one row per estimator (Markdown)."""
    estimators = summary["estimators"]
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


def motion_table(summary: Mapping[str, Any]) -> list[str]:
    """Mean / max error during outages by what the vehicle did (Markdown)."""
    placements = summary["placements"]
    motions = [m for m in MOTION_ORDER if any(p["motion"] == m for p in placements)]
    n = {m: sum(p["motion"] == m for p in placements) for m in motions}
    head = ["estimator", *(f"{m} ({n[m]} outages): mean / p95 / max (m)" for m in motions)]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for name, e in summary["estimators"].items():
        cells = [_cell(e["outage_by_motion"].get(m, {}), ("mean_m", "p95_m", "max_m")) for m in motions]
        lines.append("| " + " | ".join([f"`{name}`", *cells]) + " |")
    return lines


def markdown(summary: Mapping[str, Any]) -> str:
    """The Markdown report: how it ran, the table, errors by motion, how each figure is measured, failures."""
    out = ["# sumhe bench: estimators side by side", "", *how_it_ran(summary), "", *main_table(summary), ""]
    out += ["## Position error during outages by the truth's motion", "", *motion_table(summary), ""]
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
    ]
    if summary["failures"]:
        out += ["", "## Failed runs", ""]
        out += [f"- `{f['estimator']}` on {f['drive']}: {f['error']}" for f in summary["failures"]]
    return "\n".join(out) + "\n"
