"""Test helpers: a data logger of our own on two buses, and the frames of a drive it records.

Channel 1 is the car's OBD-II port (mode 01 replies on 0x7E8, ``dbc/obd2.dbc``) plus a car ECU whose id 0x009
is also used on channel 2; channel 2 the logger's GNSS receiver and IMU (:data:`LOGGER_DBC`, written for these
tests). The IMU is mounted so that it reads right turns positive: the config flips it with ``scale = -1``.
The drive: a constant-speed circle (speed ``SPEED_KMH``, yaw rate ``YAW_DPS`` anticlockwise) from ``DATUM``.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import can
import cantools
import numpy as np

from sumhe.geo import LocalFrame

REPO = Path(__file__).resolve().parents[1]
OBD_DBC = REPO / "dbc" / "obd2.dbc"

LOGGER_DBC = """VERSION ""

BU_: LOGGER

BO_ 2 GNSS_TIME: 6 LOGGER
 SG_ EPOCH : 0|48@1+ (0.001,0) [0|281474976710.655] "s" Vector__XXX

BO_ 3 GNSS_POS: 8 LOGGER
 SG_ POS_VALID : 0|1@1+ (1,0) [0|1] "" Vector__XXX
 SG_ ACCURACY : 1|7@1+ (0.5,0) [0|63.5] "m" Vector__XXX
 SG_ LAT : 8|28@1- (1e-06,0) [-90|90] "deg" Vector__XXX
 SG_ LON : 36|28@1- (1e-06,0) [-134.217728|134.217727] "deg" Vector__XXX

BO_ 7 GNSS_MOTION: 6 LOGGER
 SG_ SPEED_VALID : 0|1@1+ (1,0) [0|1] "" Vector__XXX
 SG_ HEADING_VALID : 1|1@1+ (1,0) [0|1] "" Vector__XXX
 SG_ SPEED : 8|16@1+ (0.01,0) [0|655.35] "m/s" Vector__XXX
 SG_ HEADING : 24|16@1+ (0.01,0) [0|655.35] "deg" Vector__XXX
 SG_ HEADING_ACC : 40|8@1+ (0.1,0) [0|25.5] "deg" Vector__XXX

BO_ 9 IMU: 8 LOGGER
 SG_ IMU_VALID : 0|1@1+ (1,0) [0|1] "" Vector__XXX
 SG_ YAW_RATE_CW : 8|16@1- (0.01,0) [-327.68|327.67] "deg/s" Vector__XXX
"""

CAR_ID_9 = 0x009
"""An id of the car's own bus (channel 1) that the logger's IMU uses on channel 2."""

DATUM = (56.1, 10.2)
SPEED_KMH = 36.0
YAW_DPS = 2.0
T0 = 1627274455.0

LOGGER_CONFIG = """
[can]
dbc = ["dbc/obd2.dbc", "logger.dbc"]

[can.signals]
speed = { signal = "OBD2.VehicleSpeed", channel = 1 }
yaw_rate = { signal = "IMU.YAW_RATE_CW", scale = -1, valid = "IMU_VALID", channel = 2 }

[gps]
source = "can"
time = "receive"

[gps.signals]
lat = { signal = "GNSS_POS.LAT", valid = "POS_VALID", channel = 2 }
lon = { signal = "GNSS_POS.LON", valid = "POS_VALID", channel = 2 }
accuracy = { signal = "GNSS_POS.ACCURACY", channel = 2 }
speed = { signal = "GNSS_MOTION.SPEED", valid = "SPEED_VALID", channel = 2 }
heading = { signal = "GNSS_MOTION.HEADING", valid = "HEADING_VALID", channel = 2 }
time = { signal = "GNSS_TIME.EPOCH", channel = 2 }
"""
"""The config of this logger (``logger.dbc`` is found beside the logs)."""


def logger_db() -> cantools.database.can.Database:
    db = cantools.database.can.Database()
    db.add_dbc_string(LOGGER_DBC)
    return db


def frame(t: float, arbitration_id: int, data: bytes, channel: int) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=arbitration_id, is_extended_id=False, data=data, channel=channel)


def obd_reply(t: float, pid: int, *data: int, channel: int = 1) -> can.Message:
    """A mode 01 reply to ``pid`` with data bytes A, B, ... (padded to 8 bytes with 0x55, as ISO 15765-4 asks)."""
    payload = bytes([2 + len(data), 0x41, pid, *data])
    return frame(t, 0x7E8, payload + b"\x55" * (8 - len(payload)), channel)


def encode(name: str, t: float, channel: int = 2, **values: float) -> can.Message:
    message = logger_db().get_message_by_name(name)
    full = {s.name: 0 for s in message.signals} | values
    return frame(t, message.frame_id, message.encode(full), channel)


def truth(t: np.ndarray) -> dict[str, np.ndarray]:
    """The drive at times ``t`` (s after :data:`T0`): east, north (m), azimuth (rad, clockwise), speed (m/s)."""
    v, w = SPEED_KMH / 3.6, math.radians(YAW_DPS)
    phi = math.radians(45.0) - w * t  # anticlockwise yaw decreases the azimuth
    r = v / w
    east = r * (np.cos(phi) - math.cos(math.radians(45.0)))
    north = r * (math.sin(math.radians(45.0)) - np.sin(phi))
    return {"east": east, "north": north, "azimuth": phi % (2 * math.pi), "speed": np.full_like(t, v)}


def drive_frames(seconds: float, t0: float = T0, no_fix_s: float = 2.0) -> list[can.Message]:
    """The frames of a drive of ``seconds`` in time order: OBD speed (2 Hz, other PIDs between), the car's id 9
    on channel 1, the IMU (20 Hz), and 1 Hz GNSS epochs (time, position, motion within 2 ms), the first
    ``no_fix_s`` without a valid position."""
    frame_geo = LocalFrame(*DATUM, 0.0)
    out = []
    for k in range(int(seconds * 20)):
        t = k * 0.05
        out.append(encode("IMU", t0 + t + 0.003, IMU_VALID=1, YAW_RATE_CW=-YAW_DPS))
        out.append(frame(t0 + t + 0.004, CAR_ID_9, bytes([0xFF] * 8), channel=1))
        if k % 10 == 0:
            out.append(obd_reply(t0 + t + 0.01, 0x0D, round(SPEED_KMH)))
            out.append(obd_reply(t0 + t + 0.03, 0x0C, 0x1A, 0x2B))
        if k % 20 == 10:
            s = truth(np.array([t]))
            lat, lon, _ = frame_geo.to_geodetic(s["east"][0], s["north"][0], 0.0)
            valid = int(t >= no_fix_s)
            out.append(encode("GNSS_TIME", t0 + t + 0.020, EPOCH=t0 + t - 4.4))
            out.append(
                encode("GNSS_POS", t0 + t + 0.021, POS_VALID=valid, ACCURACY=1.5, LAT=float(lat), LON=float(lon))
            )
            out.append(
                encode(
                    "GNSS_MOTION",
                    t0 + t + 0.022,
                    SPEED_VALID=valid,
                    HEADING_VALID=valid,
                    SPEED=float(s["speed"][0]),
                    HEADING=math.degrees(float(s["azimuth"][0])),
                )
            )
    return sorted(out, key=lambda m: m.timestamp)


def write_log(path: Path, frames: list[can.Message]) -> Path:
    """``frames`` as a log in the format of ``path``'s suffix (python-can's writers: ``.mf4``, ``.log``, ...)."""
    with can.Logger(str(path)) as writer:
        for msg in frames:
            writer.on_message_received(msg)
    return path


def write_drive(directory: Path, seconds: float, files: int = 1, suffix: str = ".mf4") -> list[Path]:
    """A drive of ``seconds`` in ``files`` consecutive logs, with ``logger.dbc`` beside them and the config
    ``logger.toml``; the log paths in time order."""
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "logger.dbc").write_text(LOGGER_DBC)
    (directory / "logger.toml").write_text(LOGGER_CONFIG)
    frames = drive_frames(seconds)
    bounds = np.linspace(0, len(frames), files + 1).astype(int)
    return [
        write_log(directory / f"{i + 1:08d}{suffix}", frames[a:b])
        for i, (a, b) in enumerate(itertools.pairwise(bounds))
    ]
