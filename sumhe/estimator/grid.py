"""From time-ordered samples to the estimator's time grid: outputs, availability and error allowances.

The grid's steps are the GNSS epochs (the fixes' times ``t``: the time their position refers to, stamped once where
fixes enter, :func:`sumhe.io.fixtime.stamp_fix`); gaps longer than 1.5 nominal
periods (an outage) are filled with evenly spaced steps that carry only CAN outputs, and the grid reaches
the first and last sample. CAN speed and yaw rate are averaged over each step's half-intervals (linear
interpolation when no sample falls inside, nothing when the nearest sample is farther than
``can_max_gap_s``). Each output also gets a per-step *error allowance*: a bound on its measurement error
in its own unit, from the receiver's reported accuracy (GST sigmas, else quality / HDOP) and the CAN
sensors' resolution and noise; :mod:`sumhe.estimator.bounds` turns allowances into caps on r.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.errors import EstimatorInputError
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, GnssFix, Sample
from sumhe.model.su import GPS_SPEED_OUTPUT, SuModel, antenna_azimuth
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)

GGA_RTK_FIXED = 4
GGA_RTK_FLOAT = 5
CAN_USED = ("speed", "yaw_rate")
GPS_SPEED_RESOLUTION_MPS = 0.001 * 1852.0 / 3600.0
"""NMEA's speed over ground resolution (0.001 knot)."""


@dataclass(frozen=True)
class Grid:
    """Data of one estimation window on its step grid (``N`` steps, ``n`` outputs of the model).

    ``y`` holds the outputs (positions in the local frame, m; angles rad; CAN SI) with 0 where missing;
    ``avail`` says which are present; ``allow`` is each output's error allowance (its unit) where present.
    ``can_speed``/``can_yaw_rate`` are the CAN values on the grid (NaN where missing).
    """

    t: NDArray[np.float64]
    y: NDArray[np.float64]
    avail: NDArray[np.bool_]
    allow: NDArray[np.float64]
    can_speed: NDArray[np.float64]
    can_yaw_rate: NDArray[np.float64]
    frame: LocalFrame

    @property
    def h(self) -> NDArray[np.float64]:
        """Step lengths (s), ``N - 1`` of them."""
        return np.diff(self.t)

    @property
    def n_steps(self) -> int:
        return len(self.t)

    @property
    def gps(self) -> NDArray[np.bool_]:
        """Steps with a GNSS position (of antenna 1)."""
        return self.avail[:, 0]


def check_samples(samples: Sequence[Sample]) -> None:
    """Raise EstimatorInputError for input no estimator can use: empty, one sample, NaN, time going back."""
    if len(samples) < 2:
        raise EstimatorInputError(f"need at least 2 samples, got {len(samples)}")
    prev = -math.inf
    for i, s in enumerate(samples):
        if not isinstance(s, GnssFix | CanSample):
            raise EstimatorInputError(f"sample {i}: not a GnssFix or CanSample: {type(s).__name__}")
        if not math.isfinite(s.t):
            raise EstimatorInputError(f"sample {i}: time is not finite: {s.t!r}")
        if s.t < prev:
            raise EstimatorInputError(f"sample {i}: time goes backwards ({s.t:.3f} s after {prev:.3f} s)")
        prev = s.t
        if isinstance(s, CanSample) and not math.isfinite(s.value):
            raise EstimatorInputError(f"sample {i}: CAN {s.quantity} is not finite: {s.value!r}")
        if isinstance(s, GnssFix) and s.valid:
            for name in ("lat_deg", "lon_deg"):
                value = getattr(s, name)
                if value is None or not math.isfinite(value):
                    raise EstimatorInputError(f"sample {i}: valid fix with {name} = {value!r}")


def nominal_period(epochs: NDArray[np.float64], default: float) -> float:
    """The GNSS period (s) of epoch times: the median of the intervals within 1.5x the shortest (outage gaps left
    out), or ``default`` from fewer than three epochs (two fixes around an outage say nothing of the period)."""
    d = np.diff(np.unique(epochs))
    if len(d) < 2:
        return default
    return float(np.median(d[d <= 1.5 * d.min()]))


def gps_speed(speed_mps: float | None, can_speed: float | None, settings: EstimationSettings) -> float | None:
    """The speed a fix's speed over ground (m/s, >= 0) measures, with the sign of the CAN speed (reversing), or
    None: no speed, or below ``course_min_speed_mps`` (at walking pace Doppler speeds are biased upwards)."""
    if speed_mps is None or not math.isfinite(speed_mps) or speed_mps < settings.gnss.course_min_speed_mps:
        return None
    return -speed_mps if can_speed is not None and can_speed < 0.0 else speed_mps


def gps_sigma_m(fix: GnssFix, settings: EstimationSettings) -> tuple[float, float]:
    """1-sigma error (east, north) in m of a fix: GST sigmas, else by GGA quality (RTK), else HDOP x UERE."""
    if fix.sigma_lat_m is not None and fix.sigma_lon_m is not None:
        return fix.sigma_lon_m, fix.sigma_lat_m
    if fix.quality == GGA_RTK_FIXED:
        s = settings.gnss.sigma_rtk_m
    elif fix.quality == GGA_RTK_FLOAT:
        s = settings.gnss.sigma_float_m
    elif fix.hdop is not None and math.isfinite(fix.hdop):
        s = fix.hdop * settings.gnss.uere_m
    else:
        s = settings.gnss.sigma_m
    return s, s


def step_times(anchors: NDArray[np.float64], t_lo: float, t_hi: float, period: float) -> NDArray[np.float64]:
    """The grid: ``anchors`` (GNSS epochs, s), widened to [t_lo, t_hi] and with gaps filled at ``period``."""
    pts = np.unique(anchors)
    if pts[0] - t_lo > 0.5 * period:
        pts = np.concatenate([[t_lo], pts])
    if t_hi - pts[-1] > 0.5 * period:
        pts = np.concatenate([pts, [t_hi]])
    out = [pts[:1]]
    for a, b in itertools.pairwise(pts):
        n = round((b - a) / period)
        if n >= 2 and b - a > 1.5 * period:
            out.append(np.linspace(a, b, n + 1)[1:])
        else:
            out.append(np.array([b]))
    return np.concatenate(out)


def can_on_grid(ts: NDArray[np.float64], vs: NDArray[np.float64], t: NDArray[np.float64], max_gap: float) -> NDArray:
    """CAN values (``vs`` at times ``ts``) on the grid ``t``: mean over each step's half-intervals, else
    linear interpolation, else NaN where the nearest sample is more than ``max_gap`` s away."""
    out = np.full(len(t), np.nan)
    if len(ts) == 0:
        return out
    mid = 0.5 * (t[1:] + t[:-1])
    lo = np.concatenate([[t[0] - (mid[0] - t[0] if len(mid) else 0.05)], mid])
    hi = np.concatenate([mid, [t[-1] + (t[-1] - mid[-1] if len(mid) else 0.05)]])
    cum = np.concatenate([[0.0], np.cumsum(vs)])
    i0 = np.searchsorted(ts, lo, side="left")
    i1 = np.searchsorted(ts, hi, side="left")
    count = i1 - i0
    has = count > 0
    out[has] = (cum[i1[has]] - cum[i0[has]]) / count[has]
    near = np.abs(ts[np.clip(np.searchsorted(ts, t), 0, len(ts) - 1)] - t)
    near = np.minimum(near, np.abs(ts[np.clip(np.searchsorted(ts, t) - 1, 0, len(ts) - 1)] - t))
    interp = ~has & (near <= max_gap) & (t >= ts[0] - max_gap) & (t <= ts[-1] + max_gap)
    out[interp] = np.interp(t[interp], ts, vs)
    return out


def build_grid(
    samples: Sequence[Sample],
    model: SuModel,
    settings: EstimationSettings,
    frame: LocalFrame | None = None,
) -> Grid:
    """Check the samples and put them on the step grid of ``model``; EstimatorInputError if unusable.

    ``frame`` defaults to a local frame at the first valid fix. Fixes are projected into it at the datum's
    height ``frame.alt0_m`` (a level road; NMEA altitudes are above the geoid, not the ellipsoid, and mixing
    the two moves positions by ``dh * distance / R_earth``). Fixes of antenna 2 are used by ``su7`` only;
    Fix times ``t`` are their measurement times (:func:`sumhe.io.fixtime.stamp_fix`); CAN times are moved back
    by ``settings.can.delay_s``.
    """
    check_samples(samples)
    fixes = [s for s in samples if isinstance(s, GnssFix)]
    ant1 = [f for f in fixes if f.antenna != 2]
    ant2 = [f for f in fixes if f.antenna == 2 and model.antennas == 2]
    valid1 = [f for f in ant1 if f.valid]
    if len(valid1) < 2:
        raise EstimatorInputError(f"need at least 2 valid GNSS positions in the window, got {len(valid1)}")
    if frame is None:
        first = valid1[0]
        frame = LocalFrame(float(first.lat_deg), float(first.lon_deg), first.alt_m or 0.0)  # type: ignore[arg-type]
    cans = [s for s in samples if isinstance(s, CanSample)]
    t_can = {q: np.array([s.t - settings.can.delay_s for s in cans if s.quantity == q]) for q in CAN_USED}
    v_can = {q: np.array([s.value for s in cans if s.quantity == q]) for q in CAN_USED}
    epochs = np.array([f.t for f in ant1])
    t_all = np.concatenate([epochs, *t_can.values()])
    period = nominal_period(epochs, settings.gnss.period_s)
    t = step_times(epochs, float(t_all.min()), float(t_all.max()), period)
    n_out = model.n_outputs
    y = np.zeros((len(t), n_out))
    avail = np.zeros((len(t), n_out), dtype=bool)
    allow = np.ones((len(t), n_out))
    k_sig = settings.estimator.r_cap_sigmas
    for group, col in ((valid1, 0), ([f for f in ant2 if f.valid], 2)):
        if not group:
            continue
        tf = np.array([f.t for f in group])
        k = _nearest(t, tf, 0.5 * period)
        ok = k >= 0
        enu = frame.to_enu([f.lat_deg for f in group], [f.lon_deg for f in group], frame.alt0_m)
        sig = np.array([gps_sigma_m(f, settings) for f in group])
        for c in (0, 1):
            y[k[ok], col + c] = enu[ok, c]
            avail[k[ok], col + c] = True
            allow[k[ok], col + c] = k_sig * np.maximum(sig[ok, c], settings.gnss.resolution_m)
    can_speed, can_yaw = (can_on_grid(t_can[q], v_can[q], t, settings.can.max_gap_s) for q in CAN_USED)
    _angle_output(model, settings, t, y, avail, allow, valid1, can_speed, can_yaw, period)
    if GPS_SPEED_OUTPUT in model.outputs:
        j = model.outputs.index(GPS_SPEED_OUTPUT)
        for k, value in _gps_speeds(valid1, t, can_speed, settings, period):
            y[k, j], avail[k, j] = value, True
        allow[:, j] = k_sig * max(settings.gnss.speed_sigma_mps, GPS_SPEED_RESOLUTION_MPS)
    has_bias = "yaw_rate_bias" in model.states
    has_scale = "speed_scale" in model.states
    i_v, i_w = model.j_can_speed, model.j_can_yaw_rate
    for col, values in ((i_v, can_speed), (i_w, can_yaw)):
        ok = np.isfinite(values)
        y[ok, col] = values[ok]
        avail[ok, col] = True
    allow[:, i_v] = (
        0.5 * settings.can.speed_quantum_mps
        + k_sig * settings.can.speed_sigma_mps
        + (0.0 if has_scale else settings.can.speed_scale_max * np.abs(np.nan_to_num(can_speed)))
    )
    allow[:, i_w] = (
        0.5 * settings.can.yaw_rate_quantum_rps
        + k_sig * settings.can.yaw_rate_sigma_rps
        + (0.0 if has_bias else settings.can.yaw_rate_bias_max_rps)
    )
    log.debug("grid: %d steps over %.2f s, %d with GNSS", len(t), t[-1] - t[0], int(avail[:, 0].sum()))
    return Grid(t=t, y=y, avail=avail, allow=allow, can_speed=can_speed, can_yaw_rate=can_yaw, frame=frame)


def _nearest(t: NDArray[np.float64], tf: NDArray[np.float64], tol: float) -> NDArray[np.int64]:
    """Index of the grid step nearest to each time in ``tf``; -1 where farther than ``tol``."""
    k = np.clip(np.searchsorted(t, tf), 1, len(t) - 1)
    k = np.where(np.abs(t[k - 1] - tf) <= np.abs(t[k] - tf), k - 1, k)
    return np.where(np.abs(t[k] - tf) <= tol + 1e-9, k, -1)


def _gps_speeds(
    fixes: list[GnssFix],
    t: NDArray[np.float64],
    can_speed: NDArray[np.float64],
    settings: EstimationSettings,
    period: float,
) -> list[tuple[int, float]]:
    """(grid step, speed) of the fixes whose speed over ground counts (:func:`gps_speed`); ``period`` (s) the
    nominal step, half of which is the farthest a fix may be from its step."""
    out = []
    for f, k in zip(fixes, _nearest(t, np.array([f.t for f in fixes]), 0.5 * period), strict=True):
        if k >= 0:
            value = gps_speed(f.speed_mps, float(can_speed[k]) if math.isfinite(can_speed[k]) else None, settings)
            if value is not None:
                out.append((int(k), value))
    return out


def _angle_output(
    model: SuModel,
    settings: EstimationSettings,
    t: NDArray[np.float64],
    y: NDArray[np.float64],
    avail: NDArray[np.bool_],
    allow: NDArray[np.float64],
    fixes: list[GnssFix],
    can_speed: NDArray[np.float64],
    can_yaw: NDArray[np.float64],
    period: float,
) -> None:
    """Fill the azimuth output in place: xi of the antenna pair (su7) or the receiver's heading/course (su5).

    The allowance adds half a step of turning, ``h |omega| / 2``: with the paper's Euler steps the model's
    azimuth is the chord direction of the step, half a step behind the instantaneous one.
    """
    j = model.angle_outputs[0]
    h = np.concatenate([np.diff(t), [period]])
    turn = 0.5 * h * np.abs(np.nan_to_num(can_yaw))
    k_sig = settings.estimator.r_cap_sigmas
    if model.antennas == 2:
        both = avail[:, 0] & avail[:, 2]
        y[both, j] = antenna_azimuth(y[both, 0], y[both, 1], y[both, 2], y[both, 3])
        avail[both, j] = True
        allow[both, j] = (allow[both, 0] + allow[both, 2]) * math.sqrt(2) / settings.vehicle.antenna_distance_m + turn[
            both
        ]
        return
    k = _nearest(t, np.array([f.t for f in fixes]), 0.5 * period)
    for f, kk in zip(fixes, k, strict=True):
        if kk < 0:
            continue
        speed = f.speed_mps if f.speed_mps is not None else can_speed[kk]
        if settings.gnss.use_heading and f.heading_rad is not None and math.isfinite(f.heading_rad):
            angle, sigma = f.heading_rad, settings.gnss.heading_sigma_rad
        elif (
            f.course_rad is not None
            and math.isfinite(f.course_rad)
            and speed is not None
            and math.isfinite(speed)
            and speed >= settings.gnss.course_min_speed_mps
        ):
            angle, sigma = f.course_rad, settings.gnss.speed_sigma_mps / max(speed, 1e-3)
        else:
            continue
        y[kk, j] = angle
        avail[kk, j] = True
        allow[kk, j] = k_sig * sigma + turn[kk]
