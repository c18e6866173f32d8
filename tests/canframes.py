"""Test helpers: CAN frames of the reference DBC and the opendbc excerpt, encoded with cantools."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import can
import cantools

from sumhe.io.checksum import protect

ROOT = Path(__file__).resolve().parents[1]
REF_DBC = ROOT / "dbc" / "sumhe_ref.dbc"
TOYOTA_DBC = Path(__file__).resolve().parent / "data" / "toyota_nodsu_pt_excerpt.dbc"


@cache
def ref_db() -> cantools.database.can.Database:
    return cantools.database.load_file(str(REF_DBC))


@cache
def toyota_db() -> cantools.database.can.Database:
    return cantools.database.load_file(str(TOYOTA_DBC), strict=False)


def encode(db: cantools.database.can.Database, name: str, t: float = 0.0, **values: float) -> can.Message:
    """A frame of message ``name`` with ``values`` (DBC units; unnamed signals 0) at time ``t``.

    Messages with a ``*_COUNTER`` and ``*_CHECKSUM`` signal get a valid CRC in byte 0.
    """
    message = db.get_message_by_name(name)
    full = {s.name: 0 for s in message.signals} | values
    data = message.encode(full, strict=False)
    if any(s.name.endswith("_CHECKSUM") for s in message.signals):
        data = protect(data)
    return can.Message(
        timestamp=t, arbitration_id=message.frame_id, is_extended_id=message.is_extended_frame, data=data
    )


def yaw_frame(t: float, yaw_deg_s: float, counter: int, lat: float = 0.0, lon: float = 0.0) -> can.Message:
    return encode(
        ref_db(), "ESP_YAW_RATE", t, YAW_RATE=yaw_deg_s, LAT_ACCEL=lat, LON_ACCEL=lon, ESP_YAW_COUNTER=counter % 16
    )


def speed_frame(t: float, speed_kmh: float, counter: int) -> can.Message:
    return encode(ref_db(), "ESP_VEHICLE_SPEED", t, VEHICLE_SPEED=speed_kmh, ESP_SPEED_COUNTER=counter % 16)


MESSAGE_FIELDS = (
    "timestamp",
    "arbitration_id",
    "data",
    "channel",
    "is_rx",
    "is_extended_id",
    "is_fd",
    "bitrate_switch",
    "error_state_indicator",
    "is_error_frame",
    "is_remote_frame",
    "dlc",
)
"""Every field of a ``can.Message`` a log reader fills: two readers agree when these do."""
