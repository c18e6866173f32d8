"""The measurement maths of the front-end: each GNSS and CAN measurement's value and error, decided once.

Pure functions, no state; each takes floats or numpy arrays alike (the batch grid calls them on whole windows,
the streaming front-end on one fix). Units in the names; angles in rad, clockwise from north. Every estimator
reads its measurements from here, through :class:`~sumhe.frontend.stream.FrontEnd` (MHE, Kalman peers) or
:func:`~sumhe.estimator.grid.build_grid` (batch): the same fix gets the same sigma everywhere.

* Position, per axis (east, north): the receiver's GST sigmas; else by GGA quality, RTK fixed
  ``sigma_rtk_m``, float ``sigma_float_m``; else HDOP x ``uere_m``; else ``sigma_m``; at least ``resolution_m``
  (:func:`fix_sigmas`).
* Azimuth: an HDT/THS heading (with ``use_heading``) at ``heading_sigma_rad``, or at the receiver's rating of it
  where it rates it worse (:func:`heading_sigma`), or, in the streaming front-end, at what its turn against the CAN
  yaw rate says where that is worse still (:mod:`~sumhe.frontend.heading_check`; the batch grid leaves it out);
  else the course over ground above ``course_min_speed_mps`` (of the fix's speed, else the CAN speed) at
  ``hypot(course_sigma_rad, speed_sigma_mps / speed)`` (:func:`azimuth_measurement`).
* Azimuth from the fixes' motion, for receivers that send no course or heading: the chord between two fixes,
  turned by half the CAN yaw rate's turn in between, at ``sigma / distance`` (:func:`chord_azimuth`).
* Speed over ground (Doppler, with ``use_speed``): above ``course_min_speed_mps``, signed like the CAN speed
  (reversing), at ``max(speed_sigma_mps, NMEA's resolution)`` (:func:`gps_speed`).
* CAN: an average of ``count`` samples bounds its error by half a quantum plus ``k`` sigmas of the mean
  (:func:`can_allowance`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sumhe.frontend.can import Samples
from sumhe.settings import CanModel, GnssModel

GGA_RTK_FIXED = 4
GGA_RTK_FLOAT = 5
GPS_SPEED_RESOLUTION_MPS = 0.001 * 1852.0 / 3600.0
"""NMEA's speed over ground resolution (0.001 knot)."""
MAX_FIX_SIGMA_M = 1000.0
"""The largest 1-sigma error (m) a usable fix may have (a larger one says the position is unknown)."""
MIN_SPEED_MPS = 1e-3
"""Speeds below this are taken as this in the course's sigma (no division by zero)."""


def fix_sigmas(quality: Any, hdop: Any, gst_east_m: Any, gst_north_m: Any, gnss: GnssModel) -> tuple[Any, Any]:
    """1-sigma position error (east, north), m, of fixes: GST, else by quality (RTK fixed, float), else HDOP x
    ``uere_m``, else ``sigma_m``; at least ``resolution_m``. Missing values are NaN (arrays) or None (floats)."""
    if all(v is None or isinstance(v, int | float) for v in (quality, hdop, gst_east_m, gst_north_m)):
        return _one_fix_sigmas(quality, hdop, gst_east_m, gst_north_m, gnss)
    quality = np.asarray(quality)
    hdop, gst_e, gst_n = (np.asarray(np.nan if v is None else v, dtype=float) for v in (hdop, gst_east_m, gst_north_m))
    by_hdop = np.where(np.isfinite(hdop), hdop * gnss.uere_m, gnss.sigma_m)
    by_quality = np.where(
        quality == GGA_RTK_FIXED, gnss.sigma_rtk_m, np.where(quality == GGA_RTK_FLOAT, gnss.sigma_float_m, by_hdop)
    )
    has_gst = np.isfinite(gst_e) & np.isfinite(gst_n)
    east = np.where(has_gst, gst_e, by_quality)
    north = np.where(has_gst, gst_n, by_quality)
    # a non-positive sigma is the receiver's error, not a precise fix: kept, so that the fix is refused as unusable
    floor = gnss.resolution_m
    east = np.where(east > 0, np.maximum(east, floor), east)
    north = np.where(north > 0, np.maximum(north, floor), north)
    return (float(east), float(north)) if east.ndim == 0 else (east, north)


def _one_fix_sigmas(
    quality: int | None, hdop: float | None, gst_east_m: float | None, gst_north_m: float | None, gnss: GnssModel
) -> tuple[float, float]:
    """:func:`fix_sigmas` of one fix in plain floats (the same values; a dozen numpy calls on 0-d arrays cost tens
    of microseconds a fix)."""
    if quality == GGA_RTK_FIXED:
        sigma = gnss.sigma_rtk_m
    elif quality == GGA_RTK_FLOAT:
        sigma = gnss.sigma_float_m
    else:
        sigma = hdop * gnss.uere_m if _finite(hdop) else gnss.sigma_m  # type: ignore[operator]
    east, north = (gst_east_m, gst_north_m) if _finite(gst_east_m) and _finite(gst_north_m) else (sigma, sigma)
    floor = gnss.resolution_m
    return float(max(east, floor) if east > 0 else east), float(max(north, floor) if north > 0 else north)  # type: ignore[operator]


def sigmas_usable(sigma_east_m: float, sigma_north_m: float) -> bool:
    """Whether a fix's sigmas (:func:`fix_sigmas`) are positive and at most :data:`MAX_FIX_SIGMA_M`."""
    return all(0 < s <= MAX_FIX_SIGMA_M for s in (sigma_east_m, sigma_north_m))


def course_sigma(speed_mps: Any, gnss: GnssModel) -> Any:
    """1-sigma error (rad) of the course over ground at ``speed_mps``: ``hypot(course_sigma_rad, speed_sigma_mps /
    speed)``."""
    return np.hypot(gnss.course_sigma_rad, gnss.speed_sigma_mps / np.maximum(np.abs(speed_mps), MIN_SPEED_MPS))


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


def _scalar(value: Any) -> bool:
    """Whether ``value`` is a number or None (not an array: the functions' plain-float paths)."""
    return value is None or isinstance(value, float | int)


def azimuth_measurement(
    course_rad: float | None,
    heading_rad: float | None,
    speed_mps: float | None,
    gnss: GnssModel,
    heading_rated_rad: float | None = None,
) -> tuple[float, float, bool] | None:
    """The azimuth a fix measures: (value rad, 1-sigma rad, whether it is a heading), or None. ``speed_mps``: the
    fix's speed over ground, else the CAN speed (for the course's minimum speed and sigma). A heading's sigma is
    ``heading_sigma_rad``, or the receiver's own rating of it (``heading_rated_rad``: a GNSS + IMU module's heading
    accuracy) where that is larger: :func:`heading_sigma`."""
    if gnss.use_heading and _finite(heading_rad):
        return float(heading_rad), heading_sigma(heading_rated_rad, gnss), True  # type: ignore[arg-type]
    if _finite(course_rad) and _finite(speed_mps) and speed_mps >= gnss.course_min_speed_mps:  # type: ignore[operator]
        return float(course_rad), float(course_sigma(speed_mps, gnss)), False  # type: ignore[arg-type]
    return None


def heading_sigma(rated_rad: float | None, gnss: GnssModel) -> float:
    """A heading's 1-sigma (rad): ``gnss.heading_sigma_rad``, or the receiver's rating ``rated_rad`` where it is
    larger. The configured sigma is the floor because below about 0.5 deg a receiver's rating does not order its
    errors (the shared real drive's GNSS + IMU module: on straight road, headings rated 0.2 deg were off the track by
    0.3 deg rms, rated 0.5-0.6 deg by 0.3 deg); above it the rating is what tells a converged heading from one the
    module has not settled yet (rated 2-40 deg in that drive's first minutes, up to 8 deg off, all to one side)."""
    if rated_rad is None or not rated_rad > gnss.heading_sigma_rad:
        return gnss.heading_sigma_rad
    return float(rated_rad)


def chord_azimuth(
    east_m: float, north_m: float, sigma_m: float, dt_s: float, yaw_rate_rps: float
) -> tuple[float, float] | None:
    """The azimuth (rad, clockwise from north, in [0, 2 pi)) the motion between two fixes measures at the later one,
    and its 1-sigma (rad): a receiver that sends no course or heading still gives the chord between its positions.
    ``east_m``, ``north_m``: the later fix less the earlier (m); ``sigma_m``: the chord's 1-sigma error across it
    (m, both fixes' errors); ``dt_s``: the time between them (s); ``yaw_rate_rps``: the mean yaw rate in between
    (rad/s, anticlockwise). At a constant yaw rate the chord points along the azimuth half-way, half the turn
    behind the later fix's. None for fixes at one place."""
    distance = math.hypot(east_m, north_m)
    if not distance > 0.0:
        return None
    azimuth = math.atan2(east_m, north_m) - 0.5 * yaw_rate_rps * dt_s
    return azimuth % (2.0 * math.pi), sigma_m / distance


def gps_speed(speed_mps: Any, can_speed_mps: Any, gnss: GnssModel) -> Any:
    """The speed (m/s) a fix's speed over ground measures, with the sign of the CAN speed (reversing): None (NaN in
    arrays) without a speed or below ``course_min_speed_mps`` (at walking pace Doppler speeds are biased upwards).
    Numbers (or None) take a plain-float path, the same comparisons and negation without numpy's set-up: 8.6 ->
    0.3 us a fix."""
    if _scalar(speed_mps) and _scalar(can_speed_mps):
        if speed_mps is None or not speed_mps >= gnss.course_min_speed_mps:  # NaN fails the test too
            return None
        value = -float(speed_mps) if can_speed_mps is not None and can_speed_mps < 0.0 else float(speed_mps)
        return value if math.isfinite(value) else None
    speed = np.asarray(np.nan if speed_mps is None else speed_mps, dtype=float)
    can = np.asarray(np.nan if can_speed_mps is None else can_speed_mps, dtype=float)
    with np.errstate(invalid="ignore"):
        out = np.where(speed >= gnss.course_min_speed_mps, np.where(can < 0.0, -speed, speed), np.nan)
    if out.ndim:
        return out
    return float(out) if math.isfinite(out) else None


def gps_speed_sigma(gnss: GnssModel) -> float:
    """1-sigma error (m/s) of the speed over ground: the receiver's, at least NMEA's resolution."""
    return max(gnss.speed_sigma_mps, GPS_SPEED_RESOLUTION_MPS)


def can_allowance(resolution: float, sigma: float, k_sigmas: float, count: Any = 1) -> Any:
    """Error allowance of a CAN value averaged over ``count`` samples: half a quantum plus ``k_sigmas`` sigmas of
    the mean (the sensor's sigma over the root of the samples averaged). A positive int ``count`` (the streaming
    estimators' four a GNSS epoch) takes ``math.sqrt``, the same correctly rounded root without numpy's ufunc call:
    1.4 -> 0.2 us."""
    if type(count) is int and count > 0:
        return 0.5 * resolution + k_sigmas * sigma / math.sqrt(count)
    return 0.5 * resolution + k_sigmas * sigma / np.sqrt(count)


def unmodelled_can_errors(can_speed_mps: Any, can: CanModel, scale_state: bool, bias_state: bool) -> tuple[Any, float]:
    """What the CAN speed's and yaw rate's allowances must add when the model has no state for the speed scale
    (``speed_scale_max`` x |speed|) or the yaw-rate bias (``yaw_rate_bias_max_rps``)."""
    speed = 0.0 if scale_state else can.speed_scale_max * np.abs(np.nan_to_num(can_speed_mps))
    return speed, 0.0 if bias_state else can.yaw_rate_bias_max_rps


ACCELERATION_SPAN_S = 0.5
"""The CAN speed's acceleration at a fix is its change over the last this many seconds."""


def timed_speed_sigma(sigma_mps: float, acceleration_mps2: float, time_sd_s: float) -> float:
    """The sigma (m/s) of a speed over ground of sigma ``sigma_mps`` whose time is uncertain by ``time_sd_s`` (s)
    while the car accelerates at ``acceleration_mps2``: a speed measured at the wrong time differs by the
    acceleration times the error."""
    return math.hypot(sigma_mps, acceleration_mps2 * time_sd_s)


def can_acceleration(speed: Samples, t: float, max_age_s: float) -> float:
    """The CAN speed's change over the :data:`ACCELERATION_SPAN_S` before ``t`` (m/s^2; 0 without samples)."""
    now, before = speed.at(t, max_age_s), speed.at(t - ACCELERATION_SPAN_S, max_age_s)
    return 0.0 if now is None or before is None else (now - before) / ACCELERATION_SPAN_S
