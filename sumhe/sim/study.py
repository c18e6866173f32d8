"""Measure a real CAN-logger drive's sensors, to check the simulator's error ranges against real recordings.

``sumhe simulate --study-real LOG [LOG ...] --gps-dbc FILE`` prints what :func:`study_real` measures on a
drive logged like the CANedge + CANmod.gps one in ``shared/data/real_drives`` (GNSS and IMU as CAN frames
``gnss_pos``, ``gnss_time``, ``gnss_speed``, ``gnss_attitude``, ``gnss_imu`` of the logger's DBC; OBD-II mode-01
replies on 0x7E8 decoded by ``dbc/obd2.dbc``), every figure on the frames' own clock:

- OBD speed (PID 0x0D): reply rate, quantum, and the scale and delay against the GNSS speed (least squares
  over a grid of delays; positive delay = the OBD value is older than the GNSS value received at the same time);
- yaw rate (the IMU axis ``--imu-yaw``, anticlockwise positive): bias and noise at standstill (OBD speed 0),
  quantum, and scale and bias against the GNSS heading's rate over 10 s windows at the best lag;
- GNSS: fix rate, missed epochs, share of valid fixes, the accuracy field; its UTC time tags against the frame
  clock (offset, drift in ppm, spread); heading minus course from the positions;
- frame timing: the IMU message's period percentiles and its share of gaps under 1 ms (bursts).

It is a measurement, not a fit the simulator uses: docs/simulator.md sets the ranges from it and other cars.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from cantools.database.can import Database
from numpy.typing import NDArray

from sumhe.io.can import load_dbc, read_log
from sumhe.sim.production import OBD_DBC, OBD_REPLY_ID

FloatArray = NDArray[np.float64]

SPEED_PID = 0x0D
MOVING_MPS = 3.0
WINDOW_S = 10.0
"""Window over which the GNSS heading change is compared with the integrated yaw rate."""
DELAYS_S = np.round(np.arange(-1.0, 1.0001, 0.01), 3)
LAGS_S = np.round(np.arange(0.0, 0.8001, 0.05), 3)


@dataclass(frozen=True, slots=True)
class StudyRow:
    """One measured figure: name, value(s) as text, unit, and how it was measured."""

    name: str
    value: str
    unit: str
    how: str


@dataclass(frozen=True, eq=False)
class Series:
    """One decoded signal: frame times (s, the logger's clock) and values (DBC units)."""

    t: FloatArray
    v: FloatArray


def decode_drive(logs: Iterable[str | Path], gps_db: Database, obd_db: Database) -> dict[str, Series]:
    """Every signal of the GNSS/IMU messages (``message.signal``) and the OBD speed (``obd.speed_kmh``)."""
    rows: dict[str, list[tuple[float, float]]] = {}
    gps_ids = {m.frame_id: m for m in gps_db.messages}
    obd = obd_db.get_message_by_frame_id(OBD_REPLY_ID)
    for path in logs:
        for msg in read_log(path):
            if msg.arbitration_id == OBD_REPLY_ID and not msg.is_extended_id:
                values = obd.decode(bytes(msg.data), decode_choices=False)
                if values.get("PID") == SPEED_PID and "VehicleSpeed" in values:
                    rows.setdefault("obd.speed_kmh", []).append((msg.timestamp, float(values["VehicleSpeed"])))
                continue
            message = gps_ids.get(msg.arbitration_id)
            if message is None or msg.is_extended_id or len(msg.data) < message.length:
                continue
            for name, value in message.decode(bytes(msg.data), decode_choices=False).items():
                rows.setdefault(f"{message.name}.{name}", []).append((msg.timestamp, float(value)))
    return {k: Series(*np.array(v, dtype=float).T) for k, v in rows.items()}


def _pct(values: FloatArray, qs: Sequence[float], fmt: str = "{:.3f}") -> str:
    return " / ".join(fmt.format(v) for v in np.percentile(values, qs)) if values.size else "-"


def quantum(values: FloatArray) -> float:
    """The smallest step between distinct values (the resolution a signal is sent with)."""
    steps = np.diff(np.unique(values))
    return float(steps.min()) if steps.size else math.nan


def scale_and_delay(t: FloatArray, v: FloatArray, ref_t: FloatArray, ref: FloatArray) -> tuple[float, float, float]:
    """(scale, delay_s, rms): ``v(t) ~ scale * ref(t - delay)`` by least squares, delay on :data:`DELAYS_S`,
    over samples where the reference moves faster than :data:`MOVING_MPS`."""
    best = (math.nan, math.nan, math.inf)
    for delay in DELAYS_S:
        r = np.interp(t - delay, ref_t, ref)
        use = (r > MOVING_MPS) & (t - delay > ref_t[0]) & (t - delay < ref_t[-1])
        if use.sum() < 10:
            continue
        scale = float(np.sum(v[use] * r[use]) / np.sum(r[use] ** 2))
        rms = float(np.sqrt(np.mean((v[use] - scale * r[use]) ** 2)))
        if rms < best[2]:
            best = (scale, float(delay), rms)
    return best


def yaw_fit(
    imu_t: FloatArray, yaw_dps: FloatArray, head_t: FloatArray, head_deg: FloatArray, moving: FloatArray
) -> tuple[float, float, float, float]:
    """(scale, bias_dps, lag_s, rms_dps): the GNSS heading's rate over :data:`WINDOW_S` windows (anticlockwise)
    ~ scale * (mean yaw rate over the window ``lag`` earlier - bias), the lag on :data:`LAGS_S`."""
    integral = np.concatenate([[0.0], np.cumsum(np.diff(imu_t) * (yaw_dps[1:] + yaw_dps[:-1]) / 2.0)])
    heading = np.unwrap(np.radians(head_deg))
    step = max(1, round(WINDOW_S / max(float(np.median(np.diff(head_t))), 1e-3)))
    i0 = np.arange(len(head_t) - step)
    i1 = i0 + step
    span = head_t[i1] - head_t[i0]
    use = (np.abs(span - WINDOW_S) < 0.2 * WINDOW_S) & (moving[i0] > 0) & (moving[i1] > 0)
    rate = -np.degrees(heading[i1] - heading[i0])[use] / span[use]
    best = (math.nan, math.nan, math.nan, math.inf)
    for lag in LAGS_S:
        mean_yaw = (np.interp(head_t[i1] - lag, imu_t, integral) - np.interp(head_t[i0] - lag, imu_t, integral))[use]
        a = np.column_stack([mean_yaw / span[use], np.ones(int(use.sum()))])
        if len(a) < 10:
            break
        (scale, c), *_ = np.linalg.lstsq(a, rate, rcond=None)
        rms = float(np.std(rate - a @ [scale, c]))
        if rms < best[3]:
            best = (float(scale), float(-c / scale), float(lag), rms)
    return best


def heading_minus_course(t: FloatArray, lat: FloatArray, lon: FloatArray, head_deg: FloatArray) -> FloatArray:
    """GNSS heading minus the course of the positions (central differences), deg, where faster than 10 m/s."""
    east = np.radians(lon - lon[0]) * 6_371_000.0 * math.cos(math.radians(lat[0]))
    north = np.radians(lat - lat[0]) * 6_371_000.0
    de, dn, dt = east[2:] - east[:-2], north[2:] - north[:-2], t[2:] - t[:-2]
    course = np.degrees(np.arctan2(de, dn))
    diff = (head_deg[1:-1] - course + 180.0) % 360.0 - 180.0
    return diff[(np.hypot(de, dn) / np.maximum(dt, 1e-3) > 10.0) & (dt < 2.5)]


def study_real(
    logs: Sequence[str | Path], gps_dbc: str | Path, imu_yaw: str = "gnss_imu.AngularRateX"
) -> list[StudyRow]:
    """The measured figures of one recorded drive (see the module docstring)."""
    s = decode_drive(logs, load_dbc(gps_dbc), load_dbc(OBD_DBC))
    rows: list[StudyRow] = []
    valid = s["gnss_pos.PositionValid"].v > 0
    pos_t = s["gnss_pos.PositionValid"].t
    epoch = s["gnss_time.Epoch"]
    fix_dt = np.diff(epoch.v)
    rows += [
        StudyRow("GNSS epochs", f"{len(epoch.t)}", "", "gnss_time frames"),
        StudyRow("GNSS fix period p50", f"{np.median(fix_dt):.3f}", "s", "steps of the UTC epoch"),
        StudyRow("GNSS epochs missed", f"{100.0 * np.sum(np.round(fix_dt) - 1) / len(fix_dt):.1f}", "%", "gaps"),
        StudyRow("GNSS valid fixes", f"{100.0 * valid.mean():.1f}", "%", "PositionValid"),
        StudyRow("GNSS first valid fix after", f"{pos_t[np.argmax(valid)] - pos_t[0]:.0f}", "s", "from 1st frame"),
        StudyRow(
            "GNSS accuracy field p5/p50/p95",
            _pct(s["gnss_pos.PositionAccuracy"].v[valid], (5, 50, 95), "{:.0f}"),
            "m",
            "valid fixes",
        ),
    ]
    offset = epoch.t - epoch.v
    fit = np.polyfit(epoch.t - epoch.t[0], offset, 1)
    resid = offset - np.polyval(fit, epoch.t - epoch.t[0])
    rows += [
        StudyRow("frame time - UTC tag p50", f"{np.median(offset):.3f}", "s", "clock offset + latency"),
        StudyRow("  its drift", f"{fit[0] * 1e6:.0f}", "ppm", "linear fit"),
        StudyRow("  spread about the drift p5/p50/p95", _pct(resid, (5, 50, 95)), "s", "latency jitter"),
    ]
    obd = s.get("obd.speed_kmh")
    speed = s["gnss_speed.Speed"]
    if obd is not None:
        scale, delay, rms = scale_and_delay(obd.t, obd.v / 3.6, speed.t[valid], speed.v[valid])
        rows += [
            StudyRow("OBD speed replies", f"{len(obd.t)}", "", "PID 0x0D on 0x7E8"),
            StudyRow("OBD speed period p1/p50/p99", _pct(np.diff(obd.t), (1, 50, 99)), "s", "reply spacing"),
            StudyRow("OBD speed quantum", f"{quantum(obd.v):g}", "km/h", "smallest step"),
            StudyRow("OBD speed / GNSS speed", f"{scale:.4f}", "", f"LS at the best delay, rms {rms:.3f} m/s"),
            StudyRow("OBD speed delay vs GNSS frames", f"{delay:.2f}", "s", "grid -1..1 s"),
        ]
    message, _, signal = imu_yaw.partition(".")
    imu = s[imu_yaw]
    period = np.diff(imu.t) * 1000.0
    rows += [
        StudyRow(f"{message} period p1/p50/p99", _pct(period, (1, 50, 99), "{:.1f}"), "ms", "frame gaps"),
        StudyRow(f"{message} period max", f"{period.max():.1f}", "ms", ""),
        StudyRow(f"{message} gaps < 1 ms", f"{100.0 * np.mean(period < 1.0):.2f}", "%", "bursts"),
        StudyRow(f"yaw rate ({signal}) quantum", f"{quantum(imu.v):g}", "deg/s", "smallest step"),
    ]
    if obd is not None:
        still = np.interp(imu.t, obd.t, obd.v) == 0.0
        rows += [
            StudyRow("yaw rate at standstill mean", f"{imu.v[still].mean():.3f}", "deg/s", "bias, OBD speed 0"),
            StudyRow("yaw rate at standstill std", f"{imu.v[still].std():.3f}", "deg/s", "noise + quantum"),
        ]
    att = s["gnss_attitude.Heading"]
    ok = (s["gnss_attitude.AttitudeValid"].v > 0) & valid
    moving = (np.interp(att.t, speed.t, speed.v) > MOVING_MPS).astype(float)
    scale, bias, lag, rms = yaw_fit(imu.t, imu.v, att.t[ok], att.v[ok], moving[ok])
    lat, lon = s["gnss_pos.Latitude"].v[ok], s["gnss_pos.Longitude"].v[ok]
    rows += [
        StudyRow("GNSS heading rate / yaw rate", f"{scale:.4f}", "", f"{WINDOW_S:g} s windows, rms {rms:.3f} deg/s"),
        StudyRow("yaw rate bias (moving)", f"{bias:.3f}", "deg/s", "same fit"),
        StudyRow("GNSS frames lag the yaw rate by", f"{lag:.2f}", "s", "best lag of the fit"),
        StudyRow(
            "heading - course of positions p5/p50/p95",
            _pct(heading_minus_course(att.t[ok], lat, lon, att.v[ok]), (5, 50, 95), "{:.2f}"),
            "deg",
            "> 10 m/s",
        ),
    ]
    return rows


def format_study(rows: Iterable[StudyRow], title: str) -> str:
    """A fixed-width text table of the study's rows under ``title``."""
    lines = [title, f"{'figure':<42} {'value':>22} {'unit':>6}  how"]
    lines += [f"{r.name:<42} {r.value:>22} {r.unit:>6}  {r.how}" for r in rows]
    return "\n".join(lines)
