"""``sumhe bench tune``: the search and evaluation on simulated drives that tuned the peers' noise levels.

The tuned values are the defaults of the peers' tables (:mod:`sumhe.settings.peers`). They come from
``sumhe bench tune search NAME`` (a coordinate-wise grid search on *training* drives, seeds 100-105: never the test
seeds 1-99) minimising

    J = mean over drives of the mean position error at outage epochs
      + mean over drives of the mean position error at epochs with a fix used,

and ``sumhe bench tune evaluate`` reports the accuracy on *test* drives. Each drive is a simulated drive
(:mod:`sumhe.sim`, GPS error model ``walk``) with a 10 s and a 30 s outage placed at random (from the seed); the
fixes go through :class:`~sumhe.frontend.fixes.FixConverter` with the datum of the drive and are stamped with their
UTC time of fix, and every sample is pushed as the service would. See ``docs/baselines.md`` for the procedure and
the results.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sumhe.baseline.dead_reckoning import DeadReckoning
from sumhe.baseline.ekf import Ekf
from sumhe.baseline.imm import Imm
from sumhe.baseline.particle import ParticleFilter
from sumhe.baseline.rts import Rts
from sumhe.baseline.stream import RecursiveEstimator
from sumhe.baseline.ukf import Ukf
from sumhe.config import DatumSettings, GpsSettings
from sumhe.estimator.base import StateEstimate
from sumhe.estimator.registry import estimator_class
from sumhe.frontend.fixes import FixConverter, LocalFix
from sumhe.io.fixtime import stamp_fix
from sumhe.messages import CanSample
from sumhe.settings import CanModel, EstimationSettings, NoiseSettings
from sumhe.sim import Drive, SimSettings, simulate

log = logging.getLogger(__name__)

# ---- drives -----------------------------------------------------------------------------------------------------

SCENARIOS = ("urban", "highway", "offroad")
TRAINING_SEEDS = range(100, 106)
TEST_SEEDS = range(1, 7)
OUTAGE_LENGTHS_S = (10.0, 30.0)
WARM_UP_S = 20.0
"""Estimates of the first seconds of a drive (the filters converging) are left out of the figures."""


@dataclass(frozen=True, eq=False)
class Case:
    """One drive as the estimators see it: the time-ordered samples (fixes already local), and its truth."""

    drive: Drive
    samples: list[LocalFix | CanSample]

    @property
    def name(self) -> str:
        s = self.drive.settings
        return f"{s.scenario}-{s.seed}"


def make_case(seed: int, duration_s: float = 150.0, gps_error: str = "walk") -> Case:
    """The drive of ``seed``: scenario by seed, a 10 s and a 30 s outage at places drawn from the seed.

    Fixes are stamped with their UTC time of fix and merged in measurement order, as a replay does
    (:func:`sumhe.io.replay.log_samples`).
    """
    rng = np.random.default_rng(seed)
    short = rng.uniform(WARM_UP_S + 5.0, 0.4 * duration_s - 10.0)
    long = rng.uniform(0.45 * duration_s, duration_s - 35.0)
    s = SimSettings(
        scenario=SCENARIOS[seed % len(SCENARIOS)],
        seed=seed,
        duration_s=duration_s,
        gps_error=gps_error,
        outages=((round(short, 1), OUTAGE_LENGTHS_S[0]), (round(long, 1), OUTAGE_LENGTHS_S[1])),
    )
    return case_from(s)


def case_from(s: SimSettings) -> Case:
    """The simulated drive of ``s`` as the estimators see it."""
    drive = simulate(s)
    converter = FixConverter(DatumSettings("fixed", s.datum_lat_deg, s.datum_lon_deg, s.datum_alt_m))
    local = [converter.convert(stamp_fix(f, GpsSettings())) for f in drive.fixes()]
    can = [c for c in drive.can_samples() if c.quantity in ("speed", "yaw_rate")]
    return Case(drive, list(heapq.merge(local, can, key=lambda sample: sample.t)))


def case_settings(case: Case) -> EstimationSettings:
    """The estimator settings for a case: defaults with the CAN sensor delay calibrated (as the protocol does)."""
    return EstimationSettings(can=CanModel(delay_s=case.drive.settings.can_sensor_delay_s))


# ---- running and scoring ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Run:
    """One estimator over one case: every estimate, which of them are GNSS epochs, the time of each push (ms)."""

    estimates: list[StateEstimate]
    is_epoch: list[bool]
    push_ms: np.ndarray

    @property
    def epochs(self) -> list[StateEstimate]:
        """The estimates at GNSS epochs (fixes and outage epochs), without the CAN-rate ones."""
        return self.select(self.estimates)

    def select(self, estimates: Sequence[StateEstimate]) -> list[StateEstimate]:
        """The epochs of a list parallel to ``estimates`` (e.g. the RTS smoother's)."""
        return [e for e, keep in zip(estimates, self.is_epoch, strict=True) if keep]


def run_case(estimator: RecursiveEstimator, case: Case) -> Run:
    """Push every sample of ``case``; an estimate is a CAN-rate one when a CAN sample returned it at its time."""
    estimates: list[StateEstimate] = []
    is_epoch: list[bool] = []
    push_ms = np.empty(len(case.samples))
    for i, sample in enumerate(case.samples):
        t0 = time.perf_counter()
        out = estimator.push(sample)
        push_ms[i] = 1000.0 * (time.perf_counter() - t0)
        estimates.extend(out)
        is_epoch.extend(isinstance(sample, LocalFix) or e.t != sample.t for e in out)
    return Run(estimates, is_epoch, push_ms)


@dataclass(frozen=True)
class Errors:
    """Horizontal position errors (m) of one run, by kind: outage epochs per outage length, epochs with GPS."""

    outage: dict[float, np.ndarray]
    gps: np.ndarray


def position_errors(case: Case, epochs: Sequence[StateEstimate]) -> Errors:
    """Errors against the truth at each epoch's time (after the warm-up)."""
    s = case.drive.settings
    t = np.array([e.t for e in epochs])
    truth = case.drive.truth.at(t)
    err = np.hypot(
        np.array([e.east_m for e in epochs]) - truth.east, np.array([e.north_m for e in epochs]) - truth.north
    )
    rel = t - s.start_unix_s
    late = rel >= WARM_UP_S
    ok = np.array([e.gps == "ok" for e in epochs]) & late
    outage = {}
    for start, length in s.outages:
        inside = (rel >= start) & (rel < start + length) & np.array([e.gps == "outage" for e in epochs])
        outage[length] = np.concatenate([outage.get(length, np.empty(0)), err[inside]])
    return Errors(outage, err[ok])


def objective(errors: Sequence[Errors]) -> float:
    """J of the module docstring."""
    outage = np.mean([np.mean(np.concatenate(list(e.outage.values()))) for e in errors])
    return float(outage + np.mean([np.mean(e.gps) for e in errors]))


# ---- the search -------------------------------------------------------------------------------------------------

SEARCH_FACTORS = (0.25, 0.5, 2.0, 4.0)
"""Each sweep tries every parameter at these multiples of its current value."""

SEARCH_PARAMETERS: dict[str, tuple[str, ...]] = {
    "ekf": ("pos_rw", "heading_rw", "speed_rw", "yaw_rate_rw", "bias_rw", "gps_scale", "course_rad"),
    "ukf": ("pos_rw", "heading_rw", "yaw_rate_rw", "gps_scale"),
    "pf": ("pos_rw", "heading_rw", "bias_rw", "scale_rw", "gps_scale", "course_rad"),
    "gtsam-fls": (
        "pos_rw",
        "heading_rw",
        "can_speed_mps",
        "can_yaw_rate_rps",
        "bias_rw",
        "scale_rw",
        "gps_scale",
        "sog_scale",
        "course_rad",
    ),
    "mskf-em": ("pos_rw", "heading_rw", "bias_rw", "scale_rw", "gps_scale", "course_rad"),
    "sr-upf": ("pos_rw", "heading_rw", "bias_rw", "scale_rw", "gps_scale", "course_rad"),
    "imm": ("straight.yaw_rate_rw", "straight.heading_rw", "straight.pos_rw", "turn.yaw_rate_rw", "turn.heading_rw"),
}
"""What the search tunes per estimator (an estimator not tuned yet starts from the EKF's values). ``gtsam-fls``: its
odometry's model errors and CAN sigmas, the calibration's random walks, the GNSS position, speed-over-ground and course
sigmas; not ``speed_rw`` and ``yaw_rate_rw``, which only widen a held CAN value (the training drives have no CAN gaps).
"""

SEARCH_BOUNDS: dict[str, tuple[float, float]] = {
    "pos_rw": (1e-5, 1.0),
    "heading_rw": (1e-6, 0.1),
    "speed_rw": (1e-3, 10.0),
    "yaw_rate_rw": (1e-4, 1.0),
    "bias_rw": (1e-7, 1e-2),
    "scale_rw": (1e-7, 1e-2),
    "can_speed_mps": (0.005, 1.0),
    "can_yaw_rate_rps": (2e-4, 0.05),
    "gps_scale": (0.5, 10.0),
    "sog_scale": (0.5, 10.0),
    "course_rad": (1e-4, 0.2),
}
"""Where the search may go, by the parameter's field name (``turn.heading_rw`` is a ``heading_rw``), SI units: what
real vehicles and receivers allow. A GNSS sigma at most halved (a receiver is not twice as good as it says), CAN
sigmas from a quantum's rounding to 1 m/s and 3 deg/s, random walks from negligible to far beyond a real sensor's."""

PEER_TABLES = {"gtsam-fls": "gtsam_fls", "mskf-em": "mskf_em", "sr-upf": "sr_upf"}
"""The peers built from their table (``[estimator.NAME]``): the search sets its ``noise`` and the fields of
``TABLE_FIELDS``."""
TABLE_FIELDS = {"gtsam-fls": ("sog_scale",)}


def candidates(param: str, current: float, factors: Sequence[float] = SEARCH_FACTORS) -> list[float]:
    """The values a sweep tries for ``param`` at ``current``: ``factors`` times it, within its bounds."""
    lo, hi = SEARCH_BOUNDS[param.rpartition(".")[2]]
    return [current * f for f in factors if lo <= current * f <= hi]


def start_values(name: str, settings: EstimationSettings | None = None) -> dict[str, Any]:
    """Where the search of ``name`` starts: the current defaults of its table (for the IMM, its two models and the
    sojourn times, which are paper 002's and not searched)."""
    table = (settings or EstimationSettings()).estimator
    if name == "imm":
        return {
            "straight": table.imm.straight,
            "turn": table.imm.turn,
            "sojourn_straight_s": table.imm.sojourn_straight_s,
            "sojourn_turn_s": table.imm.sojourn_turn_s,
        }
    if name in PEER_TABLES:
        peer = getattr(table, PEER_TABLES[name])
        return {"noise": peer.noise, **{key: getattr(peer, key) for key in TABLE_FIELDS.get(name, ())}}
    noise = {"dead-reckoning": NoiseSettings(), "pf": table.pf.noise, "ukf": table.ukf, "rts": table.rts}
    return {"noise": noise.get(name, table.ekf)}


def with_value(values: dict[str, Any], param: str, value: float) -> dict[str, Any]:
    """``values`` with one parameter (``field``, ``model.field`` or a top-level key) set."""
    out = dict(values)
    if "." in param:
        model, field = param.split(".")
        out[model] = dataclasses.replace(out[model], **{field: value})
    elif param in out:
        out[param] = value
    else:
        out["noise"] = dataclasses.replace(out["noise"], **{param: value})
    return out


def get_value(values: dict[str, Any], param: str) -> float:
    if "." in param:
        model, field = param.split(".")
        return float(getattr(values[model], field))
    if param in values:
        return float(values[param])
    return float(getattr(values["noise"], param))


def build(name: str, settings: EstimationSettings, values: dict[str, Any] | None = None) -> RecursiveEstimator:
    """Estimator ``name`` with the given settings and search values (the tuned defaults when None)."""
    if values is None:
        values = start_values(name, settings)
    if name == "imm":
        return Imm(
            settings,
            models=(values["straight"], values["turn"]),
            sojourn_s=(values["sojourn_straight_s"], values["sojourn_turn_s"]),
        )
    if name in PEER_TABLES:  # the registry imports it (GTSAM only when asked for: the optional ``sumhe[peers]``)
        table = dataclasses.replace(getattr(settings.estimator, PEER_TABLES[name]), **values)
        return estimator_class(name)(settings, table)  # type: ignore[no-any-return]
    classes: dict[str, Callable[..., RecursiveEstimator]] = {
        "dead-reckoning": DeadReckoning,
        "ekf": Ekf,
        "rts": Rts,
        "ukf": Ukf,
        "pf": ParticleFilter,
    }
    return classes[name](settings, noise=values["noise"])


def score(name: str, values: dict[str, Any], cases: Sequence[Case]) -> float:
    return objective([position_errors(c, run_case(build(name, case_settings(c), values), c).epochs) for c in cases])


def search(
    name: str,
    cases: Sequence[Case],
    sweeps: int,
    write: Callable[[str], None],
    params: Sequence[str] | None = None,
    start: dict[str, Any] | None = None,
    factors: Sequence[float] = SEARCH_FACTORS,
) -> dict[str, Any]:
    """Coordinate-wise grid search of ``params`` (default ``SEARCH_PARAMETERS[name]``) within ``SEARCH_BOUNDS``,
    from ``start`` (default: the current defaults), trying ``factors`` times each value in turn."""
    values = start if start is not None else start_values(name)
    best = score(name, values, cases)
    write(f"{name}: start J = {best:.4f} m")
    for sweep in range(sweeps):
        improved = False
        for param in params or SEARCH_PARAMETERS[name]:
            for value in candidates(param, get_value(values, param), factors):
                candidate = with_value(values, param, value)
                try:
                    j = score(name, candidate, cases)
                except ValueError as e:
                    write(f"  {param} = {value:.4g}: invalid ({e})")
                    continue
                if j < best - 1e-4:
                    best, values, improved = j, candidate, True
                    write(f"  sweep {sweep + 1}: {param} = {value:.4g} -> J = {j:.4f} m")
        if not improved:
            break
    write(f"{name}: best J = {best:.4f} m")
    return values


# ---- the evaluation ---------------------------------------------------------------------------------------------


def summary(errors: np.ndarray) -> tuple[float, float, float]:
    """Mean, 95th percentile and maximum (NaN when empty)."""
    if errors.size == 0:
        return math.nan, math.nan, math.nan
    return float(errors.mean()), float(np.percentile(errors, 95)), float(errors.max())


def evaluate(names: Sequence[str], cases: Sequence[Case], write: Callable[[str], None]) -> None:
    """A table of position errors per estimator over ``cases`` (the RTS also smoothed)."""
    head = "".join(f" | {f'outage {int(L)} s':^20}" for L in OUTAGE_LENGTHS_S)
    write(f"{'estimator':<15}{head} | {'with GPS':^20} | ms per sample")
    write(f"{'':<15}" + " | mean   p95    max   " * (len(OUTAGE_LENGTHS_S) + 1) + " | mean   p99    max")
    for name in names:
        rows: dict[str, list[Errors]] = {name: []}
        ms = []
        for case in cases:
            estimator = build(name, case_settings(case))
            run = run_case(estimator, case)
            ms.append(run.push_ms)
            rows[name].append(position_errors(case, run.epochs))
            if name == "rts":
                smoothed = run.select(estimator.smoothed())  # type: ignore[attr-defined]
                rows.setdefault("rts-smoothed", []).append(position_errors(case, smoothed))
        timing = np.concatenate(ms)
        cost = f"{timing.mean():6.3f} {np.percentile(timing, 99):6.3f} {timing.max():6.2f}"
        for label, errs in rows.items():
            cells = [summary(np.concatenate([e.outage[L] for e in errs])) for L in OUTAGE_LENGTHS_S]
            cells.append(summary(np.concatenate([e.gps for e in errs])))
            text = "".join(" | " + " ".join(f"{v:6.2f}" for v in c) for c in cells)
            write(f"{label:<15}{text} | {cost}")


def _seeds(text: str) -> list[int]:
    """``"100-105"`` or ``"1,3,5"`` -> seeds."""
    out: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.partition("-")
        out.extend(range(int(lo), int(hi) + 1) if sep else [int(lo)])
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``sumhe bench tune {search,evaluate} ...``."""
    sub = parser.add_subparsers(dest="command", required=True, metavar="{search,evaluate}")
    p_search = sub.add_parser("search", help="grid-search one estimator's noise on training drives")
    p_search.add_argument("estimator", choices=sorted(SEARCH_PARAMETERS))
    p_search.add_argument("--sweeps", type=int, default=2)
    p_search.add_argument("--params", help="comma-separated subset of the estimator's searched parameters")
    p_search.add_argument(
        "--factors",
        default=",".join(f"{f:g}" for f in SEARCH_FACTORS),
        help="multiples of each value a sweep tries (a smaller grid for a slow estimator: 0.5,2)",
    )
    p_eval = sub.add_parser("evaluate", help="position errors of the estimators on test drives")
    p_eval.add_argument("--estimators", default="dead-reckoning,ekf,rts,ukf,pf,imm")
    for p, seeds in ((p_search, TRAINING_SEEDS), (p_eval, TEST_SEEDS)):
        p.add_argument("--seeds", default=f"{seeds.start}-{seeds.stop - 1}", help="e.g. 100-105 or 1,2,7")
        p.add_argument("--duration", type=float, default=150.0, help="drive length (s)")
        p.add_argument("--gps-error", default="walk", help="GPS error model of the simulator")
        p.set_defaults(_parser=p)


def run(args: argparse.Namespace, write: Callable[[str], None]) -> int:
    """Search (printing the table to put under ``[estimator.NAME]``) or evaluate; ``write`` prints a line."""
    seeds = _seeds(args.seeds)
    if args.command == "search" and set(seeds) & set(range(1, 100)):
        args._parser.error("the search must not see the test seeds 1-99")
    cases = [make_case(s, args.duration, args.gps_error) for s in seeds]
    if args.command == "search":
        params = args.params.split(",") if args.params else None
        unknown = set(params or ()) - set(SEARCH_PARAMETERS[args.estimator])
        if unknown:
            args._parser.error(f"--params: {args.estimator} searches {', '.join(SEARCH_PARAMETERS[args.estimator])}")
        factors = [float(f) for f in args.factors.split(",")]
        values = search(args.estimator, cases, args.sweeps, write, params, factors=factors)
        for key, value in values.items():
            write(f"{key} = {value!r}")
    else:
        evaluate(args.estimators.split(","), cases, write)
    return 0
