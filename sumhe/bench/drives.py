"""The drives of ``sumhe bench`` (``peers``): simulated and recorded drives with outages placed on them.

On each drive the bench places one outage of every length (5, 10, 30, 55 s) in an order and at gaps drawn from the
drive's seed, after a warm-up, with GNSS for at least ``recover_s`` between them; the fixes whose measurement time
falls inside an outage are removed (a silent receiver). Each placement is labelled by the truth's motion during it
(:func:`sumhe.bench.protocol.label_motion`: stop, sharp turn, bend, straight). Recorded drives are directories with
``drive.log``, ``drive.nmea`` and a ``truth.csv`` in the simulator's format, replayed through
:func:`sumhe.io.replay.log_samples`. Fixes are stamped once with their measurement time
(:func:`~sumhe.io.fixtime.stamp_fix`) and merged with the CAN samples by time, as a replay merges them. The config
has a fixed datum at the truth's frame; on simulated drives the CAN sensor delay is calibrated
(``sensors.can.delay_s`` = the simulator's delay) for every estimator alike.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sumhe.bench import metrics
from sumhe.bench.protocol import label_motion
from sumhe.config import Config, DatumSettings
from sumhe.errors import ConfigError
from sumhe.estimator.registry import estimator_names
from sumhe.geo import LocalFrame
from sumhe.io.fixtime import stamp_fix
from sumhe.io.replay import log_samples, merge_by_time
from sumhe.messages import GnssFix, Sample
from sumhe.settings import with_changes
from sumhe.sim import SimSettings, Truth, load_settings, load_truth, simulate
from sumhe.sim.settings import GPS_ERROR_MODELS, SCENARIO_NAMES

log = logging.getLogger(__name__)

RECORDED_FILES = ("drive.log", "drive.nmea", "truth.csv")
MAX_DURATION_S = 3600.0


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
