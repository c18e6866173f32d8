"""OBD-II polling as a logger on the car's diagnostic port sees it: mode-01 requests and the engine ECU's replies.

Every ``1 / obd_rate_hz`` s the logger sends one functional request (id 0x7DF, ``02 01 PID`` + padding) per
polled PID, :data:`REQUEST_SPACING_S` apart, and the engine ECU answers on 0x7E8 a few ms later with a
single-frame reply encoded by cantools from ``dbc/obd2.dbc`` (message ``OBD2``, multiplexed by PID). The speed
(PID 0x0D) is the ECU's vehicle speed of ``obd_delay_s`` before the reply, times the speed scale, in whole km/h
(rounded or truncated: ``obd_rounding``); now and then the ECU does not answer. Both directions are logged, as
a SocketCAN logger that sees its own frames logs them; the padding byte (0x00, 0x55 or 0xAA) is drawn per drive.
"""

from __future__ import annotations

import math

import numpy as np

from sumhe.sim.can_frames import MIN_WHEEL_SPEED_MPS, Encoded, Sensors
from sumhe.sim.production import OBD_REPLY_ID, OBD_REQUEST_ID, obd_db
from sumhe.sim.vehicle import Trajectory

SPEED_PID = 0x0D
POLLED_PIDS = (0x0C, SPEED_PID, 0x05, 0x11)
"""Engine speed, vehicle speed, coolant temperature, throttle position: what a fleet logger typically polls."""
REQUEST_SPACING_S = 0.02
REPLY_DELAY_S = (0.002, 0.012)
"""Range of the ECU's answer time after a request."""
NO_REPLY_RATE = 0.005
PADDING = (0x00, 0x55, 0xAA)
SCHEDULE_JITTER_S = 0.0005
KMH_PER_MPS = 3.6


def _pid_values(pid: int, speed_kmh: np.ndarray, accel: np.ndarray) -> tuple[str, np.ndarray]:
    """The signal of ``pid`` and its raw values (rpm from a fixed overall gearing, throttle from the acceleration)."""
    if pid == SPEED_PID:
        return "VehicleSpeed", speed_kmh
    if pid == 0x0C:
        rpm = np.clip(800.0 + 40.0 * speed_kmh, 800.0, 6000.0)
        return "EngineSpeed", np.round(rpm * 4.0)
    if pid == 0x05:
        return "CoolantTemperature", np.full(len(speed_kmh), 88.0 + 40.0)
    return "ThrottlePosition", np.round(np.clip(15.0 + 12.0 * accel, 0.0, 100.0) * 2.55)


def simulate_obd(trajectory: Trajectory, sensors: Sensors, rng: np.random.Generator) -> tuple[Encoded, ...]:
    """The request frames and the reply frames (the speed replies carry the mapped ``speed`` sample)."""
    cfg = sensors.settings
    message = obd_db().get_message_by_name("OBD2")
    pad = int(rng.choice(PADDING))
    cycle = 1.0 / cfg.obd_rate_hz
    starts = rng.uniform(0.0, cycle) + np.arange(math.ceil(cfg.duration_s / cycle) + 1) * cycle
    groups: list[Encoded] = []
    for j, pid in enumerate(POLLED_PIDS):
        request_t = starts + j * REQUEST_SPACING_S + rng.uniform(0.0, SCHEDULE_JITTER_S, len(starts))
        request_t = request_t[request_t < cfg.duration_s]
        reply_t = request_t + rng.uniform(*REPLY_DELAY_S, len(request_t))
        answered = (rng.random(len(reply_t)) >= NO_REPLY_RATE) & (reply_t < cfg.duration_s)
        reply_t = reply_t[answered]
        m = trajectory.at(reply_t - cfg.obd_delay_s)
        read = m.speed * sensors.speed_scale + sensors.noise(cfg.speed_noise_mps, len(reply_t))
        kmh = np.where(read >= MIN_WHEEL_SPEED_MPS, read, 0.0) * KMH_PER_MPS
        whole = np.clip(np.round(kmh) if cfg.obd_rounding == "round" else np.floor(kmh), 0.0, 255.0)
        name, raw = _pid_values(pid, whole, m.accel)
        length = 2 + message.get_signal_by_name(name).length // 8
        payloads = []
        for value in raw.tolist():
            data = message.encode({"Length": length, "Service": 0x41, "PID": pid, name: int(value)}, scaling=False)
            payloads.append(data[: 1 + length] + bytes([pad]) * (7 - length))
        request = bytes([0x02, 0x01, pid]) + bytes([pad]) * 5
        groups.append(Encoded(OBD_REQUEST_ID, request_t, [request] * len(request_t), [], np.empty((len(request_t), 0))))
        speed = pid == SPEED_PID
        values = (whole / KMH_PER_MPS)[:, None] if speed else np.empty((len(reply_t), 0))
        groups.append(Encoded(OBD_REPLY_ID, reply_t, payloads, ["speed"] if speed else [], values))
    return tuple(groups)
