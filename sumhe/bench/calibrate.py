"""``sumhe bench calibrate``: ``sumhe calibrate`` on realistic simulated drives, against the installation parameters
each drive was simulated with (``scenario.toml``'s ``[calibration]``), with issue 12's targets.

Each drive is simulated (``realistic`` profile: its draws of every sensor error), written to a folder and read back
as ``sumhe calibrate DIR/drive.log --nmea DIR/drive.nmea --config DIR/config.toml`` reads it, with the drive's CAN
delay configured as the benchmarks configure it (``[sensors.can] delay_s`` = the chassis sensors' age).

Like with like (:func:`comparable_truth`): the simulator's ``gps_time_offset_s`` is the fix's true time against the
CAN clock; calibrate's is against the CAN speed taken to be ``delay_s`` old, so the truth it is compared with adds
the speed's own age beyond ``delay_s`` (an OBD-II reply's ``obd_delay_s``; 0 for a broadcast speed, whose age is
the chassis sensors'). The simulator's ``can_delay_s`` is the chassis sensors' age (not observable from GNSS and
CAN); calibrate's is the speed's age minus the yaw rate's, compared with ``obd_delay_s - can_sensor_delay_s`` on
OBD drives and 0 on the others. The CAN frames' host timestamps come a few ms after the bus (USB reads) for both.

Where the drive's speed is OBD-II's whole km/h, the speed's rounding is compared too: the one calibrate writes
(``speed_rounding``) and the one the on-line sensor check says as the drive is replayed (:func:`online_rounding`),
against the simulator's ``obd_rounding``.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from sumhe.bench.reprocess import replay_drive
from sumhe.calibration import KEYS, Calibration, calibrate, read_signals
from sumhe.config import Config, load_config
from sumhe.estimator.registry import make_estimator
from sumhe.frontend.can import CAN_USED
from sumhe.io.replay import RecordedDrive
from sumhe.sim import SimSettings, simulate_profile, write_drive
from sumhe.sim.production import CONFIG_FILE
from sumhe.sim.settings import SCENARIO_NAMES

TARGETS: dict[str, tuple[float, bool]] = {
    "gps_time_offset_s": (0.03, False),
    "speed_scale": (0.002, True),
    "yaw_rate_bias_dps": (0.05, False),
    "yaw_rate_scale": (0.02, True),
}
"""Issue 12's targets: parameter -> (tolerance, relative). The yaw-rate scale's applies where the drive turns
(where calibrate determines it)."""


@dataclass(frozen=True, slots=True)
class CalibrateBenchSettings:
    """Drives: ``scenarios`` x ``seeds`` of ``duration_s`` s each, realistic profile."""

    scenarios: tuple[str, ...] = SCENARIO_NAMES
    seeds: tuple[int, ...] = (1, 2, 3, 4)
    duration_s: float = 600.0

    def __post_init__(self) -> None:
        for s in self.scenarios:
            if s not in SCENARIO_NAMES:
                raise ValueError(f"scenarios: unknown {s!r} (known: {', '.join(SCENARIO_NAMES)})")
        if not self.seeds or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in self.seeds):
            raise ValueError(f"seeds: need integers >= 0, got {self.seeds!r}")
        if not 60.0 <= self.duration_s <= 3600.0:
            raise ValueError(f"duration_s: must be within [60, 3600] s, got {self.duration_s!r}")

    @classmethod
    def quick(cls) -> CalibrateBenchSettings:
        """A minute or so: an urban and a highway drive of 300 s."""
        return cls(scenarios=("urban", "highway"), seeds=(1,), duration_s=300.0)


def comparable_truth(settings: SimSettings, calibration: Mapping[str, float], delay_s: float) -> dict[str, float]:
    """The drive's true parameters in the terms calibrate reports them with ``[sensors.can] delay_s = delay_s``
    (see the module docstring)."""
    speed_age = settings.can_sensor_delay_s + settings.speed_age_beyond_s
    return {
        "gps_time_offset_s": calibration["gps_time_offset_s"] + speed_age - delay_s,
        "speed_scale": calibration["speed_scale"],
        "yaw_rate_bias_dps": calibration["yaw_rate_bias_dps"],
        "yaw_rate_scale": calibration["yaw_rate_scale"],
        "can_delay_s": settings.speed_age_beyond_s,
    }


def error(key: str, value: float, truth: float) -> float:
    """The estimate's error: relative for the scales, absolute otherwise."""
    return value / truth - 1.0 if key in ("speed_scale", "yaw_rate_scale") else value - truth


@dataclass(frozen=True)
class DriveResult:
    """One drive: its name and kind, calibrate's result and the truth it is compared with."""

    name: str
    kind: str
    calibration: Calibration
    truth: dict[str, float]
    rounding: str | None = None
    """How the drive's CAN speed was made whole km/h (``sensors.can.speed_rounding``'s words) where it is OBD-II's;
    None for a broadcast speed (a quantum too fine to tell)."""
    online: str | None = None
    """What the on-line check said of it over the drive (:func:`online_rounding`); None: not told, or no OBD-II
    speed."""

    def errors(self) -> dict[str, float | None]:
        out: dict[str, float | None] = {}
        for key, p in self.calibration.parameters().items():
            out[key] = None if p.value is None else error(key, p.value, self.truth[key])
        return out


def calibrate_drive(scenario: str, seed: int, duration_s: float, directory: Path) -> DriveResult:
    """Simulate one realistic drive into ``directory``, calibrate it as the command would, compare."""
    drive = simulate_profile("realistic", seed, scenario=scenario, duration_s=duration_s)
    write_drive(drive, directory)
    delay = drive.calibration["can_delay_s"]
    config = load_config(directory / CONFIG_FILE, env={}, overrides={"sensors.can.delay_s": delay})
    signals = read_signals(config, directory / "drive.log", directory / "drive.nmea")
    cal = calibrate(signals, delay)
    s = drive.settings
    kind = f"{s.speed_source} speed, {s.gps_rate_hz:g} Hz GNSS"
    truth = comparable_truth(s, drive.calibration, delay)
    rounding = ("truncate" if s.obd_rounding == "floor" else "round") if s.speed_source == "obd" else None
    online = online_rounding(config, directory) if rounding is not None else None
    return DriveResult(f"{scenario}-{seed}", kind, cal, truth, rounding, online)


def online_rounding(config: Config, directory: Path) -> str | None:
    """What the on-line sensor check says of the CAN speed's rounding over the drive in ``directory``, run as
    ``sumhe replay`` runs it with ``config`` (``speed_rounding = "round"``, the default) and dead reckoning (the
    check is the front-end's, alike for every estimator): ``"truncate"`` (said to be truncated), ``"round"``
    (confirmed), or None (not told by the drive's end)."""
    drive = RecordedDrive(config, directory / "drive.log", directory / "drive.nmea", quantities=CAN_USED)
    estimator = make_estimator("dead-reckoning", drive.config)
    replay_drive(drive, estimator)
    if estimator.stats().get("speed_rounding_wrong"):
        return "truncate"
    return "round" if estimator.frontend.check.rounding_done else None


def run_benchmark(bs: CalibrateBenchSettings, progress: Callable[[str], None] | None = None) -> list[str]:
    """Every drive of ``bs`` calibrated; the report's lines (a table per drive, then per parameter)."""
    say = progress or (lambda _msg: None)
    results = []
    with tempfile.TemporaryDirectory(prefix="sumhe-bench-calibrate-") as tmp:
        for scenario in bs.scenarios:
            for seed in bs.seeds:
                say(f"calibrate {scenario} seed {seed}")
                results.append(calibrate_drive(scenario, seed, bs.duration_s, Path(tmp) / f"{scenario}-{seed}"))
    return report(results, bs)


def _cell(key: str, r: DriveResult) -> str:
    p = r.calibration.parameters()[key]
    if p.value is None:
        return "null"
    err = error(key, p.value, r.truth[key])
    scale = 100.0 if key in ("speed_scale", "yaw_rate_scale") else 1.0
    unit = " %" if scale == 100.0 else ""
    sigmas = f" ({err / p.std:+.1f} sd)" if p.std and math.isfinite(p.std) else ""
    return f"{scale * err:+.3f}{unit}{sigmas}"


def report(results: list[DriveResult], bs: CalibrateBenchSettings) -> list[str]:
    """Markdown: errors per drive (in standard errors too), then per parameter against its target."""
    lines = [
        f"sumhe bench calibrate: {len(results)} realistic drives of {bs.duration_s:g} s "
        f"({', '.join(bs.scenarios)} x seeds {', '.join(map(str, bs.seeds))}); errors of calibrate against the "
        "simulated parameters, like with like (sumhe/bench/calibrate.py); scales in per cent",
        "",
        "| drive | kind | " + " | ".join(KEYS) + " | speed_rounding: calibrate / on line (simulated) |",
        "|" + "---|" * (len(KEYS) + 3),
    ]
    for r in results:
        rounding = f"{r.calibration.speed_rounding or '-'} / {r.online or '-'} ({r.rounding or '-'})"
        lines.append(f"| {r.name} | {r.kind} | " + " | ".join(_cell(k, r) for k in KEYS) + f" | {rounding} |")
    lines += ["", "| parameter | target | determined | within target | max abs error | median abs error / std |"]
    lines.append("|---|---|---|---|---|---|")
    for key in KEYS:
        errs = [(r.errors()[key], r.calibration.parameters()[key].std) for r in results]
        found = [(e, s) for e, s in errs if e is not None]
        tol, relative = TARGETS.get(key, (math.nan, False))
        scale = 100.0 if relative else 1.0
        target = "-" if math.isnan(tol) else f"{scale * tol:g}{' %' if relative else ''}"
        within = "-" if math.isnan(tol) else f"{sum(abs(e) <= tol for e, _ in found)} of {len(found)}"
        worst = f"{scale * max(abs(e) for e, _ in found):.3f}" if found else "-"
        ratios = sorted(abs(e) / s for e, s in found if s and math.isfinite(s))
        median = f"{ratios[len(ratios) // 2]:.1f}" if ratios else "-"
        lines.append(f"| {key} | {target} | {len(found)} of {len(results)} | {within} | {worst} | {median} |")
    obd = [r for r in results if r.rounding is not None]
    right = sum(r.calibration.speed_rounding == r.rounding for r in obd)
    untold = sum(r.calibration.speed_rounding is None for r in obd)
    told = [r for r in obd if r.online is not None]
    right_online = sum(r.online == r.rounding for r in told)
    lines += [
        "",
        f"speed_rounding, on the {len(obd)} drives whose speed is OBD-II's whole km/h: right on {right}, wrong on "
        f"{len(obd) - right - untold}, not told (no key written) on {untold}; the on-line check (the config's "
        f"'round'): right on {right_online}, wrong on {len(told) - right_online}, not told on {len(obd) - len(told)}",
    ]
    return lines
