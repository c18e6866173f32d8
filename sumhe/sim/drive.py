"""A simulated drive: truth, CAN frames and NMEA lines from one seed, and its four files.

``simulate(settings)`` is pure and deterministic: independent random streams (``numpy.random.SeedSequence``
children) drive the route, the sensor errors, the CAN bus and each GNSS receiver, so changing e.g. the outages
changes nothing else. ``write_drive`` writes ``drive.log`` (candump -L), ``drive.nmea`` (receive-time-prefixed
NMEA; ``drive2.nmea`` for antenna 2), ``truth.csv`` and ``scenario.toml``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np
from numpy.typing import ArrayLike, NDArray

from sumhe.config import PACKAGE_DATA
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, GnssFix
from sumhe.sim.can_frames import CHANNEL, TYRE_DEVIATION, CanLog, Sensors, simulate_can
from sumhe.sim.gps import GpsEpochs, in_outage, simulate_receiver
from sumhe.sim.routes import build_route
from sumhe.sim.settings import SimSettings, settings_to_toml
from sumhe.sim.truth import Truth, write_truth
from sumhe.sim.vehicle import WHEELBASE_M, Trajectory

log = logging.getLogger(__name__)

DRIVE_FILES = ("drive.log", "drive.nmea", "truth.csv", "scenario.toml")
SECOND_ANTENNA_FILE = "drive2.nmea"


def bundled_drive_dir() -> Path:
    """The directory of the demo drive shipped with the package (the four files of :func:`write_drive`)."""
    return PACKAGE_DATA / "drive"


@dataclass(frozen=True, eq=False)
class Drive:
    """One simulated drive: everything in memory that :func:`write_drive` puts in files.

    ``can_frames`` carry Unix timestamps on the same clock as the NMEA receive times. ``gps`` holds one
    :class:`~sumhe.sim.gps.GpsEpochs` per antenna; ``nmea_lines2`` is empty with one antenna.
    """

    settings: SimSettings
    frame: LocalFrame
    truth: Truth
    can_frames: list[can.Message]
    nmea_lines: list[str]
    nmea_lines2: list[str]
    gps: tuple[GpsEpochs, ...]
    can_log: CanLog
    applied: dict[str, float | str]

    def fixes(self, antenna: int = 1) -> list[GnssFix]:
        """The fixes of antenna 1 (``drive.nmea``) or 2 (``drive2.nmea``) as the sentences carry them;
        ``t`` is the receive time of the epoch's GGA line, ``alt_m`` the GGA altitude (MSL)."""
        if antenna not in range(1, len(self.gps) + 1):
            raise ValueError(f"antenna: this drive has {len(self.gps)} antenna(s), got {antenna!r}")
        return self.gps[antenna - 1].fixes()

    def can_samples(self) -> list[CanSample]:
        """Every mapped signal of every logged frame, in SI units, in log order."""
        return self.can_log.samples()

    def in_outage(self, t: ArrayLike) -> bool | NDArray[np.bool_]:
        """True where a fix time ``t`` (Unix s) is inside one of the outages."""
        inside = in_outage(self.settings, np.asarray(t, dtype=float) - self.settings.start_unix_s)
        return bool(inside) if inside.ndim == 0 else inside


def _sensors(settings: SimSettings, rng: np.random.Generator, can_rng: np.random.Generator) -> Sensors:
    """Draw the sensor errors (always all of them, so a given setting changes no other draw)."""
    scale = 1.0 + (1.0 if rng.random() < 0.5 else -1.0) * rng.uniform(0.01, 0.02)
    bias_dps = rng.uniform(-0.5, 0.5)
    knots = np.arange(-1.0, settings.duration_s + 2.0)
    steps = rng.normal(0.0, settings.yaw_rate_bias_drift_dps / math.sqrt(60.0), len(knots))
    steps[:2] = 0.0
    tyres = rng.normal(0.0, TYRE_DEVIATION, 4)
    if settings.speed_scale is not None:
        scale = settings.speed_scale
    if settings.yaw_rate_bias_dps is not None:
        bias_dps = settings.yaw_rate_bias_dps
    return Sensors(settings, scale, knots, np.radians(bias_dps + np.cumsum(steps)), tyres, can_rng)


def simulate(settings: SimSettings) -> Drive:
    """Simulate one drive (no file I/O; the same settings give the same drive)."""
    route_seq, sensor_seq, can_seq, gps1_seq, gps2_seq = np.random.SeedSequence(settings.seed).spawn(5)
    route = build_route(settings.scenario, settings.duration_s, np.random.default_rng(route_seq), WHEELBASE_M)
    trajectory = Trajectory(route)
    sensors = _sensors(settings, np.random.default_rng(sensor_seq), np.random.default_rng(can_seq))
    frame = LocalFrame(settings.datum_lat_deg, settings.datum_lon_deg, settings.datum_alt_m)

    t_rel = np.arange(math.floor(settings.duration_s * settings.truth_rate_hz) + 1) / settings.truth_rate_hz
    m = trajectory.at(t_rel)
    geo = frame.to_geodetic(m.east, m.north)
    second: dict[str, NDArray[np.float64]] = {}
    if settings.antennas == 2:
        east2 = m.east - settings.antenna_distance_m * np.sin(m.azimuth)
        north2 = m.north - settings.antenna_distance_m * np.cos(m.azimuth)
        geo2 = frame.to_geodetic(east2, north2)
        second = {"lat2": geo2[:, 0], "lon2": geo2[:, 1], "east2": east2, "north2": north2}
    truth = Truth(
        t=settings.start_unix_s + t_rel,
        lat=geo[:, 0],
        lon=geo[:, 1],
        east=m.east,
        north=m.north,
        azimuth=np.mod(m.azimuth, 2.0 * math.pi),
        speed=m.speed,
        yaw_rate=m.yaw_rate,
        accel=m.accel,
        steering=m.steering,
        speed_scale=np.full(len(t_rel), sensors.speed_scale),
        yaw_rate_bias=sensors.yaw_rate_bias(t_rel),
        **second,
    )
    can_log = simulate_can(settings, trajectory, sensors)
    receivers = [
        simulate_receiver(settings, trajectory, frame, antenna, np.random.default_rng(seq))
        for antenna, seq in zip(range(1, settings.antennas + 1), (gps1_seq, gps2_seq), strict=False)
    ]
    applied: dict[str, float | str] = {
        "speed_scale": sensors.speed_scale,
        "yaw_rate_bias_dps": float(math.degrees(sensors.bias_rps[0])),
        "gps_error_m": settings.gps_error_scale_m,
        "distance_m": float(m.s[-1]),
        "route": ", ".join(
            f"{name} at {t:.0f} s"
            for (name, _), t in zip(route.features, trajectory.time_at([s for _, s in route.features]), strict=True)
            if t < settings.duration_s
        ),
    }
    log.debug("simulated %s drive: %.0f m, %d CAN frames", settings.scenario, m.s[-1], len(can_log.frames))
    return Drive(
        settings=settings,
        frame=frame,
        truth=truth,
        can_frames=can_log.frames,
        nmea_lines=receivers[0][1],
        nmea_lines2=receivers[1][1] if len(receivers) > 1 else [],
        gps=tuple(epochs for epochs, _ in receivers),
        can_log=can_log,
        applied=applied,
    )


def candump_line(msg: can.Message) -> str:
    """One ``candump -L`` line: ``(1780300800.012345) can0 1A0#0011223344556677``."""
    us = round(msg.timestamp * 1e6)
    frame = f"{msg.arbitration_id:03X}#{msg.data.hex().upper()}"
    return f"({us // 1_000_000}.{us % 1_000_000:06d}) {msg.channel or CHANNEL} {frame}"


def write_drive(drive: Drive, out_dir: str | Path) -> list[Path]:
    """Write the drive's files into ``out_dir`` (created if needed); returns the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / name for name in DRIVE_FILES]
    log_path, nmea_path, truth_path, scenario_path = paths
    log_path.write_text("".join(candump_line(m) + "\n" for m in drive.can_frames), encoding="ascii")
    nmea_path.write_text("".join(line + "\n" for line in drive.nmea_lines), encoding="ascii")
    write_truth(drive.truth, truth_path)
    scenario_path.write_text(settings_to_toml(drive.settings, drive.applied), encoding="utf-8")
    if drive.nmea_lines2:
        paths.append(out / SECOND_ANTENNA_FILE)
        paths[-1].write_text("".join(line + "\n" for line in drive.nmea_lines2), encoding="ascii")
    return paths
