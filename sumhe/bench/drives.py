"""The drives of ``sumhe bench`` (``peers``): simulated drives of each profile with outages placed on them.

Profiles (:mod:`sumhe.sim.profiles`): ``kind`` drives for every scenario x GNSS error model x seed, ``realistic``
drives (every real-car error drawn from the seed: GNSS clock offset, 1 Hz fixes, OBD-II speed, production DBC
quanta, lever arm, heavy-tailed GNSS errors, ...) for every scenario x seed. On each drive the bench places one
outage of every length (5, 10, 30, 55 s) in an order and at gaps drawn from the drive's seed, after a warm-up, with
GNSS for at least ``recover_s`` between them; the fixes whose measurement time falls inside an outage are removed
(a silent receiver). Each placement is labelled by the truth's motion during it
(:func:`sumhe.bench.protocol.label_motion`: stop, sharp turn, bend, straight). Fixes are stamped once with their
measurement time (:func:`~sumhe.io.fixtime.stamp_fix`) and merged with the CAN samples by time, as a replay merges
them. The config has a fixed datum at the truth's frame and the CAN sensor delay calibrated (``sensors.can.delay_s``
= the simulator's chassis-sensor delay) for every estimator alike; on a realistic drive also the quanta of the
signals its own ``config.toml`` maps in its own DBC (:func:`drive_quanta`: the estimators get the samples decoded).
Recorded drives without a truth are :mod:`sumhe.bench.recorded`'s.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from sumhe.bench import metrics
from sumhe.bench.protocol import label_motion
from sumhe.config import Config, DatumSettings
from sumhe.estimator.registry import estimator_names
from sumhe.geo import LocalFrame
from sumhe.io.can import si_factor
from sumhe.io.fixtime import stamp_fix
from sumhe.io.replay import merge_by_time
from sumhe.messages import GnssFix, Sample
from sumhe.settings import EstimationSettings, SensorSettings, with_changes
from sumhe.sim import PROFILES, SimSettings, Truth, profile_settings, simulate
from sumhe.sim.production import signal_specs, vehicle_db
from sumhe.sim.settings import GPS_ERROR_MODELS, SCENARIO_NAMES

log = logging.getLogger(__name__)

WithCan = TypeVar("WithCan", SensorSettings, EstimationSettings)

MAX_DURATION_S = 3600.0


@dataclass(frozen=True, slots=True)
class PeersSettings:
    """What ``sumhe bench`` runs. Times in s. ``estimators`` empty: every registered estimator. ``gps_errors``
    applies to the ``kind`` profile (a realistic drive draws its own)."""

    scenarios: tuple[str, ...] = SCENARIO_NAMES
    profiles: tuple[str, ...] = ("kind", "realistic")
    gps_errors: tuple[str, ...] = ("uniform", "gaussian", "walk")
    seeds: tuple[int, ...] = (1, 2, 3)
    duration_s: float = 240.0
    outage_lengths_s: tuple[float, ...] = (5.0, 10.0, 30.0, 55.0)
    recover_s: float = 15.0
    warm_up_s: float = 20.0
    estimators: tuple[str, ...] = ()
    timeout_s: float = 600.0
    heading_min_speed_mps: float = 2.0

    def __post_init__(self) -> None:
        for name, value, known in (
            ("scenarios", self.scenarios, SCENARIO_NAMES),
            ("gps_errors", self.gps_errors, GPS_ERROR_MODELS),
            ("profiles", self.profiles, tuple(PROFILES)),
        ):
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
        if self.drive_count() and self.duration_s < needed:
            raise ValueError(f"duration_s: {self.duration_s:g} s cannot hold the outages, need {needed:g} s")

    @classmethod
    def quick(cls) -> PeersSettings:
        """About three minutes (one core): a 120 s urban drive of each profile (walk GPS errors on the kind one),
        outages of 5, 10 and 30 s, each run limited to a minute (a run that takes longer is a failed run)."""
        return cls(
            scenarios=("urban",),
            gps_errors=("walk",),
            seeds=(1,),
            duration_s=120.0,
            outage_lengths_s=(5.0, 10.0, 30.0),
            recover_s=10.0,
            timeout_s=60.0,
        )

    def names(self) -> tuple[str, ...]:
        """The estimators to run: by default every one whose optional packages are installed."""
        return self.estimators or estimator_names(available_only=True)

    def drive_count(self) -> int:
        kind = len(self.gps_errors) if "kind" in self.profiles else 0
        return len(self.scenarios) * len(self.seeds) * (kind + ("realistic" in self.profiles))


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
    profile: str
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


def drive_quanta(settings: SimSettings) -> dict[str, float]:
    """The SI quanta of the drive's mapped CAN speed and yaw rate, from its own DBC (what ``with_signal_quanta``
    reads from its ``config.toml``'s DBC, without the files)."""
    db, specs = vehicle_db(settings), signal_specs(settings)
    out = {}
    for quantity in ("speed", "yaw_rate"):
        spec = specs[quantity]
        signal = db.get_message_by_name(spec.message).get_signal_by_name(spec.signal)
        out[quantity] = abs(float(signal.scale) * (si_factor(signal.unit, quantity) or 1.0) * spec.scale)
    return out


def with_drive_can(settings: SimSettings, target: WithCan) -> WithCan:
    """``target`` (sensor or estimation settings: anything with a ``can`` table) with the drive's CAN quanta
    (:func:`drive_quanta`) and its sensors' ages as calibrated: the chassis sensors' delay, and where the speed is
    an OBD-II reply's, how much older than that it is."""
    quanta = drive_quanta(settings)
    return with_changes(
        target,
        {
            "can.delay_s": settings.can_sensor_delay_s,
            "can.speed_delay_s": settings.speed_age_beyond_s,
            "can.speed_resolution_mps": quanta["speed"],
            "can.yaw_rate_resolution_rps": quanta["yaw_rate"],
        },
    )


def simulated_drive(
    scenario: str, gps_error: str, seed: int, ps: PeersSettings, base: Config, profile: str = "kind"
) -> BenchDrive:
    """A simulated drive (no outages simulated: the bench places them) and its outages; a realistic one with its
    own mapping and quanta (``gps_error`` is its own then)."""
    if profile == "kind":
        sim = SimSettings(scenario=scenario, seed=seed, duration_s=ps.duration_s, gps_error=gps_error)
    else:
        sim = profile_settings(profile, seed, scenario=scenario, duration_s=ps.duration_s)
    drive = simulate(sim)
    config = drive_config(base, drive.frame, sim.can_sensor_delay_s)
    if profile != "kind":  # the samples come decoded: of its config the estimators need the quanta
        config = dataclasses.replace(config, sensors=with_drive_can(sim, config.sensors))
    rng = np.random.default_rng([seed, SCENARIO_NAMES.index(scenario), GPS_ERROR_MODELS.index(sim.gps_error)])
    plan = outage_plan(ps.duration_s, ps.outage_lengths_s, ps.recover_s, ps.warm_up_s, rng)
    outages = place_outages(drive.truth, plan, sim.start_unix_s)
    fixes = [stamp_fix(f, config.gps) for f in drive.fixes()]
    samples = without_fixes_in(merge_by_time(drive.can_samples(), fixes), outages)
    name = f"{scenario}-{gps_error}-{seed}" if profile == "kind" else f"{profile}-{scenario}-{seed}"
    scored_from = sim.start_unix_s + ps.warm_up_s
    return BenchDrive(name, profile, samples, drive.truth, config, with_gps_back(outages, samples), scored_from)


def drives(ps: PeersSettings, base: Config) -> Iterable[BenchDrive]:
    """Every simulated drive of the bench, built when needed: the kind profile's, then the realistic one's."""
    for profile in ps.profiles:
        for scenario in ps.scenarios:
            for gps_error in ps.gps_errors if profile == "kind" else ("",):
                for seed in ps.seeds:
                    yield simulated_drive(scenario, gps_error, seed, ps, base, profile)
