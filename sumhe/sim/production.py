"""The production-like vehicle of the ``realistic`` profile: its per-drive DBC, its signal mapping, its config.

``dbc/sumhe_prod.dbc`` is the template (Motorola signals, unsigned raw values with offsets, coarse quanta,
counters and sum checksums, an aftermarket IMU module); each drive redraws the yaw-rate and speed quanta, so
:func:`vehicle_db` rewrites those signals (length and offset follow from the quantum) and the drive carries the
result as ``vehicle.dbc``. OBD drives (``speed_source = "obd"``) see no chassis broadcast at all: their DBC
is ``dbc/obd2.dbc``'s mode-01 reply plus the IMU module, as a logger on the OBD-II port with its own IMU sees.
:func:`replay_config` is the ``config.toml`` that makes ``sumhe replay --config`` read such a drive.
"""

from __future__ import annotations

import functools
import math

from cantools.database.can import Database
from cantools.database.conversion import BaseConversion

from sumhe.config import PACKAGE_DATA, SignalSpec
from sumhe.io.can import REFERENCE_E2E, REFERENCE_SIGNALS, load_dbc
from sumhe.sim.settings import SimSettings

PRODUCTION_DBC = PACKAGE_DATA / "sumhe_prod.dbc"
OBD_DBC = PACKAGE_DATA / "obd2.dbc"
VEHICLE_DBC_FILE = "vehicle.dbc"
CONFIG_FILE = "config.toml"

OBD_REQUEST_ID = 0x7DF
"""Functional (broadcast) OBD-II request id the logger sends."""
OBD_REPLY_ID = 0x7E8
"""The engine ECU's reply id: message ``OBD2`` of dbc/obd2.dbc."""
YAW_RANGE_DPS = 125.0
"""Yaw-rate range of the chassis sensor cluster (+-); the IMU module's is :data:`IMU_RANGE_DPS`."""
IMU_RANGE_DPS = 256.0

PRODUCTION_SIGNALS: dict[str, str] = {
    "speed": "VSA_SPEED.VEHICLE_SPEED",
    "yaw_rate": "VSA_MOTION.YAW_RATE",
    "wheel_speed_fl": "VSA_WHEEL_SPEEDS.WHEEL_SPEED_FL",
    "wheel_speed_fr": "VSA_WHEEL_SPEEDS.WHEEL_SPEED_FR",
    "wheel_speed_rl": "VSA_WHEEL_SPEEDS.WHEEL_SPEED_RL",
    "wheel_speed_rr": "VSA_WHEEL_SPEEDS.WHEEL_SPEED_RR",
    "steering_angle": "EPS_STATUS.STEERING_ANGLE",
    "lat_accel": "VSA_MOTION.LAT_ACCEL",
    "lon_accel": "VSA_MOTION.LON_ACCEL",
}
"""The mapping a user writes for the production-like chassis CAN (broadcast speed)."""
OBD_SPEED_SIGNAL = "OBD2.VehicleSpeed"
IMU_YAW_SIGNAL = "IMU_RATES.RATE_Z"
OBD_LAYOUT_MESSAGES = ("IMU_RATES",)
"""Messages of the template only an OBD-port logger sees (the IMU module on its second channel); a drive with
the broadcast speed has the chassis messages only."""


def signal_specs(settings: SimSettings) -> dict[str, SignalSpec]:
    """Quantity -> where the drive's CAN carries it (with the IMU's sign as the spec's scale)."""
    if settings.can_layout == "reference":
        names = REFERENCE_SIGNALS
    elif settings.speed_source == "obd":
        return {
            "speed": SignalSpec(*OBD_SPEED_SIGNAL.split(".")),
            "yaw_rate": SignalSpec(*IMU_YAW_SIGNAL.split("."), scale=float(settings.imu_sign)),
        }
    else:
        names = PRODUCTION_SIGNALS
    return {quantity: SignalSpec(*name.split(".")) for quantity, name in names.items()}


def e2e_messages(settings: SimSettings) -> tuple[str, ...]:
    """Messages with sumhe's CRC-8 + counter protection: the reference DBC's, none in the production ones."""
    return REFERENCE_E2E if settings.can_layout == "reference" else ()


def quantised_layout(quantum: float, range_: float) -> tuple[int, float]:
    """(bits, offset) of an unsigned signal of resolution ``quantum`` covering +-``range_`` (offset -range_)."""
    return math.ceil(math.log2(2.0 * range_ / quantum + 1.0)), -range_


def _requantise(db: Database, message: str, signal: str, quantum: float, range_: float | None) -> None:
    """Give one signal a new resolution in place: unsigned with offset -range_ (None: offset 0, from 0 up)."""
    sig = db.get_message_by_name(message).get_signal_by_name(signal)
    if range_ is None:
        bits, offset = sig.length, 0.0
    else:
        bits, offset = quantised_layout(quantum, range_)
    if bits > 16:
        raise ValueError(f"{message}.{signal}: a quantum of {quantum:g} needs {bits} bits, more than its 16")
    sig.length = bits
    sig.conversion = BaseConversion.factory(scale=quantum, offset=offset, is_float=False)
    sig.minimum = offset
    sig.maximum = (2**bits - 1) * quantum if range_ is None else range_


@functools.cache
def _vehicle_db(layout: str, speed_source: str, yaw_quantum: float, speed_quantum: float) -> Database:
    if layout == "reference":
        return load_dbc(PACKAGE_DATA / "sumhe_ref.dbc")
    db = load_dbc(PRODUCTION_DBC)
    _requantise(db, "VSA_MOTION", "YAW_RATE", yaw_quantum, YAW_RANGE_DPS)
    _requantise(db, "IMU_RATES", "RATE_Z", yaw_quantum, IMU_RANGE_DPS)
    _requantise(db, "VSA_SPEED", "VEHICLE_SPEED", speed_quantum, None)
    logger = [m for m in db.messages if m.name in OBD_LAYOUT_MESSAGES]
    if speed_source == "obd":
        db.messages[:] = logger + list(obd_db().messages)
        db.nodes.extend(obd_db().nodes)
    else:
        db.messages[:] = [m for m in db.messages if m not in logger]
    db.refresh()
    return db


def vehicle_db(settings: SimSettings) -> Database:
    """The CAN database the drive's car (and logger) speaks; the same object for equal layouts (do not mutate)."""
    return _vehicle_db(
        settings.can_layout, settings.speed_source, settings.yaw_rate_quantum_dps, settings.speed_quantum_kmh
    )


def vehicle_dbc_text(settings: SimSettings) -> str:
    """``vehicle.dbc`` of a production-layout drive (cantools' DBC dump of :func:`vehicle_db`)."""
    text: str = vehicle_db(settings).as_dbc_string()
    return text


def replay_config(settings: SimSettings) -> str:
    """``config.toml`` for ``sumhe replay DIR/drive.log --nmea DIR/drive.nmea --config DIR/config.toml``:
    the drive's DBC and signal mapping, nothing else (every other key keeps its default)."""
    lines = [
        "# sumhe replay DIR/drive.log --nmea DIR/drive.nmea --config DIR/config.toml",
        f"# {settings.profile} profile, {settings.can_layout} CAN layout, speed from {settings.speed_source}",
        "[can]",
        f'dbc = "{VEHICLE_DBC_FILE}"',
        f"e2e = [{', '.join(repr(name).replace(chr(39), chr(34)) for name in e2e_messages(settings))}]",
        "",
        "[can.signals]",
    ]
    for quantity, spec in signal_specs(settings).items():
        if spec.scale == 1.0:
            lines.append(f'{quantity} = "{spec.name}"')
        else:
            lines.append(f'{quantity} = {{ signal = "{spec.name}", scale = {spec.scale!r} }}')
    return "\n".join(lines) + "\n"


@functools.cache
def obd_db() -> Database:
    """dbc/obd2.dbc (loaded once; do not mutate)."""
    return load_dbc(OBD_DBC)
