"""The simulated chassis CAN bus: frames of the reference DBC encoded by cantools, as a USB adapter logs them.

Every DBC message with a cycle time (GenMsgCycleTime) is sent by its ECU at that cycle on the ECU's own clock
(+-100 ppm, 0.1 ms task jitter) and carries the sensor values of ``can_sensor_delay_s`` earlier: yaw rate =
truth + bias + noise, speed = truth * scale + noise (0 below 0.3 m/s, as wheel-speed sensors), wheel speeds
from the turn geometry (track width, wheelbase) with the same scale and a per-wheel tyre deviation, steering-wheel
angle = road-wheel angle * steering ratio. Values are rounded to the signal's resolution; counters roll mod 16
and byte 0 gets the CRC (:func:`sumhe.io.checksum.protect`) in the protected messages (``REFERENCE_E2E``).
The host timestamps each frame at the end of its 1 ms USB frame plus U(0, ``can_jitter_s``); during random
stalls (``can_burst_per_min``, up to ``can_burst_max_s``) frames pile up and arrive in one burst.
Frames are dropped at random at ``can_drop_rate``.

Real-car options (see :class:`~sumhe.sim.settings.SimSettings`): the yaw rate is the body's (sideslip included)
times ``yaw_rate_scale``; the production-like layout (:mod:`sumhe.sim.production`) has no CRC but a 4-bit
counter and a sum checksum in byte 7; OBD drives add the logger's polled mode-01 requests and the ECU's replies
(:mod:`sumhe.sim.obd`); with ``can_poll_max_s`` > 0 the host reads the adapter at random intervals
(:func:`polled_host_times`), so frames arrive in bursts.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can
import cantools
import numpy as np
from numpy.typing import NDArray

from sumhe.config import DEFAULT_DBC, PACKAGE_DATA, SignalSpec
from sumhe.io.can import load_dbc
from sumhe.io.checksum import protect
from sumhe.messages import CanSample
from sumhe.sim.production import e2e_messages, signal_specs, vehicle_db
from sumhe.sim.settings import SimSettings
from sumhe.sim.vehicle import STEERING_RATIO, TRACK_M, WHEELBASE_M, Body, Motion, Trajectory

FloatArray = NDArray[np.float64]

DBC_PATH = PACKAGE_DATA / Path(DEFAULT_DBC).name
CHANNEL = "can0"
SECOND_CHANNEL = "can1"
"""The logger's second channel: the aftermarket IMU module of OBD drives."""
USB_FRAME_S = 0.001
ECU_CLOCK_PPM = 100.0
MIN_WHEEL_SPEED_MPS = 0.3
TYRE_DEVIATION = 0.002
"""1-sigma relative deviation of each wheel's rolling radius from the common speed scale."""
ODOMETER0_M = 12_345_600.0

UNIT_TO_SI = {"km/h": 1.0 / 3.6, "deg/s": math.pi / 180.0, "deg": math.pi / 180.0, "m/s^2": 1.0, "km": 1000.0}
"""Factor from a DBC unit to SI; signals with other units (counters, flags, ratios) are taken as they are."""


@dataclass(frozen=True)
class Sensors:
    """The sensor errors applied: speed scale, yaw-rate bias as a function of time, noise generator."""

    settings: SimSettings
    speed_scale: float
    bias_t: FloatArray
    """Knots of the yaw-rate bias (s from the start) ..."""
    bias_rps: FloatArray
    """... and its values (rad/s); linear in between."""
    tyres: FloatArray
    """Relative rolling-radius deviation of the FL, FR, RL, RR wheels."""
    rng: np.random.Generator
    yaw_scale: float = 1.0
    """CAN yaw rate / the body's true yaw rate (bias aside)."""
    body: Body | None = None
    """The body whose yaw rate the sensor sees (None: the kinematic path's)."""

    def body_yaw_rate(self, m: Motion) -> FloatArray:
        return m.yaw_rate if self.body is None else self.body.yaw_rate(m)

    def measured_yaw_rate(self, m: Motion) -> FloatArray:
        """What a yaw-rate sensor reads (rad/s): scale x body yaw rate + bias + white noise."""
        noise = self.noise(math.radians(self.settings.yaw_rate_noise_dps), len(m.t))
        return self.yaw_scale * self.body_yaw_rate(m) + self.yaw_rate_bias(m.t) + noise

    def yaw_rate_bias(self, t_rel: FloatArray) -> FloatArray:
        return np.interp(t_rel, self.bias_t, self.bias_rps)

    def noise(self, sigma: float, n: int) -> FloatArray:
        return self.rng.normal(0.0, sigma, n)


def _yaw_rate(m: Motion, s: Sensors) -> dict[str, FloatArray]:
    cfg = s.settings
    n = len(m.t)
    return {
        "YAW_RATE": s.measured_yaw_rate(m),
        "LAT_ACCEL": m.lat_accel + s.noise(cfg.accel_noise_mps2, n),
        "LON_ACCEL": m.accel + s.noise(cfg.accel_noise_mps2, n),
    }


def _imu_rates(m: Motion, s: Sensors) -> dict[str, FloatArray]:
    """The IMU module: its Z axis is the yaw rate (negated when mounted upside down), X and Y only noise."""
    n = len(m.t)
    sigma = math.radians(s.settings.yaw_rate_noise_dps)
    return {
        "RATE_Z": s.settings.imu_sign * s.measured_yaw_rate(m),
        "RATE_X": s.noise(sigma, n),
        "RATE_Y": s.noise(sigma, n),
        "IMU_VALID": np.ones(n),
    }


def _wheel(v: FloatArray, s: Sensors, sigma: float) -> FloatArray:
    """A wheel-speed sensor's reading: scaled, noisy, and zero below the sensor's minimum speed."""
    scaled = v * s.speed_scale
    return np.where(scaled >= MIN_WHEEL_SPEED_MPS, np.maximum(scaled + s.noise(sigma, len(v)), 0.0), 0.0)


def _vehicle_speed(m: Motion, s: Sensors) -> dict[str, FloatArray]:
    speed = _wheel(m.speed, s, s.settings.speed_noise_mps)
    moving = (speed > 0).astype(float)
    return {"VEHICLE_SPEED": speed, "STANDSTILL": 1.0 - moving, "DRIVE_DIRECTION": moving}


def wheel_speeds(speed: FloatArray, yaw_rate: FloatArray) -> tuple[FloatArray, ...]:
    """True FL, FR, RL, RR wheel speeds (m/s) of the bicycle model: rear wheels at -+ track/2 beside the
    reference point, front wheels a wheelbase ahead, all turning about the same centre."""
    half = yaw_rate * TRACK_M / 2
    front = yaw_rate * WHEELBASE_M
    return (np.hypot(speed - half, front), np.hypot(speed + half, front), speed - half, speed + half)


def _wheel_speeds(m: Motion, s: Sensors) -> dict[str, FloatArray]:
    names = ("WHEEL_SPEED_FL", "WHEEL_SPEED_FR", "WHEEL_SPEED_RL", "WHEEL_SPEED_RR")
    sigma = s.settings.wheel_speed_noise_mps
    speeds = wheel_speeds(m.speed, m.yaw_rate)
    return {name: _wheel(v * (1.0 + dev), s, sigma) for name, v, dev in zip(names, speeds, s.tyres, strict=True)}


def _steering(m: Motion, s: Sensors) -> dict[str, FloatArray]:
    return {
        "STEERING_ANGLE": STEERING_RATIO * m.steering,
        "STEERING_RATE": STEERING_RATIO * m.steering_rate,
        "STEERING_RATIO": np.full(len(m.t), STEERING_RATIO),
    }


def _vehicle_status(m: Motion, s: Sensors) -> dict[str, FloatArray]:
    return {"IGNITION": np.full(len(m.t), 2.0), "ODOMETER": ODOMETER0_M + m.s * s.speed_scale}


MESSAGE_MODELS: dict[str, Callable[[Motion, Sensors], dict[str, FloatArray]]] = {
    "ESP_YAW_RATE": _yaw_rate,
    "ESP_VEHICLE_SPEED": _vehicle_speed,
    "ESP_WHEEL_SPEEDS": _wheel_speeds,
    "EPS_STEERING": _steering,
    "GW_VEHICLE_STATUS": _vehicle_status,
    "VSA_MOTION": _yaw_rate,
    "VSA_SPEED": _vehicle_speed,
    "VSA_WHEEL_SPEEDS": _wheel_speeds,
    "EPS_STATUS": _steering,
    "GW_STATUS": _vehicle_status,
    "IMU_RATES": _imu_rates,
}
"""The SI values each cyclic message of the reference and production-like DBCs carries, by message name."""
MESSAGE_CHANNELS = {"IMU_RATES": SECOND_CHANNEL}
"""Messages logged on another channel than :data:`CHANNEL`."""
CHECKSUM_BYTE = 7
"""Byte of the production-like messages' sum checksum."""


@functools.cache
def reference_db() -> cantools.database.can.Database:
    """The reference DBC the kind profile's car speaks (loaded once)."""
    return load_dbc(DBC_PATH)


@dataclass(frozen=True, eq=False)
class CanLog:
    """The frames the host logged, and the SI value of every mapped signal in them (one row per sample)."""

    frames: list[can.Message]
    sample_t: FloatArray
    sample_quantity: NDArray[np.str_]
    sample_value: FloatArray

    def samples(self) -> list[CanSample]:
        return [
            CanSample(float(t), str(q), float(v))
            for t, q, v in zip(self.sample_t, self.sample_quantity, self.sample_value, strict=True)
        ]


@dataclass(frozen=True, eq=False)
class Encoded:
    """One message's (or one OBD id's) frames before the host sees them: bus times (s from the start),
    payloads and the mapped SI values."""

    frame_id: int
    bus_t: FloatArray
    payloads: list[bytes]
    quantities: list[str]
    values: FloatArray
    """(frames, quantities) SI values as encoded."""
    channel: str = CHANNEL


def _signal_si(signal: cantools.database.can.Signal) -> float:
    return UNIT_TO_SI.get(signal.unit or "", 1.0)


def _to_raw(signal: cantools.database.can.Signal, si: FloatArray) -> NDArray[np.int64]:
    """Round SI values to the signal's resolution and clip them to its range: raw integers."""
    physical = si / _signal_si(signal)
    low = signal.minimum if signal.minimum is not None else -math.inf
    high = signal.maximum if signal.maximum is not None else math.inf
    raw = np.round((np.clip(physical, low, high) - signal.offset) / signal.scale)
    bits_low = -(2 ** (signal.length - 1)) if signal.is_signed else 0
    bits_high = 2 ** (signal.length - 1) - 1 if signal.is_signed else 2**signal.length - 1
    return np.clip(raw, bits_low, bits_high).astype(np.int64)


def sum_checksum(frame_id: int, data: bytes) -> bytes:
    """``data`` with byte 7 = (id high byte + id low byte + length + bytes 0-6) mod 256 (production-like)."""
    total = (frame_id >> 8) + (frame_id & 0xFF) + len(data) + sum(data[:CHECKSUM_BYTE])
    return data[:CHECKSUM_BYTE] + bytes([total & 0xFF]) + data[CHECKSUM_BYTE + 1 :]


def _encode_message(
    message: cantools.database.can.Message,
    trajectory: Trajectory,
    sensors: Sensors,
    ecu_ppm: float,
    mapping: dict[str, SignalSpec],
    protected: bool,
) -> Encoded:
    cfg = sensors.settings
    rng = sensors.rng
    cycle = message.cycle_time / 1000.0
    n = math.ceil(cfg.duration_s / cycle) + 1
    first = rng.uniform(0.0, cycle)
    bus_t = first + np.arange(n) * cycle * (1.0 + ecu_ppm) + np.abs(rng.normal(0.0, cfg.can_ecu_jitter_s, n))
    bus_t = bus_t[bus_t < cfg.duration_s]
    motion = trajectory.at(bus_t - cfg.can_sensor_delay_s)
    si = MESSAGE_MODELS[message.name](motion, sensors)
    raw: dict[str, NDArray[np.int64]] = {}
    summed = False
    for sig in message.signals:
        if sig.name.endswith("_COUNTER"):
            raw[sig.name] = np.arange(len(bus_t)) % 2**sig.length
        elif sig.name.endswith("_CHECKSUM"):
            raw[sig.name] = np.zeros(len(bus_t), dtype=np.int64)
            summed = not protected
        else:
            raw[sig.name] = _to_raw(sig, si[sig.name])
    names = list(raw)
    payloads = []
    for row in zip(*(raw[name].tolist() for name in names), strict=True):
        data = message.encode(dict(zip(names, row, strict=True)), scaling=False)
        if protected:
            data = protect(data)
        elif summed:
            data = sum_checksum(message.frame_id, data)
        payloads.append(data)
    by_name = {spec.name: (quantity, spec.scale) for quantity, spec in mapping.items()}
    mapped = [sig for sig in message.signals if f"{message.name}.{sig.name}" in by_name]
    values = np.empty((len(bus_t), len(mapped)))
    for j, sig in enumerate(mapped):
        spec_scale = by_name[f"{message.name}.{sig.name}"][1]
        values[:, j] = (raw[sig.name] * sig.scale + sig.offset) * _signal_si(sig) * spec_scale
    return Encoded(
        message.frame_id,
        bus_t,
        payloads,
        [by_name[f"{message.name}.{sig.name}"][0] for sig in mapped],
        values,
        MESSAGE_CHANNELS.get(message.name, CHANNEL),
    )


def host_times(settings: SimSettings, bus_t: FloatArray, rng: np.random.Generator) -> FloatArray:
    """When the host timestamps frames sent at ``bus_t`` (s from the start): end of the 1 ms USB frame plus
    U(0, can_jitter_s) per USB frame; frames sent during a stall all arrive when it ends."""
    usb = np.floor(bus_t / USB_FRAME_S).astype(np.int64) + 1
    latency = rng.uniform(0.0, settings.can_jitter_s, int(usb.max(initial=0)) + 1)
    host = usb * USB_FRAME_S + latency[usb]
    return _stalls(settings, bus_t, host, rng, lambda end: latency[min(int(end / USB_FRAME_S), len(latency) - 1)])


def _stalls(
    settings: SimSettings,
    bus_t: FloatArray,
    host: FloatArray,
    rng: np.random.Generator,
    delay_after: Callable[[float], float],
) -> FloatArray:
    """Random stalls (``can_burst_per_min``, up to ``can_burst_max_s``): frames sent during one arrive after it."""
    count = rng.poisson(settings.can_burst_per_min * settings.duration_s / 60.0)
    starts = rng.uniform(0.0, settings.duration_s, count)
    ends = starts + rng.uniform(0.0, settings.can_burst_max_s, count)
    for start, end in zip(starts, ends, strict=True):
        stalled = (bus_t >= start) & (bus_t < end)
        host[stalled] = np.maximum(host[stalled], end + delay_after(end))
    return host


POLL_MIN_S = 0.001
"""Shortest interval between two reads of the USB adapter by the host."""
FRAME_READ_S = (0.00002, 0.0001)
"""Range of the host's time per frame when it unpacks one USB read (the spacing of a burst's timestamps)."""


def polled_host_times(settings: SimSettings, bus_t: FloatArray, rng: np.random.Generator) -> FloatArray:
    """Host timestamps of a USB adapter read at random intervals U(1 ms, ``can_poll_max_s``): every frame sent
    since the last read arrives in one burst, stamped at the read plus a few tens of microseconds per frame
    (as USB-serial adapters with a latency timer deliver them; gaps of 0.1-29 ms for an 83 Hz message were
    measured on a real car). Stalls as in :func:`host_times` come on top."""
    span = settings.duration_s + 1.0
    mean = (POLL_MIN_S + settings.can_poll_max_s) / 2.0
    reads = np.cumsum(rng.uniform(POLL_MIN_S, settings.can_poll_max_s, math.ceil(span / mean * 1.5) + 16))
    reads = reads[reads < span + settings.can_poll_max_s]
    order = np.argsort(bus_t, kind="stable")
    read = np.minimum(np.searchsorted(reads, bus_t[order] + USB_FRAME_S), len(reads) - 1)
    first_in_read = np.concatenate([[True], read[1:] != read[:-1]])
    index_in_read = np.arange(len(read)) - np.maximum.accumulate(np.where(first_in_read, np.arange(len(read)), 0))
    per_frame = rng.uniform(*FRAME_READ_S)
    host = np.empty(len(bus_t))
    host[order] = reads[read] + index_in_read * per_frame
    return _stalls(settings, bus_t, host, rng, lambda end: per_frame)


def simulate_can(
    settings: SimSettings,
    trajectory: Trajectory,
    sensors: Sensors,
    extra: tuple[Encoded, ...] = (),
) -> CanLog:
    """All cyclic messages of the drive's DBC (plus ``extra`` groups of frames, e.g. OBD-II polling), ordered
    and timestamped as the host logs them (Unix s)."""
    db = vehicle_db(settings)
    mapping = signal_specs(settings)
    protected = set(e2e_messages(settings))
    rng = sensors.rng
    ecus = sorted({sender for m in db.messages for sender in m.senders})
    ppm = dict(zip(ecus, rng.uniform(-ECU_CLOCK_PPM, ECU_CLOCK_PPM, len(ecus)) * 1e-6, strict=True))
    encoded = [
        _encode_message(m, trajectory, sensors, ppm[m.senders[0]] if m.senders else 0.0, mapping, m.name in protected)
        for m in sorted(db.messages, key=lambda m: m.frame_id)
        if m.cycle_time and m.name in MESSAGE_MODELS
    ]
    encoded += extra
    bus_t = np.concatenate([e.bus_t for e in encoded])
    payloads = [p for e in encoded for p in e.payloads]
    if settings.can_poll_max_s > 0.0:
        host = polled_host_times(settings, bus_t, rng)
    else:
        host = host_times(settings, bus_t, rng)
    order = np.lexsort((bus_t, host))
    us = round(settings.start_unix_s * 1e6) + np.round(host[order] * 1e6).astype(np.int64)
    steps = np.arange(len(us))
    us = np.maximum.accumulate(us - steps) + steps
    keep = rng.random(len(us)) >= settings.can_drop_rate
    offsets = np.cumsum([0] + [len(e.bus_t) for e in encoded])
    owner = np.searchsorted(offsets, order, side="right") - 1
    frames: list[can.Message] = []
    t_rows: list[float] = []
    q_rows: list[str] = []
    v_rows: list[float] = []
    for u, i, e_idx in zip(us[keep].tolist(), order[keep].tolist(), owner[keep].tolist(), strict=True):
        e = encoded[e_idx]
        t = u / 1e6
        frames.append(
            can.Message(
                timestamp=t, arbitration_id=e.frame_id, is_extended_id=False, data=payloads[i], channel=e.channel
            )
        )
        t_rows.extend([t] * len(e.quantities))
        q_rows.extend(e.quantities)
        v_rows.extend(e.values[i - offsets[e_idx]].tolist())
    return CanLog(frames, np.array(t_rows, dtype=float), np.array(q_rows, dtype=str), np.array(v_rows, dtype=float))
