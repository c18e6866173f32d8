"""A simulated drive: truth, CAN frames and NMEA lines from one seed, and its four files.

``simulate(settings)`` is pure and deterministic: independent random streams (``numpy.random.SeedSequence``
children) drive the route, the sensor errors, the CAN bus and each GNSS receiver, so changing e.g. the outages
changes nothing else; the real-car errors draw from streams of their own, so a ``kind`` drive is what it was
before they existed. ``write_drive`` writes ``drive.log`` (candump -L), ``drive.nmea`` (receive-time-prefixed
NMEA; ``drive2.nmea`` for antenna 2), ``truth.csv`` and ``scenario.toml``; a drive with the production-like
CAN layout also ``vehicle.dbc`` and ``config.toml`` (its signal mapping, for ``sumhe replay --config``).
"""

from __future__ import annotations

import dataclasses
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
from sumhe.sim.gps import GpsEpochs, clock_offset_s, in_outage, simulate_receiver
from sumhe.sim.obd import simulate_obd
from sumhe.sim.production import CONFIG_FILE, VEHICLE_DBC_FILE, replay_config, vehicle_dbc_text
from sumhe.sim.routes import build_route
from sumhe.sim.settings import REAL_CAR_FIELDS, SimSettings, settings_to_toml
from sumhe.sim.truth import Truth, write_truth
from sumhe.sim.vehicle import WHEELBASE_M, Body, Trajectory

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
    calibration: dict[str, float] = dataclasses.field(default_factory=dict)
    """The installation parameters in ``sumhe calibrate``'s terms (empty for a kind drive)."""

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


def _sensors(settings: SimSettings, rng: np.random.Generator, can_rng: np.random.Generator, body: Body) -> Sensors:
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
    bias_rps = np.radians(bias_dps + np.cumsum(steps))
    return Sensors(settings, scale, knots, bias_rps, tyres, can_rng, settings.yaw_rate_scale, body)


def is_real_car(settings: SimSettings) -> bool:
    """True when any real-car error is switched on (not a kind drive)."""
    default = SimSettings()
    return any(getattr(settings, name) != getattr(default, name) for name in REAL_CAR_FIELDS)


def calibration_truth(settings: SimSettings, sensors: Sensors) -> dict[str, float]:
    """The true installation parameters in ``sumhe calibrate``'s terms (issue 12): ``gps_time_offset_s`` = the
    CAN-clock time at which a fix's position was true minus its UTC tag (mid-drive), ``speed_scale`` = true / CAN
    speed, ``yaw_rate_bias_dps`` = CAN minus scaled true yaw rate (the drive's mean), ``yaw_rate_scale`` =
    true / (CAN - bias), ``can_delay_s`` = age of the chassis sensor values when sent."""
    t = np.linspace(0.0, settings.duration_s, 1001)
    return {
        "gps_time_offset_s": settings.gps_time_offset_s,
        "speed_scale": 1.0 / sensors.speed_scale,
        "yaw_rate_bias_dps": float(np.degrees(sensors.yaw_rate_bias(t).mean())),
        "yaw_rate_scale": 1.0 / settings.yaw_rate_scale,
        "can_delay_s": settings.can_sensor_delay_s,
    }


def simulate(settings: SimSettings) -> Drive:
    """Simulate one drive (no file I/O; the same settings give the same drive)."""
    seqs = np.random.SeedSequence(settings.seed).spawn(8)
    route_seq, sensor_seq, can_seq, gps1_seq, gps2_seq, real1_seq, real2_seq, obd_seq = seqs
    route = build_route(settings.scenario, settings.duration_s, np.random.default_rng(route_seq), WHEELBASE_M)
    trajectory = Trajectory(route)
    body = Body(trajectory, math.radians(settings.thrust_angle_deg), math.radians(settings.sideslip_deg_per_mps2))
    sensors = _sensors(settings, np.random.default_rng(sensor_seq), np.random.default_rng(can_seq), body)
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
    obd = simulate_obd(trajectory, sensors, np.random.default_rng(obd_seq)) if settings.speed_source == "obd" else ()
    can_log = simulate_can(settings, trajectory, sensors, obd)
    receivers = [
        simulate_receiver(
            settings, trajectory, frame, antenna, np.random.default_rng(seq), np.random.default_rng(real), body
        )
        for antenna, seq, real in zip(
            range(1, settings.antennas + 1), (gps1_seq, gps2_seq), (real1_seq, real2_seq), strict=False
        )
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
    calibration: dict[str, float] = {}
    if is_real_car(settings):
        calibration = calibration_truth(settings, sensors)
        epochs = receivers[0][0]
        sent = epochs.sent & np.isfinite(epochs.t_rx)
        tag_rel = epochs.t_fix[sent] - settings.start_unix_s
        applied["gps_clock_offset_end_s"] = float(clock_offset_s(settings, np.array([settings.duration_s]))[0])
        applied["gps_receive_minus_tag_s"] = float(np.mean(epochs.t_rx[sent] - epochs.t_fix[sent]))
        applied["gps_receive_minus_true_s"] = float(
            np.mean(epochs.t_rx[sent] - epochs.t_fix[sent] - clock_offset_s(settings, tag_rel))
        )
        applied["gps_epochs_dropped"] = int(np.count_nonzero(epochs.valid & ~epochs.sent))
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
        calibration=calibration,
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
    scenario_path.write_text(settings_to_toml(drive.settings, drive.applied, drive.calibration), encoding="utf-8")
    if drive.nmea_lines2:
        paths.append(out / SECOND_ANTENNA_FILE)
        paths[-1].write_text("".join(line + "\n" for line in drive.nmea_lines2), encoding="ascii")
    if drive.settings.can_layout != "reference":
        paths += [out / VEHICLE_DBC_FILE, out / CONFIG_FILE]
        paths[-2].write_text(vehicle_dbc_text(drive.settings), encoding="utf-8")
        paths[-1].write_text(replay_config(drive.settings), encoding="utf-8")
    return paths
