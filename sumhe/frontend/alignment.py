"""Clock alignment between the GNSS receiver and the CAN sensors, learned from the data.

A fix's position, course and speed are true at one instant, which on the CAN clock (the frames' timestamps) lies
``gps_time_offset_s`` from the time the fix was stamped with (its UTC time, or the time its frame arrived): a host
clock off UTC, a receiver's solution latency, a logger that stamps GNSS frames on arrival. Real recordings show
-0.4 to +0.2 s (``docs/frontend.md``); at 30 m/s, 0.3 s is 9 m along the road, more than the receiver's error.

The offset is measured the way a test engineer would, by the lag that best lines up two measurements of one
quantity: the receiver's speed over ground against the CAN speed (every speed change carries it), and the rate of
the receiver's course against the CAN yaw rate (every turn carries it). Both are linear least squares for a given
lag (a scale, and for the yaw rate a bias); the lag is the minimum of the residual over a grid of lags, refined by
the parabola through its neighbours, with the standard error from the parabola's curvature. Pure functions on
arrays (:func:`speed_lag`, :func:`course_lag`), used offline by ``sumhe calibrate`` and on line by
:class:`ClockLearner`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

LAGS_S = np.round(np.arange(-1.0, 1.0001, 0.02), 6)
"""The lags tried (s): a receiver's latency plus a clock's offset stays within a second."""
MIN_SPEED_MPS = 2.0
"""Course and Doppler speed are used above this speed only (below it the course is noise)."""
MIN_PAIRS = 30


@dataclass(frozen=True, slots=True)
class LagFit:
    """A lag (s) with its standard error, the fitted scale and offset of the relation at that lag, the rms of the
    residuals and the number of measurements. ``lag_s`` > 0: the GNSS quantity follows the CAN one by ``lag_s``."""

    lag_s: float
    std_s: float
    scale: float
    offset: float
    rms: float
    n: int


def _refine(lags: NDArray[np.float64], rss: NDArray[np.float64], n: int, params: int) -> tuple[float, float]:
    """The minimum of ``rss`` over ``lags`` refined by a parabola through its neighbours, and its standard error
    ``sqrt(sigma^2 / c)`` with ``rss ~ rss_min + c (lag - lag_min)^2`` and ``sigma^2 = rss_min / (n - params)``
    (inf at the grid's ends or with a flat minimum: the lag is not determined)."""
    i = int(np.argmin(rss))
    if i == 0 or i == len(lags) - 1:
        return float(lags[i]), math.inf
    h = float(lags[i + 1] - lags[i])
    a, b, c = rss[i - 1], rss[i], rss[i + 1]
    curvature = (a - 2.0 * b + c) / (2.0 * h * h)
    if not curvature > 0:
        return float(lags[i]), math.inf
    shift = (a - c) / (4.0 * curvature * h)
    lag = float(lags[i]) + float(np.clip(shift, -h, h))
    sigma2 = b / max(n - params, 1)
    return lag, math.sqrt(sigma2 / curvature)


def speed_lag(
    t_fix: ArrayLike, gnss_speed: ArrayLike, t_can: ArrayLike, can_speed: ArrayLike, lags: ArrayLike = LAGS_S
) -> LagFit | None:
    """The lag of the receiver's speed over ground behind the CAN speed: ``gnss(t) = scale * can(t - lag)``
    (speeds in m/s, times in s on one clock; CAN samples time-ordered). None with fewer than ``MIN_PAIRS``
    fixes above ``MIN_SPEED_MPS`` inside the CAN data."""
    tf, g = np.asarray(t_fix, float), np.asarray(gnss_speed, float)
    tc, c = np.asarray(t_can, float), np.asarray(can_speed, float)
    lags = np.asarray(lags, float)
    if len(tc) < 2:
        return None
    ok = np.isfinite(g) & (np.abs(g) > MIN_SPEED_MPS) & (tf - lags.max() > tc[0]) & (tf - lags.min() < tc[-1])
    tf, g = tf[ok], np.abs(g[ok])
    if len(g) < MIN_PAIRS:
        return None
    can = np.abs(np.interp(tf[None, :] - lags[:, None], tc, c))
    scale = np.einsum("ij,j->i", can, g) / np.maximum(np.einsum("ij,ij->i", can, can), 1e-12)
    rss = np.sum(np.square(g[None, :] - scale[:, None] * can), axis=1)
    lag, std = _refine(lags, rss, len(g), 2)
    i = int(np.argmin(rss))
    return LagFit(lag, std, float(scale[i]), 0.0, math.sqrt(float(rss[i]) / len(g)), len(g))


def _cumulative(t: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])


def course_lag(
    t_fix: ArrayLike,
    course_rad: ArrayLike,
    speed_mps: ArrayLike,
    t_yaw: ArrayLike,
    yaw_rps: ArrayLike,
    lags: ArrayLike = LAGS_S,
    max_gap_s: float = 1.5,
) -> LagFit | None:
    """The lag of the receiver's course behind the CAN yaw rate: the course's rate between consecutive fixes
    (clockwise) against ``-(yaw - bias) * scale`` averaged over the same interval ``lag`` earlier. ``scale`` is the
    yaw-rate scale (true = scale x (CAN - bias)), ``offset`` the bias (rad/s). Fixes below ``MIN_SPEED_MPS`` or
    more than ``max_gap_s`` apart are left out; None with fewer than ``MIN_PAIRS`` pairs."""
    tf, crs, spd = np.asarray(t_fix, float), np.asarray(course_rad, float), np.asarray(speed_mps, float)
    tw, w = np.asarray(t_yaw, float), np.asarray(yaw_rps, float)
    lags = np.asarray(lags, float)
    if len(tw) < 2 or len(tf) < 2:
        return None
    ok = np.isfinite(crs) & np.isfinite(spd) & (np.abs(spd) > MIN_SPEED_MPS)
    dt = np.diff(tf)
    pair = ok[1:] & ok[:-1] & (dt > 0) & (dt <= max_gap_s)
    t1, t2 = tf[:-1][pair], tf[1:][pair]
    inside = (t1 - lags.max() > tw[0]) & (t2 - lags.min() < tw[-1])
    t1, t2 = t1[inside], t2[inside]
    dcrs = np.angle(np.exp(1j * np.diff(crs)))[pair][inside]
    if len(t1) < MIN_PAIRS:
        return None
    rate = -dcrs / (t2 - t1)
    cum = _cumulative(tw, w)
    mean = (np.interp(t2[None, :] - lags[:, None], tw, cum) - np.interp(t1[None, :] - lags[:, None], tw, cum)) / (
        t2 - t1
    )
    rss = np.empty(len(lags))
    coef = np.empty((len(lags), 2))
    for k in range(len(lags)):
        a = np.column_stack([mean[k], np.ones(len(rate))])
        coef[k], *_ = np.linalg.lstsq(a, rate, rcond=None)
        rss[k] = float(np.sum(np.square(rate - a @ coef[k])))
    lag, std = _refine(lags, rss, len(rate), 3)
    i = int(np.argmin(rss))
    scale, intercept = coef[i]
    bias = -intercept / scale if scale else math.nan
    return LagFit(lag, std, float(scale), float(bias), math.sqrt(float(rss[i]) / len(rate)), len(rate))


class ClockLearner:
    """The GNSS time offset learned on line from the receiver's speed over ground and the CAN speed
    (:func:`speed_lag` over the last ``window_s`` s, refitted every ``refit_s`` s). ``offset_s`` is the offset
    to add to a fix's stamped time: ``initial_s`` until a fit's standard error is below ``max_std_s``, then the
    newest such fit's ``-lag``."""

    def __init__(
        self, initial_s: float = 0.0, window_s: float = 300.0, refit_s: float = 10.0, max_std_s: float = 0.03
    ) -> None:
        self.offset_s = initial_s
        self.std_s = math.inf
        self.fits = 0
        self.window_s, self.refit_s, self.max_std_s = window_s, refit_s, max_std_s
        self._fixes: deque[tuple[float, float]] = deque()
        self._can: deque[tuple[float, float]] = deque()
        self._next_fit = -math.inf

    def add_can_speed(self, t: float, speed_mps: float) -> None:
        """A CAN speed sample (s, m/s) on the CAN clock."""
        self._can.append((t, speed_mps))

    def add_fix(self, t: float, speed_mps: float | None) -> None:
        """A fix's stamped time (s, before the offset) and its speed over ground (m/s, None if it has none)."""
        if speed_mps is not None and math.isfinite(speed_mps):
            self._fixes.append((t, speed_mps))
        self._trim(t - self.window_s)
        if t >= self._next_fit:
            self._next_fit = t + self.refit_s
            self._fit()

    def _trim(self, t_min: float) -> None:
        while self._fixes and self._fixes[0][0] < t_min:
            self._fixes.popleft()
        while len(self._can) > 2 and self._can[1][0] < t_min - 2.0:
            self._can.popleft()

    def _fit(self) -> None:
        if len(self._fixes) < MIN_PAIRS or len(self._can) < 2:
            return
        f, c = np.array(self._fixes), np.array(self._can)
        fit = speed_lag(f[:, 0], f[:, 1], c[:, 0], c[:, 1])
        if fit is not None and fit.std_s <= self.max_std_s:
            self.offset_s, self.std_s = -fit.lag_s, fit.std_s
            self.fits += 1
