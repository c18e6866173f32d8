"""Messages that flow through sumhe: GNSS fixes, CAN samples and estimates.

All quantities are SI inside the package (m, s, m/s, rad, rad/s). Angles: azimuth/course/heading
clockwise from north; yaw rate positive anticlockwise. Latitude and longitude are degrees (WGS84),
named with ``_deg``. Every message carries ``t``: seconds on the service clock (Unix time for live
data and logs with receive-time prefixes).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Literal

from sumhe.records import quick_init

CanQuantity = Literal[
    "speed",
    "yaw_rate",
    "wheel_speed_fl",
    "wheel_speed_fr",
    "wheel_speed_rl",
    "wheel_speed_rr",
    "steering_angle",
    "lat_accel",
    "lon_accel",
]
"""Quantities the DBC signal mapping may provide, with their SI units:
speed and wheel speeds m/s, yaw_rate rad/s (anticlockwise positive), steering_angle rad (left positive),
accelerations m/s^2."""

CAN_QUANTITIES: tuple[str, ...] = CanQuantity.__args__  # type: ignore[attr-defined]

GnssQuantity = Literal[
    "lat", "lon", "alt", "accuracy", "speed", "course", "heading", "heading_accuracy", "time", "sats"
]
"""Quantities a GNSS receiver's CAN frames may provide (``[gps] source = "can"``), as :class:`GnssFix` holds them:
lat and lon degrees (WGS84), alt m, accuracy m (horizontal 1-sigma), speed m/s (over ground), course (over
ground) and heading rad clockwise from north, heading_accuracy rad (the receiver's 1-sigma of its heading), time s
(UTC, Unix), sats a count."""

GNSS_QUANTITIES: tuple[str, ...] = GnssQuantity.__args__  # type: ignore[attr-defined]

GpsStatus = Literal["ok", "outage", "rejected"]


@quick_init
@dataclass(frozen=True, slots=True)
class GnssFix:
    """One GNSS epoch: the sentences of one UTC time of fix assembled into one fix.

    ``t`` is the receive time (s, service clock) when the line carried one, else the fix's UTC time as
    Unix seconds. ``valid`` is False for fixes with no position (GGA quality 0, RMC status V); such a fix
    is never used as a position. ``antenna`` is 1, or 2 for the rear antenna of a two-antenna setup (su7).
    ``heading_sigma_rad``: the receiver's own 1-sigma of its heading, where it rates it (a GNSS + IMU module's
    heading accuracy, mapped as ``heading_accuracy``); None elsewhere.
    """

    t: float
    time_utc: dt.datetime | None
    lat_deg: float | None
    lon_deg: float | None
    alt_m: float | None
    quality: int
    valid: bool
    sats: int | None = None
    hdop: float | None = None
    speed_mps: float | None = None
    course_rad: float | None = None
    heading_rad: float | None = None
    sigma_lat_m: float | None = None
    sigma_lon_m: float | None = None
    sigma_alt_m: float | None = None
    talker: str = ""
    antenna: int = 1
    heading_sigma_rad: float | None = None


@quick_init
@dataclass(frozen=True, slots=True)
class CanSample:
    """One decoded CAN quantity, in SI units, at the frame's timestamp ``t`` (s)."""

    t: float
    quantity: str
    value: float


Sample = GnssFix | CanSample
"""What every source (serial, CAN bus, replay) yields, in time order per source."""


@quick_init
@dataclass(frozen=True, slots=True)
class ErrorEstimate:
    """An estimate's error figures as gpsd defines them (95 % confidence): ``eph_m`` the radius (m) of the circle
    around the estimate that holds the horizontal error, ``epx_m``/``epy_m`` the east (longitude) and north
    (latitude) half-widths (m), ``eps_mps`` the speed's (m/s), ``epd_rad`` the track's (rad); and the 1-sigma figures
    NMEA GST sends: the error ellipse (semi-major and semi-minor axes, m; orientation of the semi-major axis, rad
    clockwise from north) and the east and north sigmas (m). :mod:`sumhe.estimator.uncertainty` computes them."""

    eph_m: float
    epx_m: float
    epy_m: float
    eps_mps: float
    epd_rad: float
    sigma_major_m: float
    sigma_minor_m: float
    orient_rad: float
    sigma_east_m: float
    sigma_north_m: float


@quick_init
@dataclass(frozen=True, slots=True)
class Estimate:
    """One position estimate as the sinks send it.

    ``east_m``/``north_m`` are metres from the datum; ``track_rad`` clockwise from north;
    ``yaw_rate_rps`` anticlockwise positive. ``gps`` says whether GPS was used at this estimate.
    ``bound_east_m``/``bound_north_m`` are half-widths of the feasible set of the newest position
    where the estimator knows them. ``error`` the estimator's own error estimate (None before it has one);
    ``sats`` and ``hdop`` the satellites used and the HDOP of the newest fix used (in outages: no satellites, and
    the fix's HDOP grown with the error estimate since).
    """

    t: float
    east_m: float
    north_m: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    track_rad: float
    speed_mps: float
    yaw_rate_rps: float
    gps: GpsStatus
    mode: str
    window: int = 0
    solve_ms: float = 0.0
    bound_east_m: float | None = None
    bound_north_m: float | None = None
    error: ErrorEstimate | None = None
    sats: int | None = None
    hdop: float | None = None
