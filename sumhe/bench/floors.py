"""Two dead-reckoning floors for GNSS outages on recorded drives: what an estimator must beat to be worth running.

* :func:`plain_floor`: dead reckoning from the last fix before the outage, its heading from that fix's course (else
  its heading, else the direction from the fix before it), the CAN speed and yaw rate as they read;
* :func:`calibrated_floor`: the same from the last fix, with the yaw-rate bias, the speed scale and the heading
  fitted by least squares to the fixes of the ``window_s`` before the outage (scipy's ``least_squares``: the
  dead-reckoned track of those seconds against their fixes, its start position free too).

Both integrate with :func:`sumhe.model.su.integrate_odometry` on a :class:`CanTrack` (the CAN speed and yaw rate on
one fine grid, moved back by the config's CAN delay). Fixes are taken at the times they are stamped with; the
floors' own positions are compared with the fixes removed (:mod:`sumhe.bench.outages`). Pure: arrays in, arrays
out. Units: s, m, m/s, rad, rad/s; azimuth clockwise from north, yaw rate anticlockwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from sumhe.model.su import integrate_odometry

FloatArray = NDArray[np.float64]

GRID_S = 0.05
"""Step of the CAN grid the floors integrate on (s)."""
FIT_WINDOW_S = 30.0
MIN_FIT_FIXES = 5
MAX_HEADING_GAP_S = 2.0
"""The direction between two fixes stands in for a course only when they are this close (s)."""
MIN_MOVING_MPS = 1.0
SCALE_BOUNDS = (0.8, 1.25)
BIAS_BOUND_RPS = math.radians(3.0)


@dataclass(frozen=True, slots=True)
class CanTrack:
    """The CAN speed (m/s) and yaw rate (rad/s) on one grid of times ``t`` (s), linear in between."""

    t: FloatArray
    speed: FloatArray
    yaw: FloatArray

    @classmethod
    def of(
        cls,
        t_speed: FloatArray,
        speed: FloatArray,
        t_yaw: FloatArray,
        yaw: FloatArray,
        delay_s: float = 0.0,
        step_s: float = GRID_S,
    ) -> CanTrack:
        """Both quantities on a grid of ``step_s`` over the span they share; a sample stamped t measures the car at
        ``t - delay_s``. ValueError without two samples of each."""
        if len(t_speed) < 2 or len(t_yaw) < 2:
            raise ValueError("CanTrack: needs two CAN speed and two yaw-rate samples")
        ts, ty = np.asarray(t_speed, float) - delay_s, np.asarray(t_yaw, float) - delay_s
        t = np.arange(max(ts[0], ty[0]), min(ts[-1], ty[-1]), step_s)
        return cls(t, np.interp(t, ts, speed), np.interp(t, ty, yaw))

    def reckon(
        self,
        t0: float,
        east0: float,
        north0: float,
        phi0: float,
        t_eval: FloatArray,
        speed_scale: float = 1.0,
        bias_rps: float = 0.0,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """East, north and azimuth at the times ``t_eval`` (>= t0) dead-reckoned from ``(east0, north0, phi0)`` at
        ``t0`` with ``speed_scale x`` the CAN speed and the CAN yaw rate ``- bias_rps``."""
        t_end = float(np.max(t_eval)) if len(t_eval) else t0
        inner = self.t[(self.t > t0) & (self.t < t_end)]
        grid = np.concatenate([[t0], inner, [t_end]]) if t_end > t0 else np.array([t0, t0 + 1e-9])
        v = speed_scale * np.interp(grid, self.t, self.speed)
        w = np.interp(grid, self.t, self.yaw) - bias_rps
        east, north, phi = integrate_odometry(grid, v, w, east0, north0, phi0)
        return np.interp(t_eval, grid, east), np.interp(t_eval, grid, north), np.interp(t_eval, grid, phi)


@dataclass(frozen=True, slots=True)
class Fixes:
    """The valid fixes of a drive in a local frame: times (s), east and north (m), course and heading (rad; NaN
    where a fix has none)."""

    t: FloatArray
    east: FloatArray
    north: FloatArray
    course: FloatArray
    heading: FloatArray

    def last_before(self, t: float) -> int:
        """Index of the last fix before ``t``; -1 if none."""
        return int(np.searchsorted(self.t, t, side="left")) - 1

    def azimuth_at(self, i: int) -> float:
        """The fix's course, else its heading, else the direction from the fix before (NaN if none of them)."""
        for values in (self.course, self.heading):
            if math.isfinite(values[i]):
                return float(values[i])
        if i > 0 and self.t[i] - self.t[i - 1] <= MAX_HEADING_GAP_S:
            de, dn = self.east[i] - self.east[i - 1], self.north[i] - self.north[i - 1]
            if math.hypot(de, dn) >= MIN_MOVING_MPS * (self.t[i] - self.t[i - 1]):
                return math.atan2(de, dn)
        return math.nan


def plain_floor(track: CanTrack, fixes: Fixes, start: float, t_eval: FloatArray) -> FloatArray:
    """East/north (n x 2, m) at the removed fixes' times ``t_eval`` of dead reckoning from the last fix before the
    outage ``start`` (NaN where no fix or no heading precedes it)."""
    i = fixes.last_before(start)
    phi = fixes.azimuth_at(i) if i >= 0 else math.nan
    if not math.isfinite(phi):
        return np.full((len(t_eval), 2), math.nan)
    east, north, _ = track.reckon(float(fixes.t[i]), float(fixes.east[i]), float(fixes.north[i]), phi, t_eval)
    return np.column_stack([east, north])


@dataclass(frozen=True, slots=True)
class FloorFit:
    """What :func:`fit_before` found: speed scale, yaw-rate bias (rad/s), the azimuth at the last fix (rad), the
    rms of the fit (m) and the number of fixes."""

    speed_scale: float
    bias_rps: float
    azimuth: float
    rms_m: float
    fixes: int


def fit_before(track: CanTrack, fixes: Fixes, start: float, window_s: float = FIT_WINDOW_S) -> FloorFit | None:
    """Speed scale, yaw-rate bias and heading by least squares on the fixes of the ``window_s`` before ``start``
    (the track dead-reckoned from the window's first fix, its position and heading free, against the fixes);
    None with fewer than :data:`MIN_FIT_FIXES` fixes or without a heading to start from."""
    i = fixes.last_before(start)
    inside = np.flatnonzero((fixes.t >= start - window_s) & (fixes.t < start))
    if i < 0 or len(inside) < MIN_FIT_FIXES or fixes.t[inside[0]] < track.t[0]:
        return None
    j = int(inside[0])
    phi0 = fixes.azimuth_at(j)
    if not math.isfinite(phi0):
        k = int(inside[-1])
        phi0 = math.atan2(fixes.east[k] - fixes.east[j], fixes.north[k] - fixes.north[j])
    t, e, n = fixes.t[inside], fixes.east[inside], fixes.north[inside]

    def residuals(p: FloatArray) -> FloatArray:
        east, north, _ = track.reckon(float(t[0]), p[0], p[1], p[2], t, p[3], p[4])
        return np.concatenate([east - e, north - n])  # type: ignore[no-any-return]

    x0 = np.array([e[0], n[0], phi0, 1.0, 0.0])
    lower = [-np.inf, -np.inf, -np.inf, SCALE_BOUNDS[0], -BIAS_BOUND_RPS]
    upper = [np.inf, np.inf, np.inf, SCALE_BOUNDS[1], BIAS_BOUND_RPS]
    sol = least_squares(residuals, x0, bounds=(lower, upper), x_scale=[1.0, 1.0, 0.01, 0.01, 0.001])
    p = sol.x
    _, _, phi = track.reckon(float(t[0]), p[0], p[1], p[2], np.array([fixes.t[i]]), p[3], p[4])
    rms = math.sqrt(float(np.mean(np.square(sol.fun))) * 2.0)
    return FloorFit(float(p[3]), float(p[4]), float(phi[0]), rms, len(inside))


def calibrated_floor(
    track: CanTrack, fixes: Fixes, start: float, t_eval: FloatArray, window_s: float = FIT_WINDOW_S
) -> FloatArray:
    """East/north (n x 2, m) at ``t_eval`` of dead reckoning from the last fix before ``start`` with the speed
    scale, yaw-rate bias and heading :func:`fit_before` found (NaN where it found none)."""
    fit = fit_before(track, fixes, start, window_s)
    if fit is None:
        return np.full((len(t_eval), 2), math.nan)
    i = fixes.last_before(start)
    east, north, _ = track.reckon(
        float(fixes.t[i]),
        float(fixes.east[i]),
        float(fixes.north[i]),
        fit.azimuth,
        t_eval,
        fit.speed_scale,
        fit.bias_rps,
    )
    return np.column_stack([east, north])
