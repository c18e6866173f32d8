"""The experimental protocol of paper 000 (section 5) on simulated drives.

10 Hz GNSS with cm-level error; an outage of ``outage_epochs`` = 50 epochs (5 s) with ``before`` = N_B and
``after`` = N_A = 10 epochs of GNSS around it; one estimation run per placement on that window of 70 epochs;
the errors (24) ``|p~ - p^|`` of (px1, py1) against the truth at the window's epochs, their max and mean.
The outage is placed at ``placements`` evenly spaced parts of a drive; each placement is labelled by what the
vehicle does during the outage (stop, sharp turn, bend, straight). Methods, side by side on the same windows:

* ``nlp``: our SU formulation (the estimator's settings; :mod:`sumhe.estimator.batch`);
* ``nlp-nobias``: the same without the CAN yaw-rate bias and speed scale states;
* ``nlp-log``, ``nlp-caps``, ``nlp-nocentre``, ``nlp-euler``: one formulation choice changed (stage-1
  objective ``log`` or ``caps``; the stage-1 point instead of the centre; the paper's Euler steps);
* ``paper``: the paper's formulation taken literally: objective (15), no floors but the token one, r uncapped,
  no centre stage, no bias/scale states, Euler steps (19);
* ``lp``: the linear SU start point alone (000 (21)-(22) as 001's LP);
* ``dr``: dead reckoning from the last fix before the outage with CAN speed and yaw rate.

The bar of issue 7: max error below 0.5 m in 95 % of placements.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.config import GpsSettings
from sumhe.errors import SumheError
from sumhe.estimator.batch import SuResult, estimate_batch, estimate_lp, model_for
from sumhe.estimator.grid import build_grid
from sumhe.geo import LocalFrame
from sumhe.io.fixtime import stamp_fix
from sumhe.messages import CanSample, GnssFix, Sample
from sumhe.model.su import integrate_odometry
from sumhe.settings import EstimationSettings, with_changes
from sumhe.sim import SimSettings, simulate
from sumhe.sim.drive import Drive

log = logging.getLogger(__name__)

METHODS = ("nlp", "nlp-nobias", "nlp-euler", "nlp-log", "nlp-caps", "nlp-nocentre", "paper", "lp", "dr")
DEFAULT_METHODS = ("nlp", "nlp-nobias", "paper", "lp", "dr")
PAPER_R_CAP_SIGMAS = 1e4


@dataclass(frozen=True, slots=True)
class ProtocolSettings:
    """One protocol run: the drive (``scenario``, ``seed``, ``duration_s``, ``gps_error``, ``antennas``), the
    window (epochs before, in and after the outage) and how many placements; ``bar_m`` is the error bar (m).
    With ``calibrated_can_delay`` the estimators get the simulated CAN sensor delay as ``can_delay_s`` (a
    calibration a real installation measures once)."""

    scenario: str = "offroad"
    seed: int = 1
    duration_s: float = 300.0
    gps_error: str = "rtk"
    placements: int = 24
    before: int = 10
    outage_epochs: int = 50
    after: int = 10
    bar_m: float = 0.5
    methods: tuple[str, ...] = DEFAULT_METHODS
    antennas: int = 1
    calibrated_can_delay: bool = True

    def __post_init__(self) -> None:
        for name in ("placements", "before", "outage_epochs", "after"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: must be >= 1, got {getattr(self, name)!r}")
        for m in self.methods:
            if m not in METHODS:
                raise ValueError(f"methods: unknown method {m!r} (known: {', '.join(METHODS)})")
        if self.antennas not in (1, 2):
            raise ValueError(f"antennas: must be 1 or 2, got {self.antennas!r}")

    @property
    def window(self) -> int:
        return self.before + self.outage_epochs + self.after


@dataclass(frozen=True, slots=True)
class Run:
    """One method on one placement: errors (m) of east/north over the window, status and IPOPT time (s)."""

    method: str
    placement: int
    label: str
    max_east: float
    max_north: float
    mean_east: float
    mean_north: float
    success: bool
    ipopt_s: float
    wall_s: float

    @property
    def max_m(self) -> float:
        return max(self.max_east, self.max_north)

    @property
    def mean_m(self) -> float:
        return 0.5 * (self.mean_east + self.mean_north)


@dataclass(frozen=True, slots=True)
class Window:
    """The samples of one placement (outage fixes removed), its epoch times (s) and outage mask."""

    start: int
    samples: list[Sample]
    epoch_t: NDArray[np.float64]
    outage: NDArray[np.bool_]
    label: str


def method_settings(method: str, base: EstimationSettings) -> EstimationSettings:
    """The estimator settings of an NLP method, derived from ``base``."""
    changes: dict[str, dict[str, object]] = {
        "nlp": {},
        "nlp-nobias": {"estimator.yaw_rate_bias": False, "estimator.speed_scale": False},
        "nlp-log": {"estimator.batch.objective": "log"},
        "nlp-caps": {"estimator.batch.objective": "caps"},
        "nlp-nocentre": {"estimator.batch.centre": "none"},
        "nlp-euler": {"estimator.discretisation": "euler"},
        "paper": {
            "estimator.batch.objective": "log",
            "estimator.batch.centre": "none",
            "estimator.batch.derived_floors": False,
            "estimator.r_cap_sigmas": PAPER_R_CAP_SIGMAS,
            "estimator.yaw_rate_bias": False,
            "estimator.speed_scale": False,
            "estimator.discretisation": "euler",
            "vehicle.antenna_lever": False,
        },
    }
    return with_changes(base, changes[method])


def label_motion(speed: NDArray[np.float64], yaw_rate: NDArray[np.float64]) -> str:
    """What the vehicle does (true speed m/s, yaw rate rad/s over the outage): stop, sharp, bend or straight."""
    if np.min(speed) < 0.5:
        return "stop"
    if np.max(np.abs(yaw_rate)) > 0.3:
        return "sharp"
    if np.max(np.abs(yaw_rate)) > 0.05:
        return "bend"
    return "straight"


def make_windows(drive: Drive, ps: ProtocolSettings, est: EstimationSettings) -> list[Window]:
    """``ps.placements`` windows evenly spaced over the drive, outage fixes removed."""
    gps = GpsSettings()
    fixes = [stamp_fix(f, gps) for f in drive.fixes(1)]
    second = [stamp_fix(dataclasses.replace(f, antenna=2), gps) for f in drive.fixes(2)] if ps.antennas == 2 else []
    can = sorted(drive.can_samples(), key=lambda s: s.t)
    can_t = np.array([s.t for s in can])
    n = len(fixes) - ps.window
    if n < 0:
        raise SumheError(f"drive too short: {len(fixes)} epochs, a window needs {ps.window}")
    starts = np.unique(np.linspace(1, n, ps.placements).astype(int))
    out = []
    for k0 in starts:
        sel = range(k0, k0 + ps.window)
        keep = [k for k in sel if not ps.before <= k - k0 < ps.before + ps.outage_epochs]
        epoch_t = np.array([fixes[k].t for k in sel])
        gnss: list[Sample] = [fixes[k] for k in keep] + [second[k] for k in keep if second]
        lo, hi = np.searchsorted(can_t, [epoch_t[0] + est.can.delay_s - 0.04, epoch_t[-1] + est.can.delay_s + 0.04])
        samples = sorted(gnss + can[lo:hi], key=lambda s: s.t)
        outage = np.zeros(ps.window, dtype=bool)
        outage[ps.before : ps.before + ps.outage_epochs] = True
        truth = drive.truth.at(epoch_t[outage])
        out.append(Window(int(k0), samples, epoch_t, outage, label_motion(truth.speed, truth.yaw_rate)))
    return out


def dead_reckoning(
    window: Window, est: EstimationSettings, frame: LocalFrame
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """East, north (m, in ``frame``) at the window's epochs: fixes where present; in the outage, CAN speed
    and yaw rate integrated from the last fix, azimuth from its course (else from the last two fixes)."""
    grid = build_grid(window.samples, model_for(est), est, frame)
    east = np.interp(window.epoch_t, grid.t, grid.y[:, 0])
    north = np.interp(window.epoch_t, grid.t, grid.y[:, 1])
    fixes = [s for s in window.samples if isinstance(s, GnssFix) and s.antenna == 1 and s.valid]
    before = [f for f in fixes if f.t <= window.epoch_t[window.outage][0]]
    last, prev = before[-1], before[-2]
    p_last, p_prev = frame.to_enu([last.lat_deg, prev.lat_deg], [last.lon_deg, prev.lon_deg])[:, :2]
    if last.course_rad is not None and (last.speed_mps or 0.0) >= est.gnss.course_min_speed_mps:
        phi = last.course_rad
    else:
        phi = math.atan2(p_last[0] - p_prev[0], p_last[1] - p_prev[1])
    can = [s for s in window.samples if isinstance(s, CanSample)]
    t0 = last.t
    pos = _integrate(can, est.can.delay_s, t0, p_last, phi, window.epoch_t[window.outage])
    east[window.outage], north[window.outage] = pos[:, 0], pos[:, 1]
    return east, north


def _integrate(
    can: Sequence[CanSample], delay: float, t0: float, p0: NDArray, phi0: float, times: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Dead reckoning at CAN rate from (t0, p0, phi0); positions (m) at ``times``."""
    speed = [(s.t - delay, s.value) for s in can if s.quantity == "speed"]
    yaw = [(s.t - delay, s.value) for s in can if s.quantity == "yaw_rate"]
    ts = np.array([t for t, _ in speed])
    vs = np.array([v for _, v in speed])
    ty = np.array([t for t, _ in yaw])
    wy = np.array([w for _, w in yaw])
    grid = np.union1d(np.arange(t0, times[-1] + 1e-9, 0.01), times)
    grid = grid[grid >= t0]
    east, north, _ = integrate_odometry(grid, np.interp(grid, ts, vs), np.interp(grid, ty, wy), p0[0], p0[1], phi0)
    return np.column_stack([np.interp(times, grid, east), np.interp(times, grid, north)])


def _errors(drive: Drive, window: Window, t: NDArray, east: NDArray, north: NDArray) -> tuple[float, ...]:
    """max and mean of (24) for east and north over the window's epochs (estimate interpolated to them)."""
    truth = drive.truth.at(window.epoch_t)
    de = np.abs(np.interp(window.epoch_t, t, east) - truth.east)
    dn = np.abs(np.interp(window.epoch_t, t, north) - truth.north)
    return float(de.max()), float(dn.max()), float(de.mean()), float(dn.mean())


def run_method(method: str, drive: Drive, window: Window, base: EstimationSettings) -> Run:
    """One method on one window; a solver error is a failed run with infinite error, never a crash."""
    t0 = time.perf_counter()
    ipopt_s, success = 0.0, True
    try:
        if method == "dr":
            east, north = dead_reckoning(window, base, drive.frame)
            t = window.epoch_t
        else:
            fn: Callable[..., SuResult] = estimate_lp if method == "lp" else estimate_batch
            res = fn(window.samples, base if method == "lp" else method_settings(method, base), frame=drive.frame)
            t, east, north, ipopt_s, success = res.t, res.east, res.north, res.ipopt_time_s, res.success
    except SumheError as e:
        log.warning("%s on placement %d failed: %s", method, window.start, e)
        return Run(method, window.start, window.label, *(math.inf,) * 4, False, 0.0, time.perf_counter() - t0)
    errs = _errors(drive, window, t, east, north)
    return Run(method, window.start, window.label, *errs, success, ipopt_s, time.perf_counter() - t0)


def run_protocol(ps: ProtocolSettings, est: EstimationSettings | None = None) -> list[Run]:
    """Simulate the drive and run every method on every placement."""
    est = est or EstimationSettings()
    sim = SimSettings(
        scenario=ps.scenario, seed=ps.seed, duration_s=ps.duration_s, gps_error=ps.gps_error, antennas=ps.antennas
    )
    drive = simulate(sim)
    est = with_changes(
        est,
        {
            "estimator.model": "su7" if ps.antennas == 2 else est.estimator.model,
            "can.delay_s": sim.can_sensor_delay_s if ps.calibrated_can_delay else est.can.delay_s,
        },
    )
    windows = make_windows(drive, ps, est)
    runs = []
    for w in windows:
        for m in ps.methods:
            runs.append(run_method(m, drive, w, est))
            log.info("%s %d %s max %.3f m", m, w.start, w.label, runs[-1].max_m)
    return runs


def summarise(runs: Sequence[Run], bar_m: float) -> list[dict[str, object]]:
    """Per method: median/p95/worst of max errors, mean of mean errors, share under ``bar_m``, IPOPT times."""
    out = []
    for m in dict.fromkeys(r.method for r in runs):
        rs = [r for r in runs if r.method == m]
        mx = np.array([r.max_m for r in rs])
        ip = np.array([r.ipopt_s for r in rs])
        out.append(
            {
                "method": m,
                "n": len(rs),
                "max_median_m": float(np.median(mx)),
                "max_p95_m": float(np.percentile(mx, 95, method="higher")),
                "max_worst_m": float(mx.max()),
                "mean_m": float(np.mean([r.mean_m for r in rs])),
                "under_bar": float(np.mean(mx < bar_m)),
                "failed": sum(not r.success for r in rs),
                "ipopt_mean_s": float(ip.mean()),
                "ipopt_p95_s": float(np.percentile(ip, 95, method="higher")),
            }
        )
    return out


def format_report(runs: Sequence[Run], ps: ProtocolSettings) -> str:
    """The per-placement table (max/mean of east and north errors per method) and the summary."""
    methods = list(dict.fromkeys(r.method for r in runs))
    starts = list(dict.fromkeys(r.placement for r in runs))
    by = {(r.method, r.placement): r for r in runs}
    head = f"{'epoch':>6} {'motion':<8} " + " ".join(f"{m:>19}" for m in methods)
    lines = [
        f"paper 000 protocol: {ps.scenario} seed {ps.seed}, {ps.gps_error} GNSS, outage {ps.outage_epochs} epochs, "
        f"N_B={ps.before} N_A={ps.after}, {len(starts)} placements; cells: max / mean error (m) of (px1, py1)",
        head,
    ]
    for k in starts:
        label = by[(methods[0], k)].label
        cells = " ".join(f"{by[(m, k)].max_m:>9.3f} /{by[(m, k)].mean_m:>7.3f} " for m in methods)
        lines.append(f"{k:>6} {label:<8} {cells}")
    bar = f"<{ps.bar_m:g} m"
    lines.append("")
    lines.append(
        f"{'method':<13} {'max med':>8} {'max p95':>8} {'worst':>8} {'mean':>7} {bar:>7} "
        f"{'failed':>6} {'ipopt mean':>10} {'ipopt p95':>9}"
    )
    for s in summarise(runs, ps.bar_m):
        lines.append(
            f"{s['method']:<13} {s['max_median_m']:>8.3f} {s['max_p95_m']:>8.3f} {s['max_worst_m']:>8.3f} "
            f"{s['mean_m']:>7.3f} {100 * s['under_bar']:>6.0f}% {s['failed']:>6d} "  # type: ignore[operator]
            f"{s['ipopt_mean_s']:>9.3f}s {s['ipopt_p95_s']:>8.3f}s"
        )
    return "\n".join(lines)
