"""Measure a drive directory's sensor errors against its truth, from the files alone, with sumhe's decoders.

This is what ``sumhe simulate --errors DIR`` prints: CAN speed and yaw rate minus the truth at the frame's
timestamp (so timing, delay, scale, bias, noise and quantisation all show), GPS position minus the truth at the
time of fix, the fix latency (receive time - time of fix), GPS speed and HDT heading errors, CAN timing jitter.
It works on any directory with ``truth.csv``, ``drive.log`` and ``drive.nmea`` (``drive2.nmea`` if present);
with a ``scenario.toml`` it decodes the drive's own CAN layout (production-like, OBD) and adds the GNSS error
against where the antenna truly was at the fix's tag + the clock offset (lever arm and sideslip applied).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sumhe.errors import SourceError
from sumhe.geo import LocalFrame
from sumhe.io.can import CanDecoder, read_log
from sumhe.io.nmea import iter_fixes
from sumhe.messages import GnssFix
from sumhe.sim.drive import is_real_car
from sumhe.sim.gps import clock_offset_s
from sumhe.sim.production import e2e_messages, signal_specs, vehicle_db
from sumhe.sim.settings import SimSettings, load_settings
from sumhe.sim.truth import Truth, load_truth

MOVING_MPS = 1.0
"""Course, heading-of-motion and scale statistics use only samples faster than this."""


@dataclass(frozen=True, slots=True)
class ErrorRow:
    """Statistics of one error: mean, standard deviation, 95th percentile and maximum of |error| over n samples."""

    name: str
    unit: str
    n: int
    mean: float
    std: float
    p95: float
    max: float


def error_row(name: str, unit: str, errors: ArrayLike) -> ErrorRow:
    """The row of ``errors`` (mean and std signed; p95 and max of the absolute value); NaN when empty."""
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return ErrorRow(name, unit, 0, math.nan, math.nan, math.nan, math.nan)
    a = np.abs(e)
    return ErrorRow(
        name, unit, int(e.size), float(e.mean()), float(e.std()), float(np.percentile(a, 95)), float(a.max())
    )


def measure_errors(drive_dir: str | Path) -> list[ErrorRow]:
    """The error table of one drive directory; SourceError when a file is missing or unreadable."""
    d = Path(drive_dir)
    try:
        truth = load_truth(d / "truth.csv")
        scenario = d / "scenario.toml"
        settings = load_settings(scenario) if scenario.is_file() else SimSettings()
    except ValueError as e:
        raise SourceError(str(e)) from e
    rows = _can_rows(truth, d / "drive.log", settings)
    rows += _gps_rows(truth, d / "drive.nmea", antenna=1, settings=settings)
    if (d / "drive2.nmea").is_file():
        rows += _gps_rows(truth, d / "drive2.nmea", antenna=2, settings=settings)
    return rows


def _can_rows(truth: Truth, path: Path, settings: SimSettings) -> list[ErrorRow]:
    signals = signal_specs(settings)
    db = vehicle_db(settings)
    decoder = CanDecoder(db, signals, e2e_messages(settings), source=str(path))
    series: dict[str, list[tuple[float, float]]] = {}
    yaw_frames = []
    yaw_message = db.get_message_by_name(signals["yaw_rate"].message)
    yaw_id = yaw_message.frame_id
    for msg in read_log(path):
        if msg.arbitration_id == yaw_id:
            yaw_frames.append(msg.timestamp)
        for s in decoder.decode(msg):
            series.setdefault(s.quantity, []).append((s.t, s.value))
    speed_t, speed = np.array(series.get("speed", [(math.nan, math.nan)])).T
    yaw_t, yaw = np.array(series.get("yaw_rate", [(math.nan, math.nan)])).T
    at_speed, at_yaw = truth.at(speed_t), truth.at(yaw_t)
    moving = at_speed.speed > MOVING_MPS
    period = np.diff(yaw_frames)
    cycle = yaw_message.cycle_time / 1000.0
    return [
        error_row("CAN speed - true speed", "m/s", speed - at_speed.speed),
        error_row("CAN speed / true scale - true speed", "m/s", speed / at_speed.speed_scale - at_speed.speed),
        error_row("CAN speed / true speed - 1 (moving)", "%", 100.0 * (speed[moving] / at_speed.speed[moving] - 1.0)),
        error_row("CAN yaw rate - true yaw rate", "deg/s", np.degrees(yaw - at_yaw.yaw_rate)),
        error_row(
            "CAN yaw rate - true yaw rate - true bias",
            "deg/s",
            np.degrees(yaw - at_yaw.yaw_rate_bias - at_yaw.yaw_rate),
        ),
        error_row(f"CAN {yaw_message.name} period - cycle", "ms", 1000.0 * (period - cycle)),
    ]


def _gps_rows(truth: Truth, path: Path, antenna: int, settings: SimSettings) -> list[ErrorRow]:
    fixes = list(iter_fixes(path))
    valid = [f for f in fixes if f.valid and f.time_utc is not None]
    label = f"GPS{antenna}"
    rows = [ErrorRow(f"{label} epochs without a valid fix", "", len(fixes) - len(valid), *[math.nan] * 4)]
    if not valid:
        return rows
    t_fix = np.array([_fix_time(f) for f in valid])
    at = truth.at(t_fix)
    frame = LocalFrame(float(truth.lat[0]), float(truth.lon[0]))
    measured = frame.to_enu([f.lat_deg for f in valid], [f.lon_deg for f in valid], frame.alt0_m)
    second = antenna == 2 and at.lat2 is not None and at.lon2 is not None
    true_enu = frame.to_enu(at.lat2, at.lon2, frame.alt0_m) if second else frame.to_enu(at.lat, at.lon, frame.alt0_m)
    err = measured[:, :2] - true_enu[:, :2]
    moving = at.speed > MOVING_MPS
    rows += [
        error_row(f"{label} horizontal position error", "m", np.hypot(err[:, 0], err[:, 1])),
        error_row(f"{label} east error", "m", err[:, 0]),
        error_row(f"{label} north error", "m", err[:, 1]),
        error_row(f"{label} fix latency (receive - fix time)", "ms", 1000.0 * (np.array([f.t for f in valid]) - t_fix)),
        error_row(f"{label} speed - true speed", "m/s", _values(valid, "speed_mps") - at.speed),
        error_row(
            f"{label} course - true azimuth (moving)",
            "deg",
            _angle_deg(_values(valid, "course_rad") - at.azimuth)[moving],
        ),
    ]
    if antenna == 1 and is_real_car(settings):
        local = frame.to_enu(truth.lat, truth.lon, frame.alt0_m)
        ant = true_antenna(dataclasses.replace(truth, east=local[:, 0], north=local[:, 1]), t_fix, settings)
        err_ant = measured[:, :2] - ant
        rows.append(
            error_row(f"{label} error vs true antenna at tag + offset", "m", np.hypot(err_ant[:, 0], err_ant[:, 1]))
        )
    heading = _values(valid, "heading_rad")
    if np.isfinite(heading).any():
        rows.append(error_row(f"{label} HDT heading - true azimuth", "deg", _angle_deg(heading - at.azimuth)))
    return rows


def lever_arm(truth: Truth, t: ArrayLike, settings: SimSettings) -> NDArray[np.float64]:
    """(n, 2) east/north (m) from the reference point to antenna 1 at times ``t`` (Unix s, the CAN clock): the
    lever arm turned by the body heading (azimuth minus the sideslip of :class:`~sumhe.sim.vehicle.Body`)."""
    at = truth.at(t)
    slip = math.radians(settings.thrust_angle_deg) + math.radians(settings.sideslip_deg_per_mps2) * (
        at.speed * at.yaw_rate
    )
    psi = at.azimuth - slip
    fwd, left = settings.antenna_forward_m, settings.antenna_left_m
    return np.column_stack([fwd * np.sin(psi) - left * np.cos(psi), fwd * np.cos(psi) + left * np.sin(psi)])


def true_antenna(truth: Truth, t_tag: ArrayLike, settings: SimSettings) -> NDArray[np.float64]:
    """(n, 2) east/north (m, in the frame of ``truth.east``/``truth.north``) where antenna 1 truly was when the fixes
    tagged ``t_tag`` (Unix s, GNSS time) were taken: the reference point at the tag plus the GNSS clock's offset on
    the CAN clock (:func:`~sumhe.sim.gps.clock_offset_s`), plus the lever arm (:func:`lever_arm`)."""
    t = np.asarray(t_tag, dtype=float)
    true_t = t + clock_offset_s(settings, t - settings.start_unix_s)
    at = truth.at(true_t)
    return np.column_stack([at.east, at.north]) + lever_arm(truth, true_t, settings)


def _fix_time(fix: GnssFix) -> float:
    assert fix.time_utc is not None
    return fix.time_utc.timestamp()


def _values(fixes: Iterable[GnssFix], name: str) -> NDArray[np.float64]:
    return np.array([math.nan if getattr(f, name) is None else getattr(f, name) for f in fixes], dtype=float)


def _angle_deg(diff_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.degrees((diff_rad + math.pi) % (2.0 * math.pi) - math.pi)


def format_table(rows: Iterable[ErrorRow], title: str) -> str:
    """A fixed-width text table of the rows under ``title``."""
    lines = [title, f"{'error':<42} {'unit':>5} {'n':>7} {'mean':>9} {'std':>9} {'p95|e|':>9} {'max|e|':>9}"]
    for r in rows:
        stats = " ".join("        -" if math.isnan(v) else f"{v:>9.4f}" for v in (r.mean, r.std, r.p95, r.max))
        lines.append(f"{r.name:<42} {r.unit:>5} {r.n:>7d} {stats}")
    return "\n".join(lines)
