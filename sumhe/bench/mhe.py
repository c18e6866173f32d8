"""``sumhe bench mhe``: latency, accuracy and replay speed of the moving-horizon estimator (issue 3); the parts run
here, the report is :mod:`sumhe.bench.mhe_report`'s.

* Latency: per solver (``sqp``, ``ipopt``, ``fatrop``) and window size N, the per-epoch update time (the push of
  a GNSS epoch: append, solve, report) on a simulated drive once the window is full, p50/p99/max, with the
  solver's iterations per epoch; and the same during a 30 s outage at the longest window (N_max steps).
* Accuracy: simulated drives (scenarios x seeds) with the simulator's CAN imperfections (speed scale, yaw-rate
  bias and its drift, noise, quantisation, timestamp jitter) and outages of each length placed all along them.
  Every estimator gets the same stream; the error of every estimate made inside an outage (epochs and CAN rate:
  the newest state) against the truth, mean/p95/max, against the EKF and dead reckoning of
  :mod:`sumhe.baseline` (built through the registry). After each outage (up to ``batch_max_outage_s``), once
  ``after`` GNSS epochs are back, the MHE's smoothed window over the outage is compared with the batch estimate
  (:func:`~sumhe.estimator.batch.estimate_batch`) of the same span (``before`` + outage + ``after`` epochs).
* Multipath: drives with multipath jumps (white GNSS errors otherwise): the error of every estimate, per
  estimator (what each gate lets through).
* Replay speed: one long drive through the MHE (every decoded CAN sample pushed, as a replay does), in x real time.
"""

from __future__ import annotations

import logging
import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import casadi
import numpy as np
import osqp
from numpy.typing import NDArray

from sumhe.bench.metrics import horizontal_errors, interval_index, net_errors, offsets_before
from sumhe.config import Config, DatumSettings, GpsSettings
from sumhe.errors import SumheError
from sumhe.estimator.base import Estimator, StateEstimate
from sumhe.estimator.batch import estimate_batch
from sumhe.estimator.mhe import MovingHorizonEstimator
from sumhe.estimator.registry import make_estimator
from sumhe.frontend.fixes import FixConverter, LocalFix
from sumhe.io.fixtime import stamp_fix
from sumhe.messages import CanSample, Sample
from sumhe.settings import CanModel, EstimationSettings, with_changes
from sumhe.sim import SimSettings, simulate
from sumhe.sim.drive import Drive

log = logging.getLogger(__name__)

Progress = Callable[[str], None]
CORRELATED_GPS_ERRORS = ("walk",)
"""The simulator's GNSS error models with an offset that outlives an outage's start: there the errors are also
reported net of it (with white errors the mean of the last fixes is noise, not an offset anyone inherits)."""
PARTS = ("latency", "accuracy", "multipath", "replay")
"""The benchmark's parts, in the order they run (latency first, on a machine the others have not yet heated)."""
StreamItem = LocalFix | CanSample


@dataclass(frozen=True, slots=True)
class MheBenchSettings:
    """What the benchmark runs. Times in s; window sizes in steps (10 Hz GNSS: 50 steps = 5 s)."""

    scenarios: tuple[str, ...] = ("urban", "highway", "offroad")
    seeds: tuple[int, ...] = (21, 22)
    gps_errors: tuple[str, ...] = ("uniform", "gaussian", "walk")
    outage_lengths_s: tuple[float, ...] = (5.0, 10.0, 30.0)
    duration_s: float = 300.0
    recover_s: float = 20.0
    baselines: tuple[str, ...] = ("ekf", "dead-reckoning")
    solvers: tuple[str, ...] = ("sqp", "ipopt", "fatrop")
    window_sizes: tuple[int, ...] = (50, 300)
    latency_s: float = 60.0
    nlp_latency_epochs: int = 150
    replay_s: float = 3600.0
    batch_max_outage_s: float = 10.0
    multipath_per_min: float = 3.0
    before: int = 10
    after: int = 10
    estimator: EstimationSettings = field(
        default_factory=lambda: EstimationSettings(can=CanModel(delay_s=SimSettings().can_sensor_delay_s))
    )
    parts: tuple[str, ...] = PARTS

    def __post_init__(self) -> None:
        unknown = set(self.parts) - set(PARTS)
        if unknown or not self.parts:
            raise ValueError(f"parts: choose from {', '.join(PARTS)}, got {', '.join(self.parts) or 'none'}")

    @classmethod
    def quick(cls) -> MheBenchSettings:
        """A few minutes: one seed, N = 50 for the NLP solvers, a 10 min replay."""
        return cls(seeds=(21,), latency_s=40.0, nlp_latency_epochs=60, replay_s=600.0)


@dataclass(frozen=True, slots=True)
class Run:
    """One estimator on one drive: the estimates, the GNSS-epoch update times (ms), the wall-clock and the CPU time
    of the process (s; on a shared machine the CPU time is what one core of its own would take)."""

    estimates: list[StateEstimate]
    epoch_ms: NDArray[np.float64]
    wall_s: float
    cpu_s: float


def environment() -> str:
    """How the benchmark runs: threads, CPUs, versions."""
    threads = ", ".join(f"{v}={os.environ.get(v, 'unset')}" for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"))
    return (
        f"{platform.python_implementation()} {platform.python_version()} on {platform.machine()}, "
        f"{os.cpu_count()} CPUs (load average {os.getloadavg()[0]:.1f}: timings suffer when it exceeds the CPUs); "
        f"{threads}; numpy {np.__version__}, casadi {casadi.__version__}, osqp {osqp.__version__}"
    )


def outage_plan(duration_s: float, length_s: float, recover_s: float, first_s: float = 20.0) -> tuple:
    """Outages of ``length_s`` from ``first_s`` on, ``recover_s`` of GNSS between them, all inside the drive."""
    starts = np.arange(first_s, duration_s - length_s - recover_s, length_s + recover_s)
    return tuple((float(s), float(length_s)) for s in starts)


def drive_stream(drive: Drive) -> list[StreamItem]:
    """The drive as an estimator sees it: fixes stamped with their UTC time and put in the drive's local frame
    (the datum of the simulation, so the truth's east/north apply), CAN samples, in time order."""
    sim = drive.settings
    converter = FixConverter(
        DatumSettings(mode="fixed", lat=sim.datum_lat_deg, lon=sim.datum_lon_deg, alt=sim.datum_alt_m)
    )
    gps = GpsSettings()
    items: list[StreamItem] = [converter.convert(stamp_fix(f, gps)) for f in drive.fixes()]
    items += drive.can_samples()
    items.sort(key=lambda s: s.t)
    return items


def run_stream(
    estimator: Estimator,
    stream: Sequence[StreamItem],
    on_estimate: Callable[[StateEstimate], None] | None = None,
) -> Run:
    """Push every sample; the estimates, and the update time of each GNSS epoch (ms, the push that made it)."""
    out: list[StateEstimate] = []
    epoch_ms: list[float] = []
    t0, c0 = time.perf_counter(), time.process_time()
    for item in stream:
        ta = time.perf_counter()
        produced = estimator.push(item)
        if isinstance(item, LocalFix) and produced:
            epoch_ms.append(1e3 * (time.perf_counter() - ta))
        for e in produced:
            out.append(e)
            if on_estimate is not None:
                on_estimate(e)
    return Run(out, np.array(epoch_ms), time.perf_counter() - t0, time.process_time() - c0)


def position_errors(drive: Drive, estimates: Sequence[StateEstimate]) -> tuple[NDArray, NDArray]:
    """Times (s) and horizontal errors (m) of the estimates against the truth."""
    t = np.array([e.t for e in estimates])
    east = np.array([e.east_m for e in estimates])
    north = np.array([e.north_m for e in estimates])
    return t, horizontal_errors(t, east, north, drive.truth)


# ---- latency -----------------------------------------------------------------------------------------------------


def latency_run(
    solver: str, steps: int, duration_s: float, base: EstimationSettings, max_epochs: int | None = None
) -> dict[str, float]:
    """Per-epoch update time of the MHE with ``solver`` and a window of ``steps`` steps, once it is full."""
    settings = with_changes(
        base,
        {
            "estimator.mhe.solver": solver,
            "estimator.mhe.steps": steps,
            "estimator.mhe.max_steps": max(steps, base.estimator.mhe.max_steps),
        },
    )
    skip_s = steps * base.gnss.period_s + 1.0
    if max_epochs is not None:
        duration_s = min(duration_s, skip_s + max_epochs * base.gnss.period_s)
    drive = simulate(SimSettings(scenario="urban", seed=7, duration_s=max(duration_s, skip_s + 5.0)))
    est = MovingHorizonEstimator(settings)
    est.warm_up()
    run = run_stream(est, drive_stream(drive))
    epochs = [e for e in run.estimates if e.mode != "can" and e.window >= steps]
    ms = np.array([e.solve_ms for e in epochs])
    stats = est.stats()
    solves = max(int(stats.get("solves", 0)), 1)
    iters = int(stats.get("qp_iterations", 0)) + int(stats.get("nlp_iterations", 0))
    return {
        "epochs": float(len(ms)),
        "p50": float(np.percentile(ms, 50)) if len(ms) else math.nan,
        "p99": float(np.percentile(ms, 99)) if len(ms) else math.nan,
        "max": float(np.max(ms)) if len(ms) else math.nan,
        "iterations": iters / solves,
        "banded": float(stats.get("banded_solves", 0)) / solves,
        "fallbacks": float(stats.get("fallbacks", 0)),
    }


def outage_latency_run(solver: str, base: EstimationSettings) -> dict[str, float]:
    """Per-epoch update time while a 30 s outage grows the window to N_max (epochs with >= 90 % of N_max)."""
    settings = with_changes(base, {"estimator.mhe.solver": solver})
    drive = simulate(SimSettings(scenario="urban", seed=8, duration_s=60.0, outages=((15.0, 30.0),)))
    est = MovingHorizonEstimator(settings)
    est.warm_up()
    run = run_stream(est, drive_stream(drive))
    big = [e.solve_ms for e in run.estimates if e.mode != "can" and e.window >= 0.9 * settings.estimator.mhe.max_steps]
    ms = np.array(big)
    return {
        "epochs": float(len(ms)),
        "window": float(max((e.window for e in run.estimates), default=0)),
        "p50": float(np.percentile(ms, 50)) if len(ms) else math.nan,
        "p99": float(np.percentile(ms, 99)) if len(ms) else math.nan,
        "max": float(np.max(ms)) if len(ms) else math.nan,
    }


# ---- accuracy ------------------------------------------------------------------------------------------------------


@dataclass
class _Smoothed:
    """The MHE's smoothed window captured ``after`` GNSS epochs after each outage."""

    outages: list[tuple[float, float]]
    after: int
    estimator: MovingHorizonEstimator
    captured: dict[int, tuple[NDArray, NDArray]] = field(default_factory=dict)
    _ok_after: dict[int, int] = field(default_factory=dict)

    def __call__(self, e: StateEstimate) -> None:
        if e.mode == "can" or e.gps != "ok":
            return
        for i, (_, t1) in enumerate(self.outages):
            if e.t >= t1 and i not in self.captured:
                self._ok_after[i] = self._ok_after.get(i, 0) + 1
                if self._ok_after[i] >= self.after:
                    self.captured[i] = self.estimator.smoothed()


def accuracy_drive(
    scenario: str, seed: int, gps_error: str, length_s: float, bs: MheBenchSettings, progress: Progress | None = None
) -> dict[str, object]:
    """One drive with outages of ``length_s``: per estimator the errors inside outages; per outage the MHE's
    smoothed window against the batch estimate (for short outages)."""
    plan = outage_plan(bs.duration_s, length_s, bs.recover_s)
    sim = SimSettings(scenario=scenario, seed=seed, duration_s=bs.duration_s, outages=plan, gps_error=gps_error)
    drive = simulate(sim)
    stream = drive_stream(drive)
    start = drive.settings.start_unix_s
    outages = [(start + s, start + s + n) for s, n in plan]
    result: dict[str, object] = {"errors": {}, "smoothed": [], "batch": []}
    errors: dict[str, NDArray] = {}
    mhe = MovingHorizonEstimator(bs.estimator)
    mhe.warm_up()
    capture = _Smoothed(outages, bs.after, mhe)
    runs = {"mhe": run_stream(mhe, stream, capture)}
    config = Config.of(bs.estimator)
    for name in bs.baselines:
        try:
            runs[name] = run_stream(make_estimator(name, config), stream)
        except SumheError as e:
            log.warning("baseline %s not available: %s", name, e)
    fixes = [s for s in stream if isinstance(s, LocalFix) and s.valid]
    offsets = offsets_before(
        [f.t for f in fixes],
        [f.east_m for f in fixes],
        [f.north_m for f in fixes],
        drive.truth,
        [t0 for t0, _ in outages],
        bs.before,
    )
    net: dict[str, NDArray] = {}
    for name, run in runs.items():
        t = np.array([e.t for e in run.estimates])
        east, north = np.array([e.east_m for e in run.estimates]), np.array([e.north_m for e in run.estimates])
        inside = interval_index(t, outages) >= 0
        errors[name] = horizontal_errors(t[inside], east[inside], north[inside], drive.truth)
        net[name] = net_errors(t, east, north, drive.truth, outages, offsets)
    result["errors"], result["net"] = errors, net
    if length_s <= bs.batch_max_outage_s:
        smoothed, batch = _after_outage(drive, outages, capture, bs)
        result["smoothed"], result["batch"] = smoothed, batch
    if progress is not None:
        progress(
            f"  {scenario} seed {seed} {gps_error} outages {length_s:.0f} s: "
            + ", ".join(f"{k} {np.mean(v):.2f} m" for k, v in errors.items() if len(v))
        )
    return result


def _after_outage(
    drive: Drive, outages: list[tuple[float, float]], capture: _Smoothed, bs: MheBenchSettings
) -> tuple[list[float], list[float]]:
    """Mean error (m) over each outage of the MHE's smoothed window and of the batch estimate of the same span."""
    gps = GpsSettings()
    stamped = [stamp_fix(f, gps) for f in drive.fixes()]
    cans = drive.can_samples()
    t_can = np.array([c.t for c in cans])
    smoothed_err: list[float] = []
    batch_err: list[float] = []
    period = 1.0 / drive.settings.gps_rate_hz
    for i, (t0, t1) in enumerate(outages):
        if i not in capture.captured:
            continue
        t_win, x_win = capture.captured[i]
        lo, hi = t0 - (bs.before + 0.5) * period, t1 + (bs.after - 0.5) * period
        grid_t = np.arange(t0, t1, period)
        if len(grid_t) == 0 or t_win[0] > t0:
            continue
        truth = drive.truth.at(grid_t)
        east = np.interp(grid_t, t_win, x_win[:, 0])
        north = np.interp(grid_t, t_win, x_win[:, 1])
        smoothed_err.append(float(np.mean(np.hypot(east - truth.east, north - truth.north))))
        samples: list[Sample] = [f for f in stamped if lo <= f.t <= hi]
        i0, i1 = np.searchsorted(t_can, [lo - 0.05, hi + 0.05])
        samples += cans[i0:i1]
        samples.sort(key=lambda s: s.t)
        try:
            res = estimate_batch(samples, bs.estimator, frame=drive.frame)
        except SumheError as e:
            log.warning("batch estimate of outage %d failed: %s", i, e)
            batch_err.append(math.nan)
            continue
        east_b = np.interp(grid_t, res.t, res.east)
        north_b = np.interp(grid_t, res.t, res.north)
        batch_err.append(float(np.mean(np.hypot(east_b - truth.east, north_b - truth.north))))
    return smoothed_err, batch_err


# ---- replay --------------------------------------------------------------------------------------------------------


def replay_run(duration_s: float, base: EstimationSettings) -> dict[str, float]:
    """One long highway/urban drive (two outages per 10 minutes) through the MHE: x real time on one core."""
    plan = tuple((s, 10.0) for s in np.arange(120.0, duration_s - 60.0, 300.0))
    drive = simulate(SimSettings(scenario="urban", seed=9, duration_s=duration_s, outages=plan))
    stream = drive_stream(drive)
    est = MovingHorizonEstimator(base)
    est.warm_up()
    run = run_stream(est, stream)
    span = stream[-1].t - stream[0].t
    stats = est.stats()
    return {
        "span_s": span,
        "wall_s": run.wall_s,
        "speed": span / run.wall_s,
        "cpu_s": run.cpu_s,
        "cpu_speed": span / run.cpu_s,
        "load": os.getloadavg()[0],
        "samples": float(len(stream)),
        "estimates": float(len(run.estimates)),
        "epoch_p50": float(np.percentile(run.epoch_ms, 50)),
        "epoch_p99": float(np.percentile(run.epoch_ms, 99)),
        "fallbacks": float(stats.get("fallbacks", 0)),
        "banded": float(stats.get("banded_solves", 0)) / max(int(stats.get("solves", 0)), 1),
    }
