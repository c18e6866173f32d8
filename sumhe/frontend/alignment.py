"""Clock alignment between the GNSS receiver and the CAN sensors, learned from the data.

A fix's position, course and speed are true at one instant, which on the CAN clock (the frames' timestamps) lies
``gps_time_offset_s`` from the time the fix was stamped with (its UTC time, or the time its frame arrived): a host
clock off UTC, a receiver's solution latency, a logger that stamps GNSS frames on arrival. Real recordings show
-0.4 to +0.2 s (``docs/frontend.md``); at 30 m/s, 0.3 s is 9 m along the road, more than the receiver's error.

The offset is measured the way a test engineer would, by the lag that best lines up two measurements of one
quantity: the receiver's speed over ground against the CAN speed (every speed change carries it), and the rate of
the receiver's course against the CAN yaw rate (every turn carries it). Both are linear least squares for a given
lag (a scale, and for the yaw rate a bias); the lag is the minimum of the residual over a grid of lags, refined by
the parabola through its neighbours (the course's) or by a search between them (the speed's, which the service
learns on line: its lag must move with the fixes' stamps, :func:`_minimum_between`). Its standard error is the
larger of the parabola's (from its curvature) and the linearised least-squares one,
``rms / sqrt(sum (d model / d lag)^2)`` with the derivative taken over a second (:data:`SLOPE_S`): without speed
changes (or turns) the residual's minimum is noise and the lag undetermined, which the second says even when noise
makes a parabola look sharp. The speed's takes the derivative's square as the product of its two half-second halves
(:func:`_signal_information`: the CAN speed's noise counts against the information, not for it) and its residuals as
correlated from one fix to the next (:func:`_correlated_std`): a short window's fit claims no more than it knows,
which :class:`ClockLearner` relies on when it weighs its early fits. Pure functions on arrays (:func:`speed_lag`,
:func:`course_lag`), used offline by ``sumhe calibrate`` and on line by :class:`ClockLearner`.
"""

from __future__ import annotations

import itertools
import math
from array import array
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize_scalar  # at import: the daemon searches the lag mid-drive, on its worker

LAGS_S = np.round(np.arange(-1.0, 1.0001, 0.02), 6)
"""The lags tried (s): a receiver's latency plus a clock's offset stays within a second."""
MIN_SPEED_MPS = 2.0
"""Course and Doppler speed are used above this speed only (below it the course is noise)."""
MIN_PAIRS = 30
SLOPE_S = 0.5
"""Half the interval (s) over which the model's derivative with respect to the lag is taken (smooths sensor noise)."""
CAN_MEAN_S = 0.05
"""Half-width (s) of the mean the speed lag's fit takes of the CAN speed at each sample (:class:`CanSpeed`)."""
LAG_TOLERANCE_S = 1e-4
"""The speed lag is searched to this (s) between the grid's neighbours of its minimum (:func:`speed_lag`)."""
CHORD_S = (1.0, 2.0)
"""Shortest and longest baseline (s) of the speed and course taken between fix positions (``sumhe calibrate``, and
the on-line sensor check of a receiver without a course or heading)."""
UNLEARNED_TIME_OFFSET_SD_S = 0.3
"""The standard deviation (s) of the GNSS time offset before :class:`ClockLearner` has fitted it: real recordings
show -0.4 to +0.2 s, the realistic profile draws -0.3 to +0.3 s (docs/simulator.md)."""


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
    lever_m: float = 0.0
    """The antenna's forward lever arm (m) fitted with the lag (:func:`course_lag` with ``lever_prior_m``)."""
    scale_std: float = math.nan
    """The standard error of ``scale`` at the lag (:func:`_coefficient_std`; NaN where the scale is not fitted)."""
    offset_std: float = math.nan
    """The standard error of ``offset`` at the lag (:func:`course_lag`: the bias's, its intercept's over the scale;
    NaN where not fitted)."""
    level: float = math.nan
    """The mean magnitude of the GNSS quantity fitted (:func:`speed_lag`: the mean speed over ground, m/s)."""
    reads_low: float = math.nan
    """How much the CAN quantity reads low at the lag on the mean, fitted beside the scale (:func:`speed_lag`:
    ``gnss = s * (|can| + reads_low)``, m/s; half a quantum where the CAN speed is truncated); NaN unfitted."""
    reads_low_std: float = math.nan
    """The standard error of ``reads_low`` (:func:`_coefficient_std`)."""


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
    sigma2 = max(b, 0.0) / max(n - params, 1)  # an exact fit's sum, by differences of products, may round below 0
    return lag, math.sqrt(sigma2 / curvature)


def _linear_std(rms: float, slope: NDArray[np.float64]) -> float:
    """The least-squares standard error of a lag whose model changes by ``slope`` per second of lag at each
    measurement, with residuals of ``rms``."""
    information = float(np.sum(np.square(slope)))
    return rms / math.sqrt(information) if information > 0 else math.inf


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
    speed = CanSpeed(tc, c)
    can = np.abs(speed.at(tf[None, :] - lags[:, None]))
    rss = _grid_rss(can, g)
    lag, std = _refine(lags, rss, len(g), 2)
    i = int(np.argmin(rss))
    if math.isfinite(std):
        lag = _minimum_between(lambda x: _speed_fit(tf, g, speed, x)[0], float(lags[i - 1]), float(lags[i + 1]))
    rss_lag, scale_lag = _speed_fit(tf, g, speed, lag)
    rms = math.sqrt(rss_lag / len(g))
    early, now, late = (scale_lag * np.abs(speed.at(tf - lag + d)) for d in (-SLOPE_S, 0.0, SLOPE_S))
    slope, information = _beside(now, (early - late) / (2.0 * SLOPE_S), _signal_information(early, now, late))
    std = max(std, _correlated_std(g - now, slope, information))
    scale_std = _coefficient_std([now], g - now, 0) * abs(scale_lag)
    low, low_std = _reads_low(g, now / scale_lag) if scale_lag > 0 else (math.nan, math.nan)
    return LagFit(
        lag,
        std,
        scale_lag,
        0.0,
        rms,
        len(g),
        scale_std=scale_std,
        level=float(np.mean(g)),
        reads_low=low,
        reads_low_std=low_std,
    )


def _reads_low(g: NDArray[np.float64], can: NDArray[np.float64]) -> tuple[float, float]:
    """How much ``can`` reads low on the mean and its standard error (m/s): ``g = s * (can + low)`` by least
    squares, the residuals' correlation counted (:func:`_coefficient_std`); the speeds' spread tells the offset
    from the scale (NaN, inf at one speed)."""
    ones = np.ones_like(can)
    (s, b), *_ = np.linalg.lstsq(np.column_stack([can, ones]), g, rcond=None)
    if not s > 0:
        return math.nan, math.nan
    std = _coefficient_std([can, ones], g - s * can - b, 1)
    return float(b / s), float(std / s)


def _signal_information(early: NDArray[np.float64], now: NDArray[np.float64], late: NDArray[np.float64]) -> float:
    """The sum over the measurements of the model's squared rate of change ((m/s)^2 per s^2 for speeds: how much
    each tells of the lag), from its values :data:`SLOPE_S` (``h``) before, at and after each: the products of the
    two half differences, ``d1 d2``. With noise of variance ``s2`` at each value ``E[d1 d2] = v'^2 - s2 / h^2``
    (less ``(v'' h / 2)^2``): noise lowers it, never raises it, where it raises the central difference's square
    by ``s2 / (2 h^2)``; the CAN speed's noise differenced over a second is no speed change. On the estimator
    contract's 20 s drive at a constant 10 m/s (CAN noise 0.02 m/s) the squares summed 0.034 over 100 fixes (a
    claimed 0.07 s for an error of 0.18 s), the products -0.083. The unbiased mix ``(2 d^2 + d1 d2) / 3`` scatters
    about 0 there: positive in 2 of 8 such drives (0.22 s claimed for an error of 0.62 s)."""
    halves = (now - early) * (late - now) / (SLOPE_S * SLOPE_S)
    return float(np.sum(halves))


def _beside(
    column: NDArray[np.float64], slope: NDArray[np.float64], information: float
) -> tuple[NDArray[np.float64], float]:
    """A lag's ``slope`` (the model's change per second of lag at each measurement) and ``information`` (the sum of
    its squares, :func:`_signal_information`) with a coefficient of ``column`` fitted beside the lag: less their
    projection on the column, which the coefficient takes up. Over an acceleration the speed's lag and its scale
    trade (``scale * can(t - lag)`` along a ramp is nearly a line either way); taken alone, the lag's slope claimed
    a first fit over 6 s of 1.5 m/s^2 as known as at a constant scale (2-3 times too sure: :class:`CanSpeed`'s
    drive, 48 +- 10 ms for a true 0, the scale 0.990 for 0.981)."""
    along = float(column @ slope) / max(float(column @ column), 1e-300)
    return slope - along * column, information - along * float(column @ slope)


def _correlated_std(residuals: NDArray[np.float64], slope: NDArray[np.float64], information: float) -> float:
    """The least-squares standard error (s) of a lag whose model changes by ``slope`` per second of lag at each
    measurement (in time order) with ``information`` the sum of its squares (:func:`_signal_information`), the
    ``residuals`` correlated from one measurement to the next by their lag-1 autocorrelation ``rho`` (first-order
    autoregressive): ``sqrt(s2 sum_ij slope_i slope_j rho^|i - j|) / information``, ``s2`` their mean square; inf
    without information. A receiver's speed over ground is smoothed over epochs, so its errors against the CAN
    speed persist (``rho`` 0.86 in the median fit of the realistic profile's drives at 10 Hz): as white, the
    errors of the fits over 25-300 s were 3.0-4.0 times their standard errors (root mean square), 1.0-1.4 times
    with ``rho``."""
    if not information > 0:
        return math.inf
    mean_square = float(np.mean(np.square(residuals)))
    rho = float(residuals[1:] @ residuals[:-1]) / max(float(residuals @ residuals), 1e-300)
    n = len(slope)
    spectrum = np.fft.rfft(slope, 2 * n)
    products = np.fft.irfft(spectrum * np.conj(spectrum), 2 * n)[:n]
    quadratic = float(products[0] + 2.0 * np.sum(products[1:] * rho ** np.arange(1, n)))
    return math.sqrt(mean_square * max(quadratic, 0.0)) / information


def _coefficient_std(columns: list[NDArray[np.float64]], residuals: NDArray[np.float64], j: int) -> float:
    """The standard error of the least-squares coefficient of ``columns[j]`` (the others fitted beside it) with
    the ``residuals`` correlated as :func:`_correlated_std` takes them: the column less its projection on the others
    is what tells the coefficient. The on-line sensor check (:mod:`sumhe.frontend.sensor_check`) judges a scale by
    it."""
    x = columns[j]
    others = [c for i, c in enumerate(columns) if i != j]
    if others:
        a = np.column_stack(others)
        x = x - a @ np.linalg.lstsq(a, x, rcond=None)[0]
    return _correlated_std(residuals, x, float(x @ x))


def _grid_rss(can: NDArray[np.float64], g: NDArray[np.float64]) -> NDArray[np.float64]:
    """The residual sum of squares of ``g = scale * can[i]`` for each row ``i`` (its own least-squares scale), from
    the products ``can.g`` and ``can.can``: ``g.g - scale (2 can.g - scale can.can)``, without the residuals' lags x
    fixes array (the clock learner's 21 refits over the bundled drive 23 -> 14 ms; the sums differ from the
    residuals' by 1e-10 of themselves there, the two smallest from each other by 7e-3 at least)."""
    cg, cc = np.einsum("ij,j->i", can, g), np.einsum("ij,ij->i", can, can)
    scale = cg / np.maximum(cc, 1e-12)
    return float(g @ g) - scale * (2.0 * cg - scale * cc)  # type: ignore[no-any-return]


def _speed_fit(tf: NDArray[np.float64], g: NDArray[np.float64], can_speed: CanSpeed, lag: float) -> tuple[float, float]:
    """The residual sum of squares and the scale of ``g = scale * |can(tf - lag)|`` (:func:`speed_lag`)."""
    can = np.abs(can_speed.at(tf - lag))
    scale = float(can @ g) / max(float(can @ can), 1e-12)
    return float(np.sum(np.square(g - scale * can))), scale


class CanSpeed:
    """The CAN speed as the speed lag's fit reads it (samples ``c`` at the times ``tc``, time-ordered): at each sample
    its mean over :data:`CAN_MEAN_S` either side (of the samples joined by straight lines), and these means joined
    by straight lines in turn.

    Read as the one interpolated sample, a speed broadcast at 100 Hz brought its noise into the lag fit at every
    sample's spacing: as the lag moves by 10 ms each fix reads other samples, and the residual over the lags
    jagged by 10 % of itself, so the fit took the deepest of the noise's minima. On a kind simulated highway drive
    (seed 21; 0.02 m/s CAN noise, 0.05 m/s on the speed over ground) the first fit, over 6 s of 1.5 m/s^2 from a
    standstill, said 48 ms for a true 0. A speed polled at 1-2 Hz (OBD-II) is hardly changed: its samples lie
    farther apart than the mean's width. The means are taken once, at the samples, and interpolated: the fit reads
    the speed at 101 lags for every fix (a 300 s window of a 100 Hz speed and 10 Hz fixes: 10 ms a fit, 27 ms with
    the means taken at each reading, 9 ms read sample by sample)."""

    def __init__(self, tc: NDArray[np.float64], c: NDArray[np.float64]) -> None:
        self.t = tc
        cumulative = _cumulative(tc, c)
        upper, lower = (_integral(tc + d, tc, c, cumulative) for d in (CAN_MEAN_S, -CAN_MEAN_S))
        width = np.minimum(tc + CAN_MEAN_S, tc[-1]) - np.maximum(tc - CAN_MEAN_S, tc[0])  # less at the two ends
        self.mean = np.divide(upper - lower, width, out=c.astype(float), where=width > 0)

    def at(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """The speed at the times ``t`` (s)."""
        return np.interp(t, self.t, self.mean)


def _integral(
    t: NDArray[np.float64], tc: NDArray[np.float64], c: NDArray[np.float64], cumulative: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The integral from ``tc[0]`` to ``t`` (clipped to the samples' span) of the samples ``c`` joined by straight
    lines, from their running integral at the samples (:func:`_cumulative`): each whole interval's trapezoid, then
    the part of the interval ``t`` falls in (exact for the straight line)."""
    t = np.clip(t, tc[0], tc[-1])
    i = np.clip(np.searchsorted(tc, t, side="right") - 1, 0, len(tc) - 2)
    span = tc[i + 1] - tc[i]
    rate = np.divide(c[i + 1] - c[i], span, out=np.zeros_like(span), where=span > 0)
    dt = t - tc[i]
    return cumulative[i] + dt * (c[i] + 0.5 * rate * dt)  # type: ignore[no-any-return]


def _minimum_between(f: Callable[[float], float], lo: float, hi: float) -> float:
    """The minimum of ``f`` on ``[lo, hi]`` (s) to :data:`LAG_TOLERANCE_S`: between the grid's points the residual
    is no parabola (the CAN data are interpolated between samples as far apart as the grid's step), whose vertex
    was pulled towards the grid's points by up to 2 ms, so the lag learned moved by 4.4 ms when the fixes' stamps
    moved by 6.2 ms; searched, it moves with them."""
    return float(minimize_scalar(f, bounds=(lo, hi), method="bounded", options={"xatol": LAG_TOLERANCE_S}).x)


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
    lever_prior_m: tuple[float, float] | None = None,
    speed_weighted: bool = False,
    fixed_scale: float | None = None,
    sigma_rad: ArrayLike | None = None,
) -> LagFit | None:
    """The lag of the receiver's course behind the CAN yaw rate: the course's rate between consecutive fixes
    (clockwise) against ``-(yaw - bias) * scale`` averaged over the same interval ``lag`` earlier. ``scale`` is the
    yaw-rate scale (true = scale x (CAN - bias)), ``offset`` the bias (rad/s). Fixes below ``MIN_SPEED_MPS`` or
    more than ``max_gap_s`` apart are left out; None with fewer than ``MIN_PAIRS`` pairs.

    A course over ground is the antenna's: an antenna ``l`` ahead of the point the yaw rate turns about moves
    sideways at ``l omega`` in turns, so its course is the heading minus ``atan(l omega / v)`` and leads the
    heading by about ``l / v`` (a lag that changes with speed). With ``lever_prior_m = (l0, sigma)`` (m) the fit
    takes ``l`` as a third coefficient (the change of ``omega / v`` over the interval, from the yaw rate averaged
    over :data:`LEVER_SMOOTH_S` at its ends), with a Gaussian prior ``N(l0, sigma^2)`` that holds it where speed
    hardly varies; ``lever_m`` is the result. Leave it None for a heading (HDT: the body's own azimuth).
    ``speed_weighted``: weigh each pair by its speed squared, as the course's error is the velocity's error over the
    speed (not for a heading, whose error does not shrink with speed). ``fixed_scale``: the scale is not fitted
    but this (a drive without turns tells the bias at scale 1, not the scale). ``sigma_rad``: each azimuth's 1-sigma
    (rad; a heading's as the receiver rates it, :func:`~sumhe.frontend.measurements.heading_sigma`): each pair is
    weighed by the inverse of its rate's variance, ``sigma1^2 + sigma2^2``, beside its speed."""
    tf, crs, spd = np.asarray(t_fix, float), np.asarray(course_rad, float), np.asarray(speed_mps, float)
    tw, w = np.asarray(t_yaw, float), np.asarray(yaw_rps, float)
    lags = np.asarray(lags, float)
    if len(tw) < 2 or len(tf) < 2:
        return None
    ok = np.isfinite(crs) & np.isfinite(spd) & (np.abs(spd) > MIN_SPEED_MPS)
    dt = np.diff(tf)
    pair = ok[1:] & ok[:-1] & (dt > 0) & (dt <= max_gap_s)
    margin = LEVER_SMOOTH_S if lever_prior_m is not None else 0.0
    t1, t2 = tf[:-1][pair], tf[1:][pair]
    v1, v2 = np.abs(spd[:-1][pair]), np.abs(spd[1:][pair])
    inside = (t1 - lags.max() - margin > tw[0]) & (t2 - lags.min() + margin < tw[-1])
    t1, t2, v1, v2 = t1[inside], t2[inside], v1[inside], v2[inside]
    dcrs = np.angle(np.exp(1j * np.diff(crs)))[pair][inside]
    if len(t1) < MIN_PAIRS:
        return None
    rate = -dcrs / (t2 - t1)
    cum = _cumulative(tw, w)
    root_w = 0.5 * (v1 + v2) / np.sqrt(np.mean(np.square(0.5 * (v1 + v2)))) if speed_weighted else np.ones(len(rate))
    if sigma_rad is not None:
        sig = np.asarray(sigma_rad, float)
        inverse = 1.0 / np.sqrt(np.square(sig[:-1][pair][inside]) + np.square(sig[1:][pair][inside]))
        root_w = root_w * inverse / np.sqrt(np.mean(np.square(inverse)))

    def mean(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
        return (np.interp(b, tw, cum) - np.interp(a, tw, cum)) / (b - a)  # type: ignore[no-any-return]

    y = root_w * rate
    systems: list[tuple[list[NDArray[np.float64]], NDArray[np.float64]]] = []
    for lag in lags:
        m = root_w * mean(t1 - lag, t2 - lag)
        systems.append(([m, root_w], y) if fixed_scale is None else ([root_w], y - fixed_scale * m))
    rss, coef = _fit_lags(systems)
    if lever_prior_m is not None:
        l0, sigma_l = lever_prior_m
        weight = math.sqrt(float(rss.min()) / max(len(rate) - coef.shape[1] - 1, 1)) / sigma_l
        h = LEVER_SMOOTH_S / 2.0
        for lag, (cols, _) in zip(lags, systems, strict=True):
            w1, w2 = mean(t1 - lag - h, t1 - lag + h), mean(t2 - lag - h, t2 - lag + h)
            cols.append(root_w * (w2 / v2 - w1 / v1) / (t2 - t1))
        rss, coef = _fit_lags(systems, (coef.shape[1], l0, weight))
    lag, std = _refine(lags, rss, len(rate), coef.shape[1] + 1)
    i = int(np.argmin(rss))
    cols, y_i = systems[i]
    residuals = y_i - np.column_stack(cols) @ coef[i]
    scale_std = _coefficient_std(cols, residuals, 0) if fixed_scale is None else math.nan
    row = list(coef[i]) if fixed_scale is None else [fixed_scale, *coef[i]]
    scale, intercept = row[0], row[1]
    bias = -intercept / scale if scale else math.nan
    intercept_std = _coefficient_std(cols, residuals, 0 if fixed_scale is not None else 1)
    bias_std = intercept_std / abs(scale) if scale else math.nan
    lever = float(row[2] / scale) if lever_prior_m is not None and scale else 0.0
    rms = math.sqrt(float(rss[i]) / len(rate))
    slope = root_w * (mean(t1 - lag - SLOPE_S, t2 - lag - SLOPE_S) - mean(t1 - lag + SLOPE_S, t2 - lag + SLOPE_S))
    std = max(std, _linear_std(rms, scale * slope / (2.0 * SLOPE_S)))
    return LagFit(lag, std, float(scale), float(bias), rms, len(rate), lever, scale_std, offset_std=float(bias_std))


LEVER_SMOOTH_S = 0.5
"""The yaw rate at the ends of an interval, for the lever arm's term, is its mean over this span (s): the CAN yaw
rate's noise and quantum differenced over a GNSS period would swamp the change it measures."""


def _fit_lags(
    systems: list[tuple[list[NDArray[np.float64]], NDArray[np.float64]]],
    prior: tuple[int, float, float] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Least squares of each lag's ``(columns, y)``: the residual sums (one per lag, the prior's term included) and
    the coefficients (lags x columns). ``prior = (j, mean, weight)`` adds the row ``weight * (c_j - mean)``."""
    k = len(systems[0][0])
    rss = np.empty(len(systems))
    coef = np.empty((len(systems), k))
    for i, (cols, y) in enumerate(systems):
        a, b = np.column_stack(cols), y
        if prior is not None:
            j, mean, weight = prior
            row = np.zeros(k)
            row[j] = weight
            a, b = np.vstack([a, row]), np.append(y, weight * mean)
        coef[i], *_ = np.linalg.lstsq(a, b, rcond=None)
        rss[i] = float(np.sum(np.square(b - a @ coef[i])))
    return rss, coef


class TimeSeries:
    """(t, value) pairs appended in time order into two flat ``array('d')`` columns, forgotten from the front by
    moving a start index (the arrays compacted once half is forgotten). The learner's CAN speeds (15 000 in its
    300 s window at 50 Hz) come to each refit as numpy arrays copied in one go (2.5 us; a deque of tuples flattened
    by ``numpy.fromiter``: 0.6 ms), and are appended without a tuple each: the front-end over the bundled drive
    (21 refits) 125 -> 100 ms."""

    def __init__(self) -> None:
        self.t = array("d")
        self.v = array("d")
        self.start = 0

    def __len__(self) -> int:
        return len(self.t) - self.start

    def append(self, t: float, value: float) -> None:
        self.t.append(t)
        self.v.append(value)

    def trim(self, t_min: float, keep: int) -> None:
        """Forget the oldest pair while more than ``keep`` remain and the one after it is before ``t_min``."""
        start, t, n = self.start, self.t, len(self.t)
        while n - start > keep and t[start + 1] < t_min:
            start += 1
        if start > n // 2:
            del self.t[:start], self.v[:start]
            start = 0
        self.start = start

    def scale(self, factor: float) -> None:
        """Multiply every value kept by ``factor``."""
        self.v = array("d", [factor * v for v in self.v])

    def columns(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The times and values kept (copies)."""
        return np.frombuffer(self.t[self.start :]), np.frombuffer(self.v[self.start :])


class ClockLearner:
    """The GNSS time offset learned on line from the receiver's speed over ground and the CAN speed
    (:func:`speed_lag` over the last ``window_s`` s, refitted every ``refit_s`` s). ``offset_s`` is the offset
    to add to a fix's stamped time: the newest fit whose standard error is below ``max_std_s`` (its ``-lag``;
    ``fits`` counts them); before the first such fit, ``initial_s`` and the newest fit weighed by their precisions
    (``initial_s`` a prior of :data:`UNLEARNED_TIME_OFFSET_SD_S`: a fit of 0.23 s moves it 62 % of the way, one of
    0.04 s 98 %); :attr:`sigma_s` its standard deviation. This trusts the fits' standard errors, which count the
    residuals' correlation and only the CAN speed's true changes (:func:`speed_lag`): on a drive at a constant
    speed they are infinite and the offset stays. On the shared real drive the fits said -0.32 to -0.35 s from
    162 s (standard errors 0.23 to 0.04 s), and the first below 30 ms came at 364 s: without the weighing its 150
    and 270 s outages ran with the offset of the config (0), 7 m along the track at 19 m/s; with it the offset is
    -0.20 s from 162 s and -0.30 to -0.34 s from 172 s."""

    def __init__(
        self, initial_s: float = 0.0, window_s: float = 300.0, refit_s: float = 10.0, max_std_s: float = 0.03
    ) -> None:
        self.offset_s = self.initial_s = initial_s
        self.std_s = math.inf
        self.fits = 0
        self.newest: LagFit | None = None
        """The newest fit, sure or not (the on-line sensor check reads its speed scale)."""
        self.window_s, self.refit_s, self.max_std_s = window_s, refit_s, max_std_s
        self._fixes: deque[tuple[float, float]] = deque()
        self._can = TimeSeries()
        self._next_fit = -math.inf

    @property
    def sigma_s(self) -> float:
        """The standard deviation (s) of :attr:`offset_s`: the newest sure fit's standard error, the weighed one's
        before it, :data:`UNLEARNED_TIME_OFFSET_SD_S` before any fit."""
        return self.std_s if math.isfinite(self.std_s) else UNLEARNED_TIME_OFFSET_SD_S

    def add_can_speed(self, t: float, speed_mps: float) -> None:
        """A CAN speed sample (s, m/s) on the CAN clock."""
        self._can.append(t, speed_mps)

    def scale_can_speeds(self, factor: float) -> None:
        """Multiply the CAN speeds kept by ``factor`` (the speed's scale corrected on line)."""
        self._can.scale(factor)

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
        self._can.trim(t_min - 2.0, keep=2)

    def _fit(self) -> None:
        if len(self._fixes) < MIN_PAIRS or len(self._can) < 2:
            return
        f = row_array(self._fixes)
        fit = speed_lag(f[:, 0], f[:, 1], *self._can.columns())
        if fit is None:
            return
        self.newest = fit
        if fit.std_s <= self.max_std_s:
            self.offset_s, self.std_s = -fit.lag_s, fit.std_s
            self.fits += 1
        elif self.fits == 0 and math.isfinite(fit.std_s):
            self.offset_s, self.std_s = _weighed(self.initial_s, UNLEARNED_TIME_OFFSET_SD_S, -fit.lag_s, fit.std_s)


def _weighed(prior: float, prior_sd: float, value: float, sd: float) -> tuple[float, float]:
    """The mean and standard deviation of ``prior`` and ``value`` weighed by their precisions (two Gaussians)."""
    w = prior_sd**2 / (prior_sd**2 + sd**2)
    return prior + w * (value - prior), math.sqrt(w) * sd


def row_array(rows: deque[tuple[float, ...]]) -> NDArray[np.float64]:
    """``numpy.array(rows)`` (n x the rows' length, n > 0), built from a flat iterator (``numpy.array`` inspects
    each tuple, 2.5 times slower)."""
    width = len(rows[0])
    return np.fromiter(itertools.chain.from_iterable(rows), float, width * len(rows)).reshape(-1, width)
