"""The simulated GNSS receiver(s): fix epochs with modelled errors, sent as receive-time-prefixed NMEA.

Per epoch (aligned to whole multiples of the period in UTC, as receivers do) the receiver sends GGA, RMC and
GST (and HDT from a two-antenna receiver), one serial line after another at 115200 baud, starting
``gps_latency_s`` + U(0, ``gps_latency_jitter_s``) after the fix time. Course over ground is held at its last
value below 0.5 m/s (empty before the first motion), as receivers do at standstill. Inside an outage the
receiver is silent or sends the same sentences saying "no fix" (GGA quality 0, RMC status V and mode N, GST and
HDT empty), as a receiver in a tunnel does.

The real-car errors of :class:`~sumhe.sim.settings.SimSettings` (all off in the ``kind`` profile) come from a
second random stream, so the kind drives are bit for bit what they were: the fix tagged t (UTC) is computed at
t + the GNSS clock offset on the host clock and received ``gps_latency_s`` after that; the antenna sits on the
body at the lever arm; outlier jumps with exponential sizes; dropped epochs; velocity with a Gauss-Markov error;
no HDOP, no GST, a GN talker.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.geo import LocalFrame
from sumhe.io.nmea_format import (
    KNOTS_PER_MPS,
    MPS_PER_KNOT,
    format_gga,
    format_gst,
    format_hdt,
    format_rmc,
    quantize_angle_rad,
    quantize_latlon,
)
from sumhe.messages import GnssFix
from sumhe.sim.settings import SimSettings
from sumhe.sim.vehicle import Body, Trajectory

FloatArray = NDArray[np.float64]

GEOID_SEP_M = 45.0
"""Geoid separation reported in GGA (altitude there is MSL = ellipsoidal height - separation)."""
SERIAL_BAUD = 115200
COURSE_MIN_SPEED_MPS = 0.5
VERTICAL_ERROR_FACTOR = 1.5
WALK_SHARE = 0.95
"""Share (in sigma) of the random walk in the ``walk`` model; the white part has sqrt(1 - 0.95^2) ~ 0.31."""


@dataclass(frozen=True, eq=False)
class GpsEpochs:
    """What one receiver sent, per epoch, with the values exactly as the sentences carry them.

    ``t_fix`` is the time of fix (Unix s), ``t_rx`` the receive time of the epoch's GGA line (NaN when the
    receiver was silent). NaN marks an empty field.
    """

    antenna: int
    t_fix: FloatArray
    t_rx: FloatArray
    sent: NDArray[np.bool_]
    valid: NDArray[np.bool_]
    quality: NDArray[np.int64]
    lat: FloatArray
    lon: FloatArray
    alt_msl: FloatArray
    speed: FloatArray
    course: FloatArray
    heading: FloatArray
    sats: NDArray[np.int64]
    hdop: FloatArray
    sigma_h: float
    sigma_alt: float
    heading_sent: bool
    """True for the receiver of a two-antenna system: HDT in every epoch (empty without a fix)."""
    gst_sent: bool
    talker: str
    error_east: FloatArray
    """The position error applied (m), multipath included; NaN when no fix was sent."""
    error_north: FloatArray

    def fixes(self) -> list[GnssFix]:
        """One GnssFix per epoch that was sent, as a decoder would assemble it."""
        return [self._fix(k) for k in np.flatnonzero(self.sent)]

    def _fix(self, k: int) -> GnssFix:
        def opt(a: FloatArray) -> float | None:
            return None if math.isnan(a[k]) else float(a[k])

        valid = bool(self.valid[k])
        return GnssFix(
            t=float(self.t_rx[k]),
            time_utc=dt.datetime.fromtimestamp(round(self.t_fix[k] * 100) / 100, tz=dt.timezone.utc),
            lat_deg=opt(self.lat),
            lon_deg=opt(self.lon),
            alt_m=opt(self.alt_msl),
            quality=int(self.quality[k]),
            valid=valid,
            sats=int(self.sats[k]),
            hdop=opt(self.hdop),
            speed_mps=opt(self.speed),
            course_rad=opt(self.course),
            heading_rad=opt(self.heading),
            sigma_lat_m=self.sigma_h if valid and self.gst_sent else None,
            sigma_lon_m=self.sigma_h if valid and self.gst_sent else None,
            sigma_alt_m=self.sigma_alt if valid and self.gst_sent else None,
            talker=self.talker,
        )


def epoch_times(settings: SimSettings) -> FloatArray:
    """Fix times (s from the start) on whole multiples of the period in UTC, within the drive."""
    period_cs = round(100.0 / settings.gps_rate_hz)
    first_cs = -round(settings.start_unix_s * 100.0) % period_cs
    n = int((settings.duration_s * 100.0 - first_cs) // period_cs) + 1
    return (first_cs + period_cs * np.arange(n)) / 100.0


def in_outage(settings: SimSettings, t_rel: NDArray[np.float64]) -> NDArray[np.bool_]:
    """True where a fix time (s from the start) falls in one of the half-open outages [start, start + length)."""
    out = np.zeros(np.shape(t_rel), dtype=bool)
    for start, length in settings.outages:
        out |= (t_rel >= start) & (t_rel < start + length)
    return out


def position_errors(settings: SimSettings, n: int, rng: np.random.Generator) -> FloatArray:
    """Errors (n, 3) east/north/up (m) of the selected model, without multipath."""
    scale = settings.gps_error_scale_m * np.array([1.0, 1.0, VERTICAL_ERROR_FACTOR])
    if settings.gps_error in ("uniform", "rtk"):
        return rng.uniform(-1.0, 1.0, (n, 3)) * scale
    if settings.gps_error == "gaussian":
        return rng.normal(0.0, 1.0, (n, 3)) * scale
    rho = math.exp(-1.0 / (settings.gps_rate_hz * settings.gps_walk_tau_s))
    walk = gauss_markov(n, rho, rng, dims=3)
    white = rng.normal(0.0, 1.0, (n, 3))
    return (WALK_SHARE * walk + math.sqrt(1.0 - WALK_SHARE**2) * white) * scale


def multipath_errors(settings: SimSettings, t_rel: FloatArray, rng: np.random.Generator) -> FloatArray:
    """Horizontal jumps (n, 2) east/north (m): Poisson events of 1-10 s, sized multipath_min_m-multipath_max_m."""
    count = rng.poisson(settings.multipath_per_min * settings.duration_s / 60.0)
    starts = rng.uniform(0.0, settings.duration_s, count)
    lengths = rng.uniform(1.0, 10.0, count)
    sizes = rng.uniform(settings.multipath_min_m, settings.multipath_max_m, count)
    return _jumps(t_rel, starts, lengths, sizes, rng.uniform(0.0, 2.0 * math.pi, count))


def outlier_errors(settings: SimSettings, t_rel: FloatArray, rng: np.random.Generator) -> FloatArray:
    """Heavy-tailed horizontal outliers (n, 2) east/north (m): Poisson events (``gps_outliers_per_min``) of
    0.1-1.5 s whose sizes are exponential with mean ``gps_outlier_m``: mostly a few metres, now and then ten."""
    count = rng.poisson(settings.gps_outliers_per_min * settings.duration_s / 60.0)
    starts = rng.uniform(0.0, settings.duration_s, count)
    lengths = rng.uniform(0.1, 1.5, count)
    sizes = rng.exponential(settings.gps_outlier_m, count)
    return _jumps(t_rel, starts, lengths, sizes, rng.uniform(0.0, 2.0 * math.pi, count))


def _jumps(
    t_rel: FloatArray, starts: FloatArray, lengths: FloatArray, sizes: FloatArray, directions: FloatArray
) -> FloatArray:
    out = np.zeros((len(t_rel), 2))
    for start, length, size, direction in zip(starts, lengths, sizes, directions, strict=True):
        inside = (t_rel >= start) & (t_rel < start + length)
        out[inside] += size * np.array([math.sin(direction), math.cos(direction)])
    return out


def gauss_markov(n: int, rho: float, rng: np.random.Generator, dims: int = 2) -> FloatArray:
    """(n, dims) first-order Gauss-Markov sequence of unit variance and step correlation ``rho``."""
    drive = rng.normal(0.0, 1.0, (n, dims))
    out = np.empty((n, dims))
    if n:
        out[0] = drive[0]
    step = math.sqrt(1.0 - rho * rho)
    for k in range(1, n):
        out[k] = rho * out[k - 1] + step * drive[k]
    return out


def clock_offset_s(settings: SimSettings, t_rel: FloatArray) -> FloatArray:
    """Host (CAN) clock minus GNSS time (s) at fix times ``t_rel``: the offset at mid-drive plus the drift."""
    return settings.gps_time_offset_s + settings.gps_clock_drift_ppm * 1e-6 * (t_rel - settings.duration_s / 2.0)


def reported_sigma_m(settings: SimSettings) -> float:
    """The 1-sigma horizontal error per axis the receiver reports in GST (multipath not included)."""
    uniform = settings.gps_error in ("uniform", "rtk")
    return settings.gps_error_scale_m / (math.sqrt(3.0) if uniform else 1.0)


def _has_body_geometry(settings: SimSettings) -> bool:
    return any(
        getattr(settings, name) != 0.0
        for name in ("antenna_forward_m", "antenna_left_m", "thrust_angle_deg", "sideslip_deg_per_mps2")
    )


def simulate_receiver(
    settings: SimSettings,
    trajectory: Trajectory,
    frame: LocalFrame,
    antenna: int,
    rng: np.random.Generator,
    real_rng: np.random.Generator | None = None,
    body: Body | None = None,
) -> tuple[GpsEpochs, list[str]]:
    """The epochs of one antenna's receiver and its NMEA lines ``(unix_t) $GP...*hh``.

    ``real_rng`` draws the real-car errors (outliers, dropped epochs, velocity error); ``body`` carries the
    sideslip (default: none).
    """
    real_rng = real_rng if real_rng is not None else np.random.default_rng(0)
    body = body if body is not None else Body(trajectory)
    t_rel = epoch_times(settings)
    n = len(t_rel)
    t_true = t_rel + clock_offset_s(settings, t_rel)
    motion = trajectory.at(t_true)
    east, north, true_speed, true_course = motion.east, motion.north, motion.speed, motion.azimuth
    true_heading = motion.azimuth
    if _has_body_geometry(settings):
        forward = settings.antenna_forward_m - (settings.antenna_distance_m if antenna == 2 else 0.0)
        east, north, v_east, v_north = body.point(motion, forward, settings.antenna_left_m)
        true_speed = np.hypot(v_east, v_north)
        true_course = np.arctan2(v_east, v_north)
        true_heading = body.heading(motion)
    elif antenna == 2:
        # d behind antenna 1 on the lengthwise axis: it also moves d * yaw_rate to the right
        d = settings.antenna_distance_m
        east = east - d * np.sin(motion.azimuth)
        north = north - d * np.cos(motion.azimuth)
        true_speed = np.hypot(motion.speed, d * motion.yaw_rate)
        true_course = motion.azimuth + np.arctan2(d * motion.yaw_rate, motion.speed)
    errors = position_errors(settings, n, rng)
    errors[:, :2] += multipath_errors(settings, t_rel, rng)
    errors[:, :2] += outlier_errors(settings, t_rel, real_rng)
    geo = frame.to_geodetic(east + errors[:, 0], north + errors[:, 1], errors[:, 2])
    speed_sigma = 0.01 if settings.gps_error == "rtk" else 0.05
    speed = np.abs(true_speed + rng.normal(0.0, speed_sigma, n))
    course_noise = rng.normal(0.0, 1.0, n) * speed_sigma / np.maximum(true_speed, COURSE_MIN_SPEED_MPS)
    heading_noise = rng.normal(0.0, math.radians(settings.heading_sigma_deg), n)
    sats = np.clip(11 + np.cumsum(rng.choice([-1, 0, 1], n, p=[0.01, 0.98, 0.01])), 7, 14)
    latency = settings.gps_latency_s + rng.uniform(0.0, settings.gps_latency_jitter_s, n)
    if settings.gps_velocity_sigma_mps > 0.0:
        rho = math.exp(-1.0 / (settings.gps_rate_hz * settings.gps_velocity_tau_s))
        v_err = settings.gps_velocity_sigma_mps * gauss_markov(n, rho, real_rng)
        v_east = true_speed * np.sin(true_course) + v_err[:, 0]
        v_north = true_speed * np.cos(true_course) + v_err[:, 1]
        speed = np.hypot(v_east, v_north)
        course_noise = np.angle(np.exp(1j * (np.arctan2(v_east, v_north) - true_course)))
    dropped = real_rng.random(n) < settings.gps_drop_rate

    valid = ~in_outage(settings, t_rel)
    dual_heading = settings.antennas == 2 and antenna == 1
    nan = np.full(n, math.nan)
    lat, lon, alt, spd, course, heading = (nan.copy() for _ in range(6))
    last_course = math.nan
    for k in np.flatnonzero(valid):
        lat[k] = quantize_latlon(float(geo[k, 0]))
        lon[k] = quantize_latlon(float(geo[k, 1]))
        alt[k] = round(float(geo[k, 2]) - GEOID_SEP_M, 3)
        spd[k] = round(speed[k] * KNOTS_PER_MPS, 3) * MPS_PER_KNOT
        if spd[k] >= COURSE_MIN_SPEED_MPS:
            last_course = quantize_angle_rad(float(true_course[k] + course_noise[k]))
        course[k] = last_course
        if dual_heading:
            heading[k] = quantize_angle_rad(float(true_heading[k] + heading_noise[k]))
    error = np.where(valid[:, None], errors[:, :2], math.nan)
    hdop = np.where(valid, np.round(0.5 + 5.0 / sats, 2), 99.99)
    epochs = GpsEpochs(
        antenna=antenna,
        t_fix=settings.start_unix_s + t_rel,
        t_rx=nan.copy(),
        sent=(valid | (settings.outage_style == "nofix")) & ~dropped,
        valid=valid,
        quality=np.where(valid, 4 if settings.gps_error == "rtk" else 1, 0),
        lat=lat,
        lon=lon,
        alt_msl=alt,
        speed=spd,
        course=course,
        heading=heading,
        sats=np.where(valid, sats, 0),
        hdop=hdop if settings.gps_nmea_hdop else nan.copy(),
        sigma_h=round(reported_sigma_m(settings), 3),
        sigma_alt=round(VERTICAL_ERROR_FACTOR * reported_sigma_m(settings), 3),
        heading_sent=dual_heading,
        gst_sent=settings.gps_nmea_gst,
        talker=settings.gps_talker,
        error_east=error[:, 0],
        error_north=error[:, 1],
    )
    return _transmit(epochs, settings.start_unix_s + t_true + latency)


def _transmit(epochs: GpsEpochs, first_byte: FloatArray) -> tuple[GpsEpochs, list[str]]:
    """Serialise each sent epoch over the serial line from ``first_byte`` (Unix s, host clock): receive times
    (us) strictly increasing."""
    lines: list[str] = []
    t_rx = np.full(len(epochs.t_fix), math.nan)
    last_us = -1
    for k in np.flatnonzero(epochs.sent):
        t = float(first_byte[k])
        for i, text in enumerate(_sentences(epochs, k)):
            t += (len(text) + 2) * 10.0 / SERIAL_BAUD
            last_us = max(round(t * 1e6), last_us + 1)
            lines.append(f"({last_us // 1_000_000}.{last_us % 1_000_000:06d}) {text}")
            if i == 0:
                t_rx[k] = last_us / 1e6
    return dataclasses.replace(epochs, t_rx=t_rx), lines


def _sentences(e: GpsEpochs, k: int) -> list[str]:
    """GGA, RMC, GST (and HDT with two antennas) of epoch ``k``; with empty fields and "no fix" when not valid.
    Without ``gst_sent`` no GST; an epoch's NaN HDOP leaves the GGA field empty."""
    t = float(e.t_fix[k])
    talker = e.talker
    hdop = None if math.isnan(e.hdop[k]) else float(e.hdop[k])
    if not e.valid[k]:
        no_fix = [
            format_gga(t, None, None, 0, sats=0, hdop=hdop, talker=talker),
            format_rmc(t, None, None, status="V", mode="N", talker=talker),
        ]
        if e.gst_sent:
            no_fix.append(format_gst(t, rms_m=None, sigma_lat_m=None, sigma_lon_m=None, talker=talker))
        return no_fix + ([format_hdt(None, talker=talker)] if e.heading_sent else [])
    rtk = e.quality[k] == 4
    lat, lon = float(e.lat[k]), float(e.lon[k])
    out = [
        format_gga(
            t,
            lat,
            lon,
            int(e.quality[k]),
            sats=int(e.sats[k]),
            hdop=hdop,
            alt_msl_m=float(e.alt_msl[k]),
            geoid_sep_m=GEOID_SEP_M,
            dgps_age_s=1.0 if rtk else None,
            dgps_station="0001" if rtk else "",
            talker=talker,
        ),
        format_rmc(
            t,
            lat,
            lon,
            status="A",
            mode="R" if rtk else "A",
            speed_mps=float(e.speed[k]),
            course_rad=None if math.isnan(e.course[k]) else float(e.course[k]),
            talker=talker,
        ),
    ]
    if e.gst_sent:
        out.append(
            format_gst(
                t,
                rms_m=e.sigma_h,
                sigma_lat_m=e.sigma_h,
                sigma_lon_m=e.sigma_h,
                sigma_alt_m=e.sigma_alt,
                sigma_major_m=e.sigma_h,
                sigma_minor_m=e.sigma_h,
                orientation_rad=0.0,
                talker=talker,
            )
        )
    if e.heading_sent:
        out.append(format_hdt(float(e.heading[k]), talker=talker))
    return out
