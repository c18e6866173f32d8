"""The installation parameters of a car's GNSS receiver and CAN sensors, from one recorded drive (``sumhe
calibrate``): what a test engineer measures before trusting a new car, with standard errors.

Definitions (the CAN values as the config decodes them, its mapping's ``scale`` applied; ``d`` =
``[sensors.can] delay_s``, the age the config gives every CAN sample, and ``s`` = ``speed_delay_s``, how much
older it takes the speed to be):

* ``gps_time_offset_s``: the CAN-clock time at which a fix's position was true minus the time sumhe stamped the
  fix with (``[gps] time``, ``latency_s``), taking the CAN speed to be ``d + s`` old: ``-lag - d - s`` for the lag
  of the receiver's speed over ground behind the CAN speed (:func:`~sumhe.frontend.alignment.speed_lag`). GNSS and
  CAN alone observe relative timing only: the offset is relative to the CAN speed, whose own age (an OBD-II
  reply's, say) is the part ``d + s`` does not hold.
* ``speed_scale``: true speed = scale x CAN speed (negative: the mapping has the wrong sign).
* ``yaw_rate_bias_dps`` and ``yaw_rate_scale``: true yaw rate = scale x (CAN - bias) (deg/s; negative scale: the
  wrong sign), from the rate of the receiver's azimuth against the CAN yaw rate
  (:func:`~sumhe.frontend.alignment.course_lag`); where the car stood still long enough, the bias is that fit and
  the CAN yaw rate at standstill combined by their variances, if they agree (:func:`combined_bias`).
* ``can_delay_s``: how much older the CAN speed is than the CAN yaw rate (s): the azimuth's lag minus the speed's.
  This is what the two fits determine of the CAN sensors' ages; their common age ``d`` is not observable from
  GNSS and CAN. It is what ``[sensors.can] speed_delay_s`` holds (an OBD-II speed 0.2 s old beside a broadcast
  yaw rate put the fixes of a realistic simulated highway drive 0.19 s late against the yaw rate, 4 m behind on
  the mean at 32 m/s, until the key said so); the snippet writes it as a comment, not as the key: a course's lag
  carries the antenna's lead and the sideslip's lag, which a drive at a steady speed cannot tell from timing, and
  on simulated drives it missed by up to 0.17 s, 2-6 of its standard errors (README, ``sumhe bench calibrate``).

Methods, in order of preference: the time offset and speed scale from the receiver's speed over ground, else from
the speed between fix positions; the yaw rate from the receiver's heading (HDT: the body's azimuth), else its
course over ground, else the course between fix positions. A course is the antenna's: its lead of ``l / v`` in
turns (antenna ``l`` ahead of the rear axle) is fitted with the lag (:data:`LEVER_PRIOR_M`), and the direction
of motion turns after the body by the sideslip's build-up (``k v``, :data:`SIDESLIP_GRADIENT`), which
``can_delay_s`` removes within its uncertainty. A coarse speed quantum (whole km/h from OBD-II) is not random
error at a steady speed: the scale is fitted by generalised least squares with one random error per quantum step,
rounded or truncated (:func:`speed_rounding`, :func:`speed_scale_fit`). Standard errors are delete-one-block
jackknife estimates over :data:`JACKKNIFE_BLOCKS` stretches of the drive (GNSS errors are correlated over seconds),
at least the fit's own.

:func:`read_signals` reads the drive (I/O), :func:`calibrate` is pure, :func:`toml_snippet` writes what the
config accepts.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.config import Config, SignalSpec
from sumhe.errors import CalibrationError
from sumhe.frontend.alignment import CHORD_S, MIN_PAIRS, MIN_SPEED_MPS, LagFit, course_lag, speed_lag
from sumhe.frontend.measurements import heading_sigma
from sumhe.frontend.sensor_check import rounding_wrong
from sumhe.geo import LocalFrame
from sumhe.io.imu import Mounting
from sumhe.io.quanta import signal_quanta
from sumhe.io.replay import Paths, RecordedDrive
from sumhe.messages import CanSample, GnssFix, Sample
from sumhe.settings import GnssModel
from sumhe.settings.sensors import COARSE_QUANTUM_MPS, FALLBACK_SPEED_RESOLUTION_MPS

FloatArray = NDArray[np.float64]

KEYS = ("gps_time_offset_s", "speed_scale", "yaw_rate_bias_dps", "yaw_rate_scale", "can_delay_s")
"""The parameters, in the order they are reported (``--json``: each and ``<key>_std``)."""
JACKKNIFE_BLOCKS = 10
MAX_LAG_STD_S = 0.1
"""A lag with a larger standard error is not determined (the speed or the azimuth hardly changed)."""
MAX_YAW_SCALE_STD = 0.01
"""A yaw-rate scale with a larger standard error is not determined (the drive hardly turns): one that the
estimators could start from must be known to a per cent."""
LEVER_PRIOR_M = (1.0, 1.5)
"""Prior (mean, sigma) of the antenna's forward offset from the rear axle (m): roof and dashboard antennas and
loggers' GNSS modules sit 0-2.5 m ahead of it. It holds the fit where the speed hardly varies."""
SIDESLIP_GRADIENT = (math.radians(0.2), math.radians(0.1))
"""Body sideslip per lateral acceleration at the rear axle (mean, sigma; rad per m/s^2): passenger cars show
0.05-0.4 deg/(m/s^2). The direction of motion then follows the body's yaw by ``k v`` s: a course's lag
includes it, a heading's does not."""
TURN_RATE_RPS = math.radians(2.0)
"""A yaw rate above this is a turn (for the message saying why a scale is undetermined)."""
STANDSTILL_MIN_S = 5.0
SIGN_SIGMAS = 3.0
AGREE_SIGMAS = 3.0
"""The moving fit's bias and the standstill mean are combined only while they differ by at most this many of their
combined standard errors (a bias that depends on the motion, or a wrong fit, is reported, not averaged away)."""
"""A yaw rate's sign is told when its scale is this many standard errors from zero."""
SPEED_SCALE_PLAUSIBLE = (0.8, 1.25)
YAW_SCALE_PLAUSIBLE = (0.5, 2.0)


@dataclass(frozen=True, slots=True)
class DriveSignals:
    """What calibration reads of a drive: the valid fixes (times in s, east/north in m from the first, speed over
    ground in m/s, course and heading in rad; NaN where a fix lacks one; each heading's 1-sigma as the front-end
    weighs it, :func:`~sumhe.frontend.measurements.heading_sigma`: the receiver's rating where it rates it worse
    than ``sensors.gnss.heading_sigma_rad``), the CAN speed (m/s) and yaw rate (rad/s) with their times, the CAN
    speed's quantum (m/s), and counts for the report."""

    t_fix: FloatArray
    east: FloatArray
    north: FloatArray
    gnss_speed: FloatArray
    course: FloatArray
    heading: FloatArray
    t_speed: FloatArray
    speed: FloatArray
    t_yaw: FloatArray
    yaw: FloatArray
    speed_quantum_mps: float
    fixes: int
    origin_deg: tuple[float, float] = (0.0, 0.0)
    """Latitude and longitude (deg) of the east/north frame's origin: the first valid fix."""
    heading_sigma: FloatArray | None = None
    """Each fix's heading's 1-sigma (rad) as the front-end weighs it; None: all alike."""
    imu: Mounting | None = None
    """With the yaw rate from a 3-axis IMU: how the IMU sits, as its accelerometer found it."""

    @property
    def span_s(self) -> float:
        times = [a[[0, -1]] for a in (self.t_fix, self.t_speed, self.t_yaw) if len(a)]
        both = np.concatenate(times)
        return float(both.max() - both.min())


@dataclass(frozen=True, slots=True)
class Parameter:
    """One parameter: its value and standard error (None: not determined), and how it was measured or why not."""

    value: float | None
    std: float | None
    method: str


@dataclass(frozen=True, slots=True)
class SignCheck:
    """A check of a mapped CAN quantity against the receiver: ``ok`` None when it cannot be told; ``fix`` says what
    to change in the config when it is not ok."""

    quantity: str
    ok: bool | None
    detail: str
    fix: str = ""


@dataclass(frozen=True)
class Calibration:
    """The five parameters (:data:`KEYS`), the sign checks, notes (further findings), and the config's CAN delay
    and speed delay the time offset is relative to (s)."""

    gps_time_offset_s: Parameter
    speed_scale: Parameter
    yaw_rate_bias_dps: Parameter
    yaw_rate_scale: Parameter
    can_delay_s: Parameter
    signs: tuple[SignCheck, ...]
    notes: tuple[str, ...]
    delay_s: float
    speed_delay_s: float = 0.0
    speed_factor: float | None = None
    """What the mapping's speed ``scale`` is multiplied by: ``speed_scale``, or where the best fit's offset is
    not the one ``speed_rounding`` takes, the one factor that fits the drive's speeds best at that one."""
    speed_rounding: str | None = None
    """``sensors.can.speed_rounding`` as the drive shows it (``"round"`` or ``"truncate"``); None where the CAN
    speed's quantum is too fine to tell (below :data:`~sumhe.settings.sensors.COARSE_QUANTUM_MPS`) or the drive
    does not tell it (:func:`speed_rounding`)."""

    def parameters(self) -> dict[str, Parameter]:
        return {key: getattr(self, key) for key in KEYS}

    def to_json(self) -> dict[str, float | None]:
        """Exactly the five keys and ``<key>_std`` (None where not determined)."""
        out: dict[str, float | None] = {}
        for key, p in self.parameters().items():
            out[key] = p.value
            out[f"{key}_std"] = p.std
        return out


# ---- reading a drive -----------------------------------------------------------------------------------------------


def read_signals(config: Config, can_logs: Paths, nmea_logs: Paths = None) -> DriveSignals:
    """Decode a recorded drive (as ``sumhe replay`` reads it) into :class:`DriveSignals`. SourceError for a missing
    or unreadable log, ConfigError for a mapping the DBCs lack, CalibrationError without a valid fix or a CAN
    speed."""
    drive = RecordedDrive(config, can_logs, nmea_logs)
    return signals_of(drive, drive.samples())


def signals_of(drive: RecordedDrive, samples: Iterable[Sample]) -> DriveSignals:
    """:class:`DriveSignals` of ``samples`` (the drive's, in time order; the drive gives its config and counters).
    CalibrationError without a valid fix or a CAN speed."""
    config = drive.config
    fixes: list[GnssFix] = []
    can: dict[str, list[tuple[float, float]]] = {"speed": [], "yaw_rate": []}
    total = 0
    for s in samples:
        if isinstance(s, GnssFix):
            total += 1
            if s.valid and s.lat_deg is not None and s.lon_deg is not None and math.isfinite(s.t):
                fixes.append(s)
        elif isinstance(s, CanSample) and s.quantity in can and math.isfinite(s.value):
            can[s.quantity].append((s.t, s.value))
    if not fixes:
        source = "the CAN logs (gps.source = 'can')" if config.gps.source == "can" else "the NMEA logs"
        raise CalibrationError(f"no valid GNSS fix in {source} ({total} fixes, none with a position)")
    if len(can["speed"]) < 2:
        ls = drive.log_stats
        raise CalibrationError(
            f"no CAN speed decoded ({len(can['speed'])} samples from {ls.frames} CAN frames of {ls.files} readable "
            f"files): check the logs and can.signals.speed in {drive.config.source}"
        )
    frame = LocalFrame(float(fixes[0].lat_deg), float(fixes[0].lon_deg), 0.0)  # type: ignore[arg-type]
    enu = frame.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes])

    def column(name: str) -> FloatArray:
        return np.array([math.nan if getattr(f, name) is None else getattr(f, name) for f in fixes], dtype=float)

    speed = np.array(sorted(can["speed"])).reshape(-1, 2)
    yaw = np.array(sorted(can["yaw_rate"])).reshape(-1, 2)
    quantum = signal_quanta(drive.config).get("speed") or (
        drive.config.sensors.can.speed_resolution_mps or FALLBACK_SPEED_RESOLUTION_MPS
    )
    imu = drive.decoder.imu_mountings().get("can.signals.yaw_rate") if drive.decoder is not None else None
    return DriveSignals(
        t_fix=np.array([f.t for f in fixes]),
        east=enu[:, 0],
        north=enu[:, 1],
        gnss_speed=column("speed_mps"),
        course=column("course_rad"),
        heading=column("heading_rad"),
        heading_sigma=np.array([heading_sigma(f.heading_sigma_rad, config.estimation.gnss) for f in fixes]),
        t_speed=speed[:, 0],
        speed=speed[:, 1],
        t_yaw=yaw[:, 0],
        yaw=yaw[:, 1],
        speed_quantum_mps=float(quantum),
        fixes=total,
        origin_deg=(frame.lat0_deg, frame.lon0_deg),
        imu=imu,
    )


# ---- the fits ------------------------------------------------------------------------------------------------------


def speed_scale_fit(
    gnss: FloatArray, can: FloatArray, quantum_mps: float, turn_rps: FloatArray | None = None
) -> tuple[float, float, float]:
    """``(scale, offset_mps, std)`` of ``gnss = scale * (can + offset)`` (speeds > 0, m/s, paired at one time) by
    generalised least squares: the CAN speed's rounding error is one random value per quantum step (uniform over
    a quantum: at a steady speed it does not average out), white noise besides; ``std`` is the scale's standard
    error under that model. ``offset`` is 0 (rounded) or, for a quantum of at least :data:`COARSE_QUANTUM_MPS`,
    half a quantum (truncated) if that fits better. With the yaw rate ``turn_rps`` (rad/s) at the same times, a
    term ``- y turn_rps`` is fitted beside: an antenna ``y`` left of the rear axle's middle runs slower in left
    turns, and a drive turns one way more than the other."""
    offsets = (0.0, quantum_mps / 2.0) if quantum_mps >= COARSE_QUANTUM_MPS else (0.0,)
    level = np.unique(np.round(can / quantum_mps), return_inverse=True)[1]
    n = np.bincount(level).astype(float)
    best = (math.inf, math.nan, 0.0, math.inf)
    for offset in offsets:
        x = np.column_stack([can + offset] + ([turn_rps] if turn_rps is not None else []))
        coef0, *_ = np.linalg.lstsq(x, gnss, rcond=None)
        tau2 = (coef0[0] * quantum_mps) ** 2 / 12.0
        sigma2 = max(float(np.var(gnss - x @ coef0)) - tau2, 1e-4)
        sx = np.column_stack([np.bincount(level, weights=col) for col in x.T])
        sy = np.bincount(level, weights=gnss)
        shrink = tau2 / (sigma2 + n * tau2)
        a = x.T @ x - (sx * shrink[:, None]).T @ sx
        coef = np.linalg.solve(a, x.T @ gnss - (sx * shrink[:, None]).T @ sy)
        rss = float(np.sum(np.square(gnss - x @ coef)))
        if rss < best[0]:
            best = (rss, float(coef[0]), offset, math.sqrt(sigma2 * float(np.linalg.inv(a)[0, 0])))
    return best[1], best[2], best[3]


def speed_rounding(fit: LagFit, quantum_mps: float) -> str | None:
    """How a CAN speed of ``fit`` (:func:`~sumhe.frontend.alignment.speed_lag`) is made whole quanta:
    ``"truncate"`` where it reads half a quantum low on the mean, ``"round"`` where it does not, told apart as the
    on-line check tells them (:func:`~sumhe.frontend.sensor_check.rounding_wrong`); None for a quantum below
    :data:`COARSE_QUANTUM_MPS` or while the drive does not tell them apart."""
    if quantum_mps < COARSE_QUANTUM_MPS:
        return None
    truncated = rounding_wrong(fit.reads_low, fit.reads_low_std, quantum_mps / 2.0)
    return None if truncated is None else "truncate" if truncated else "round"


def jackknife_std(
    fit: Callable[[NDArray[np.bool_]], Sequence[float] | None], t: FloatArray, blocks: int = JACKKNIFE_BLOCKS
) -> FloatArray | None:
    """Delete-one-block jackknife standard errors of the numbers ``fit(keep)`` returns, ``keep`` leaving out one of
    ``blocks`` equal stretches of the times ``t`` at a time; None with fewer than 3 fits that succeed."""
    edges = np.linspace(float(np.min(t)), float(np.max(t)), blocks + 1)
    reps = []
    for i in range(blocks):
        out = fit(~((t >= edges[i]) & (t <= edges[i + 1])))
        if out is not None and all(math.isfinite(v) for v in out):
            reps.append(out)
    if len(reps) < 3:
        return None
    values = np.array(reps, dtype=float)
    n = len(values)
    return np.sqrt((n - 1) / n * np.sum(np.square(values - values.mean(axis=0)), axis=0))  # type: ignore[no-any-return]


def chords(t: FloatArray, east: FloatArray, north: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Speed (m/s) and course (rad) between fix positions at least ``CHORD_S[0]`` s apart, at the middle times (s):
    fixes thinned to that spacing, consecutive pairs up to ``CHORD_S[1]`` s apart."""
    keep = []
    last = -math.inf
    for i, ti in enumerate(t.tolist()):
        if ti - last >= CHORD_S[0] - 1e-6:
            keep.append(i)
            last = ti
    k = np.array(keep, dtype=int)
    dt = np.diff(t[k])
    ok = dt <= CHORD_S[1]
    de, dn = np.diff(east[k])[ok], np.diff(north[k])[ok]
    mid = (0.5 * (t[k][1:] + t[k][:-1]))[ok]
    return mid, np.hypot(de, dn) / dt[ok], np.arctan2(de, dn)


@dataclass(frozen=True, slots=True)
class _SpeedFit:
    lag: LagFit
    scale: float
    """Signed: negative when the CAN speed reads negative while the car moves forward."""
    offset_mps: float
    negative_share: float
    zero_share: float
    lag_std_s: float
    scale_std: float
    rounding: str | None
    """:func:`speed_rounding` of the whole drive's fit."""
    factor: float
    """The one factor (signed) that fits the drive's speeds best as ``rounding`` takes them (half a quantum added
    where truncated): what the mapping's scale is multiplied by. ``scale`` unless the best fit's offset differs."""


def _speed_fit(t: FloatArray, g: FloatArray, sig: DriveSignals, turn_rps: FloatArray | None) -> _SpeedFit | None:
    """The speed's lag and scale (``turn_rps``: the yaw rate at the times ``t``, for :func:`speed_scale_fit`)."""
    q = sig.speed_quantum_mps

    def at_lag(keep: NDArray[np.bool_], offset: float | None) -> tuple[LagFit, float, float, float] | None:
        fit = speed_lag(t[keep], g[keep], sig.t_speed, sig.speed)
        if fit is None:
            return None
        c = np.abs(np.interp(t[keep] - fit.lag_s, sig.t_speed, sig.speed))
        gk = np.abs(g[keep])
        moving = np.isfinite(gk) & (c > MIN_SPEED_MPS) & (gk > MIN_SPEED_MPS)
        if np.count_nonzero(moving) < MIN_PAIRS:
            return None
        if offset is None:
            turns = turn_rps[keep][moving] if turn_rps is not None else None
            k, off, std = speed_scale_fit(gk[moving], c[moving], q, turns)
        else:
            x = c[moving] + offset
            k, off, std = float(x @ gk[moving] / (x @ x)), offset, math.nan
        return fit, k, off, std

    everything = np.ones(len(t), dtype=bool)
    full = at_lag(everything, None)
    if full is None:
        return None
    fit, k, offset, model_std = full

    def replicate(keep: NDArray[np.bool_]) -> tuple[float, float] | None:
        # the replicates keep the full fit's offset; the GLS weighting changes the scale by far less than its spread
        r = at_lag(keep, offset)
        return None if r is None else (r[0].lag_s, r[1])

    jack = jackknife_std(replicate, t)
    c = np.interp(t - fit.lag_s, sig.t_speed, sig.speed)
    moving = np.abs(g) > MIN_SPEED_MPS
    negative = float(np.mean(c[moving] < -MIN_SPEED_MPS / 2))
    zero = float(np.mean(np.abs(c[moving]) < MIN_SPEED_MPS / 4))
    sign = -1.0 if negative > 0.5 else 1.0
    lag_std = max(fit.std_s, float(jack[0])) if jack is not None else fit.std_s
    scale_std = max(float(jack[1]), model_std) if jack is not None else math.inf
    rounding = speed_rounding(fit, q)
    key_offset = q / 2.0 if rounding == "truncate" else 0.0
    keyed = full if key_offset == offset else at_lag(everything, key_offset)
    factor = keyed[1] if keyed is not None else k
    return _SpeedFit(fit, sign * k, offset, negative, zero, lag_std, scale_std, rounding, sign * factor)


@dataclass(frozen=True, slots=True)
class _YawFit:
    fit: LagFit
    """The free fit (scale and bias), or with the scale held at 1 where the drive does not tell it."""
    source: str
    lever: bool
    lag_std_s: float
    scale: float
    scale_std: float
    """Of the free fit: above :data:`MAX_YAW_SCALE_STD` the scale is not determined and ``fit`` holds it at 1."""
    bias_std_rps: float
    v_eff_mps: float


def _azimuth_series(sig: DriveSignals) -> tuple[FloatArray, FloatArray, str, bool, FloatArray | None] | None:
    """Times, azimuths, what they are, whether they are the antenna's course (lever arm), and their sigmas where
    they differ (a heading's rating): the receiver's heading, else its course over ground, else the course between
    fix positions."""
    for name, values, lever, sigma in (
        ("the receiver's heading", sig.heading, False, sig.heading_sigma),
        ("the receiver's course over ground", sig.course, True, None),
    ):
        if np.count_nonzero(np.isfinite(values)) >= MIN_PAIRS:
            return sig.t_fix, values, name, lever, sigma
    t, _, crs = chords(sig.t_fix, sig.east, sig.north)
    if len(t) >= MIN_PAIRS:
        return t, crs, "the course between fix positions (the fixes carry no course or heading)", True, None
    return None


def _yaw_fit(sig: DriveSignals) -> _YawFit | None:
    """The azimuth's fit (its speed threshold and lever term take the CAN speed as the speed: a few per cent of
    scale do not matter there)."""
    series = _azimuth_series(sig)
    if series is None or len(sig.t_yaw) < 2:
        return None
    t, azimuth, source, lever, sigma = series
    speed = np.abs(np.interp(t, sig.t_speed, sig.speed))
    prior = LEVER_PRIOR_M if lever else None

    def fit_on(keep: NDArray[np.bool_], scale: float | None) -> LagFit | None:
        azimuths = np.where(keep, azimuth, np.nan)
        return course_lag(
            t,
            azimuths,
            speed,
            sig.t_yaw,
            sig.yaw,
            lever_prior_m=prior,
            speed_weighted=lever,
            fixed_scale=scale,
            sigma_rad=sigma,
        )

    def fitted(scale: float | None) -> tuple[LagFit, tuple[float, ...]] | None:
        full = fit_on(np.ones(len(t), dtype=bool), scale)
        if full is None:
            return None

        def replicate(keep: NDArray[np.bool_]) -> tuple[float, float, float] | None:
            r = fit_on(keep, scale)
            return None if r is None else (r.lag_s, r.scale, r.offset)

        jack = jackknife_std(replicate, t)
        return full, (math.inf, math.inf, math.inf) if jack is None else tuple(float(v) for v in jack)

    free = fitted(None)
    if free is None:
        return None
    full, stds = free
    scale, scale_std = full.scale, stds[1]
    if not scale_std <= MAX_YAW_SCALE_STD:
        unit = fitted(1.0)
        if unit is not None:
            full, stds = unit
    moving = speed > MIN_SPEED_MPS
    yaw_at = np.interp(t, sig.t_yaw, sig.yaw)
    weight = np.square(np.diff(yaw_at))[moving[1:] & moving[:-1]]
    v = 0.5 * (speed[1:] + speed[:-1])[moving[1:] & moving[:-1]]
    v_eff = float(np.sum(weight * v) / np.sum(weight)) if np.sum(weight) > 0 else math.nan
    return _YawFit(full, source, lever, max(full.std_s, stds[0]), scale, scale_std, stds[2], v_eff)


def _turn_rate(t: FloatArray, yf: _YawFit, sig: DriveSignals) -> FloatArray:
    """The yaw rate (rad/s) at the times ``t``: the CAN's, corrected by the fit and moved by its lag."""
    fit = yf.fit
    return fit.scale * (np.interp(t - fit.lag_s, sig.t_yaw, sig.yaw) - fit.offset)  # type: ignore[no-any-return]


def _standstill_bias(sig: DriveSignals) -> tuple[float, float, float] | None:
    """Mean, standard error and duration (rad/s, rad/s, s) of the CAN yaw rate while the CAN speed reads zero
    before and after; None with less than :data:`STANDSTILL_MIN_S` of it."""
    if len(sig.t_yaw) < 2:
        return None
    j = np.searchsorted(sig.t_speed, sig.t_yaw)
    inside = (j > 0) & (j < len(sig.t_speed))
    jj = np.clip(j, 1, len(sig.t_speed) - 1)
    still = inside & (sig.speed[jj - 1] == 0.0) & (sig.speed[jj] == 0.0)
    period = float(np.median(np.diff(sig.t_yaw)))
    duration = np.count_nonzero(still) * period
    if duration < STANDSTILL_MIN_S:
        return None
    values = sig.yaw[still]
    blocks = max(int(duration), 1)  # the noise is correlated over the sensor's filter: one value per second
    return float(np.mean(values)), float(np.std(values)) / math.sqrt(blocks), duration


def combined_bias(fit: tuple[float, float], still: tuple[float, float], quantum: float) -> tuple[float, float] | None:
    """The yaw-rate bias (value, standard error; rad/s) of the moving fit ``fit`` and the standstill mean ``still``
    (each value and standard error) weighted by their variances; the standstill's error at least a ``quantum``
    step's rounding (``quantum / sqrt 12``: a sensor that reads one value all along averages none of it away).
    None where they disagree (:data:`AGREE_SIGMAS`) or the fit's error is not finite."""
    (b_fit, s_fit), (b_still, s_still) = fit, (still[0], max(still[1], quantum / math.sqrt(12.0)))
    if not (math.isfinite(s_fit) and s_fit > 0.0 and s_still > 0.0):
        return None
    if abs(b_fit - b_still) > AGREE_SIGMAS * math.hypot(s_fit, s_still):
        return None
    w_fit, w_still = s_fit**-2, s_still**-2
    return (w_fit * b_fit + w_still * b_still) / (w_fit + w_still), (w_fit + w_still) ** -0.5


def _quantum(values: FloatArray) -> float:
    """The smallest step between the distinct values of a signal (its resolution as logged; 0 with fewer than two)."""
    steps = np.diff(np.unique(values[np.isfinite(values)]))
    return float(np.min(steps)) if len(steps) else 0.0


# ---- the calibration -----------------------------------------------------------------------------------------------


def calibrate(sig: DriveSignals, delay_s: float = 0.0, speed_delay_s: float = 0.0) -> Calibration:
    """The installation parameters of one drive (see the module docstring); ``delay_s`` and ``speed_delay_s`` are
    the config's ``[sensors.can]`` ones (s)."""
    notes = [sig.imu.describe()] if sig.imu is not None else []
    moving_fixes = int(np.count_nonzero(np.abs(sig.gnss_speed) > MIN_SPEED_MPS))
    if moving_fixes >= MIN_PAIRS:
        t_g, g, g_source = sig.t_fix, sig.gnss_speed, "the receiver's speed over ground"
    else:
        t_g, g, _ = chords(sig.t_fix, sig.east, sig.north)
        g_source = (
            "the speed between fix positions (the fixes carry "
            + ("no speed over ground" if moving_fixes == 0 else f"a speed over ground above 2 m/s {moving_fixes} times")
            + ")"
        )
    yf = _yaw_fit(sig)
    turn = _turn_rate(t_g, yf, sig) if yf is not None else None
    if yf is not None and turn is not None and yf.lever:
        # an antenna l ahead of the rear axle runs faster than the axle in turns, sqrt(v^2 + (l omega)^2): 0.6 %
        # at 5 m/s and 0.3 rad/s with 1.85 m, enough to bias the scale of a town drive
        g = np.sign(g) * np.sqrt(np.maximum(np.square(g) - np.square(yf.fit.lever_m * turn), 0.0))
        g_source += ", less the antenna's sideways speed in turns"
    if turn is not None and not float(np.std(turn)) >= TURN_RATE_RPS / 2:
        turn = None  # a drive that hardly turns tells no lateral antenna offset
    sf = _speed_fit(t_g, g, sig, turn) if len(t_g) else None
    offset, scale, speed_sign = _speed_parameters(sf, g_source, delay_s + speed_delay_s, sig, notes)
    bias, yaw_scale, yaw_sign = _yaw_parameters(yf, sig, notes)
    return Calibration(
        gps_time_offset_s=offset,
        speed_scale=scale,
        yaw_rate_bias_dps=bias,
        yaw_rate_scale=yaw_scale,
        can_delay_s=_relative_delay(sf, yf, notes),
        signs=(speed_sign, yaw_sign),
        notes=tuple(notes),
        delay_s=delay_s,
        speed_delay_s=speed_delay_s,
        speed_factor=sf.factor if sf is not None and scale.value is not None else None,
        speed_rounding=sf.rounding if sf is not None and scale.value is not None else None,
    )


def _untold(lag: LagFit, quantum_mps: float) -> str:
    return (
        f"the drive does not tell rounded from truncated apart (the CAN speed reads {lag.reads_low:.3f} +- "
        f"{lag.reads_low_std:.3f} m/s low on the mean; truncated {quantum_mps / 2:.3f})"
    )


def _speed_parameters(
    sf: _SpeedFit | None, source: str, speed_age_s: float, sig: DriveSignals, notes: list[str]
) -> tuple[Parameter, Parameter, SignCheck]:
    if sf is None:
        why = (
            f"not determined: fewer than {MIN_PAIRS} moving fixes above {MIN_SPEED_MPS:g} m/s within the CAN data "
            f"({source})"
        )
        return Parameter(None, None, why), Parameter(None, None, why), SignCheck("speed", None, why)
    lag = sf.lag
    if sf.lag_std_s <= MAX_LAG_STD_S:
        direction = "before" if lag.lag_s >= 0 else "after"
        offset = Parameter(
            -lag.lag_s - speed_age_s,
            sf.lag_std_s,
            f"{source} against the CAN speed: it follows it by {lag.lag_s:.3f} s, so a fix is true "
            f"{abs(lag.lag_s):.3f} s {direction} its stamp on the clock of a CAN speed taken to be "
            f"{speed_age_s:g} s old ([sensors.can] delay_s + speed_delay_s)",
        )
    else:
        offset = Parameter(
            None,
            None,
            f"not determined: the speed hardly changes (the lag of {source} behind the CAN speed has a standard "
            f"error of {sf.lag_std_s:.2g} s)",
        )
    q = sig.speed_quantum_mps
    kind = "truncated" if sf.offset_mps > 0 else "rounded"
    scale = Parameter(
        sf.scale,
        sf.scale_std,
        f"{source} against the CAN speed at that lag ({lag.n} fixes; the CAN speed {kind} to {q:.3g} m/s steps)",
    )
    if sf.rounding == "truncate":
        notes.append(
            f"the CAN speed is truncated to whole steps of {q:.3g} m/s: true speed = {sf.factor:.4f} x (CAN + "
            f"{q / 2:.3g} m/s); with sensors.can.speed_rounding = 'truncate' (below) the estimators take each CAN "
            "speed other than 0 at the middle of its step"
        )
    elif sf.offset_mps > 0:
        notes.append(
            f"the CAN speed's steps of {q:.3g} m/s fit best as truncated (true speed = {sf.scale:.4f} x (CAN + "
            f"{sf.offset_mps:.3g} m/s)), but {_untold(lag, q)}: speed_rounding is left as it is and the mapping gets "
            f"the one factor that fits the drive's speeds best without the offset, {sf.factor:.4f}"
        )
    elif sf.rounding is None and q >= COARSE_QUANTUM_MPS:
        notes.append(f"the CAN speed's steps of {q:.3g} m/s fit best as rounded, but {_untold(lag, q)}")
    k = abs(sf.scale)
    if not SPEED_SCALE_PLAUSIBLE[0] <= k <= SPEED_SCALE_PLAUSIBLE[1]:
        notes.append(
            f"the CAN speed reads {1 / k:.3g} x the receiver's: check the signal's unit (can.signals.speed.unit; "
            "km/h read as m/s is 3.6x) before folding the scale into the mapping"
        )
    if sf.zero_share > 0.5:
        sign = SignCheck(
            "speed",
            None,
            f"the CAN speed reads zero at {100 * sf.zero_share:.0f} % of the fixes that move: is can.signals.speed the "
            "vehicle's speed?",
        )
    elif sf.scale < 0:
        sign = SignCheck(
            "speed",
            False,
            f"the CAN speed reads negative at {100 * sf.negative_share:.0f} % of the fixes that move forward",
            "set scale = -1 (times the scale it has) in can.signals.speed",
        )
    else:
        sign = SignCheck("speed", True, "the CAN speed is positive while the fixes move")
    return offset, scale, sign


def _yaw_parameters(yf: _YawFit | None, sig: DriveSignals, notes: list[str]) -> tuple[Parameter, Parameter, SignCheck]:
    still = _standstill_bias(sig)
    if still is not None:
        notes.append(
            f"the CAN yaw rate at standstill ({still[2]:.0f} s): {math.degrees(still[0]):+.3f} +- "
            f"{math.degrees(still[1]):.3f} deg/s"
        )
    if yf is None:
        why = (
            "not determined: no CAN yaw rate"
            if len(sig.t_yaw) < 2
            else f"not determined: fewer than {MIN_PAIRS} pairs of moving fixes with an azimuth"
        )
        bias = (
            Parameter(math.degrees(still[0]), math.degrees(still[1]), "the CAN yaw rate at standstill (" + why + ")")
            if still is not None
            else Parameter(None, None, why)
        )
        return bias, Parameter(None, None, why), SignCheck("yaw_rate", None, why)
    fit = yf.fit
    lag = f"lag {fit.lag_s:.3f} +- {yf.lag_std_s:.3f} s"
    lever = f", antenna {fit.lever_m:.2f} m ahead of the rear axle fitted" if yf.lever else ""
    method = f"the rate of {yf.source} against the CAN yaw rate ({fit.n} pairs of fixes, {lag}{lever})"
    determined = yf.scale_std <= MAX_YAW_SCALE_STD
    method_bias = method + ("" if determined else ", the scale at 1")
    both = combined_bias((fit.offset, yf.bias_std_rps), still[:2], _quantum(sig.yaw)) if still is not None else None
    if both is not None:
        assert still is not None
        method_bias += f", combined with the CAN yaw rate at standstill ({still[2]:.0f} s) by their variances"
    elif still is not None:
        notes.append("the CAN yaw rate at standstill disagrees with the moving fit: the fit's bias is reported")
    value, std = both if both is not None else (fit.offset, yf.bias_std_rps)
    bias = Parameter(math.degrees(value), math.degrees(std), method_bias)
    if yf.lever:
        notes.append(f"the GNSS antenna sits {fit.lever_m:.2f} m ahead of the rear axle (from the course in turns)")
    if determined:
        scale = Parameter(yf.scale, yf.scale_std, method)
    else:
        turning = np.abs(sig.yaw - fit.offset) > TURN_RATE_RPS
        scale = Parameter(
            None,
            None,
            f"not determined: the drive hardly turns (the CAN yaw rate exceeds {math.degrees(TURN_RATE_RPS):g} deg/s "
            f"{100 * float(np.mean(turning)):.0f} % of the time: {yf.scale:.3f} +- {yf.scale_std:.2g})",
        )
    k = abs(yf.scale)
    if determined and not YAW_SCALE_PLAUSIBLE[0] <= k <= YAW_SCALE_PLAUSIBLE[1]:
        notes.append(
            f"the CAN yaw rate reads {1 / k:.3g} x the receiver's azimuth rate: check the signal's unit "
            "(can.signals.yaw_rate.unit; deg/s read as rad/s is 57x)"
        )
    if not abs(yf.scale) > SIGN_SIGMAS * yf.scale_std:
        sign = SignCheck("yaw_rate", None, "the drive turns too little to tell the yaw rate's sign")
    elif yf.scale < 0:
        sign = SignCheck(
            "yaw_rate",
            False,
            f"the CAN yaw rate turns against {yf.source} (left turns must read positive)",
            "set scale = -1 (times the scale it has) in can.signals.yaw_rate",
        )
    else:
        sign = SignCheck("yaw_rate", True, f"the CAN yaw rate turns with {yf.source}")
    return bias, scale, sign


def _relative_delay(sf: _SpeedFit | None, yf: _YawFit | None, notes: list[str]) -> Parameter:
    if sf is None or yf is None or sf.lag_std_s > MAX_LAG_STD_S or yf.lag_std_s > MAX_LAG_STD_S:
        return Parameter(None, None, "not determined: needs both the speed's and the yaw rate's lag")
    delay = yf.fit.lag_s - sf.lag.lag_s
    variance = yf.lag_std_s**2 + sf.lag_std_s**2
    how = f"the yaw rate's lag {yf.fit.lag_s:.3f} s minus the speed's {sf.lag.lag_s:.3f} s"
    if yf.lever and math.isfinite(yf.v_eff_mps):
        k, sigma_k = SIDESLIP_GRADIENT
        delay -= k * yf.v_eff_mps
        variance += (sigma_k * yf.v_eff_mps) ** 2
        how += (
            f", less the sideslip's {k * yf.v_eff_mps:.3f} +- {sigma_k * yf.v_eff_mps:.3f} s at the turns' "
            f"{yf.v_eff_mps:.0f} m/s"
        )
    notes.append(
        "GNSS and CAN observe only how the CAN sensors' ages differ: [sensors.can] delay_s is their common age, "
        "speed_delay_s how much older the speed is"
    )
    return Parameter(delay, math.sqrt(variance), how)


# ---- the config snippet --------------------------------------------------------------------------------------------


def _number(value: float, digits: int) -> str:
    text = f"{value:.{digits}f}"
    return "0.0" if float(text) == 0.0 else text


def _quoted(name: str) -> str:
    return f'"{name}"'


def _spec_toml(spec: SignalSpec, scale: float) -> str:
    """A signal spec as a TOML inline table with ``scale``."""
    if spec.rates:
        parts = [
            f'message = "{spec.message}"',
            f"rates = [{', '.join(map(_quoted, spec.rates))}]",
            f"accelerations = [{', '.join(map(_quoted, spec.accelerations))}]",
        ]
    else:
        parts = [f'signal = "{spec.name}"']
    if spec.channel is not None:
        parts.append(f"channel = {spec.channel}" if spec.channel.isdigit() else f'channel = "{spec.channel}"')
    if spec.valid is not None:
        parts.append(f'valid = "{spec.valid}"')
    if spec.unit is not None:
        parts.append(f'unit = "{spec.unit}"')
    parts.append(f"scale = {scale:.6g}")
    return "{ " + ", ".join(parts) + " }"


def time_offset_key() -> bool:
    """True when the config has ``[sensors.gnss] time_offset_s`` (the estimator's GNSS time offset, which comes
    with its on-line learner); until then the snippet gives it as a comment."""
    return "time_offset_s" in {f.name for f in dataclasses.fields(GnssModel)}


def report_lines(cal: Calibration, sig: DriveSignals) -> list[str]:
    """The human report: one line per parameter (value, standard error, method or reason), the sign checks and the
    notes."""
    digits = {"gps_time_offset_s": 3, "speed_scale": 4, "yaw_rate_bias_dps": 3, "yaw_rate_scale": 4, "can_delay_s": 3}
    lines = [
        f"sumhe calibrate: {sig.span_s:.0f} s of data, {sig.fixes} fixes ({len(sig.t_fix)} valid), "
        f"{len(sig.t_speed)} CAN speeds, {len(sig.t_yaw)} CAN yaw rates"
    ]
    for key, p in cal.parameters().items():
        if p.value is None:
            lines.append(f"{key:18s} = null: {p.method}")
        else:
            d = digits[key]
            sign = "" if key.endswith("scale") else "+"
            std = f"{p.std:.{d}f}" if p.std is not None and math.isfinite(p.std) else "?"
            lines.append(f"{key:18s} = {p.value:{sign}.{d}f} +- {std}: {p.method}")
    for s in cal.signs:
        state = {True: "ok", False: "WRONG SIGN", None: "not checked"}[s.ok]
        lines.append(
            f"sign of the CAN {s.quantity.replace('_', ' ')}: {state}: {s.detail}" + (f"; {s.fix}" if s.fix else "")
        )
    lines += [f"note: {n}" for n in cal.notes]
    return lines


def toml_snippet(cal: Calibration, config: Config) -> str:
    """The calibration as TOML the config accepts: ``[sensors.gnss] time_offset_s``, ``[sensors.can]
    speed_rounding`` (for a coarse quantum) and the mapping's ``scale`` of ``can.signals.speed`` and ``yaw_rate``
    (the found scale folded into the one the mapping has; the sign included); what has no key (the CAN sensors'
    common age, the bias) and what it does not set (``speed_delay_s``: module docstring) as comments."""
    lines: list[str] = []
    offset = cal.gps_time_offset_s
    if offset.value is not None:
        lines.append("[sensors.gnss]")
        entry = f"time_offset_s = {_number(offset.value, 3)}"
        if time_offset_key():
            lines.append(f"{entry}  # +- {offset.std:.3f} s")
        else:
            lines.append(f"# {entry}  (+- {offset.std:.3f} s; the key comes with the estimator's time-offset learner)")
        lines.append("")
    lines += [
        "[sensors.can]",
        f"# delay_s = {cal.delay_s:g} as configured: GNSS and CAN cannot observe the CAN sensors' common age",
    ]
    if cal.can_delay_s.value is not None:
        lines.append(
            f"# the CAN speed's age minus the yaw rate's: {cal.can_delay_s.value:+.3f} +- {cal.can_delay_s.std:.3f} s "
            f"(speed_delay_s = {cal.speed_delay_s:g} as configured; set it where the speed is surely older, an "
            "OBD-II reply's, and the time offset above by as much less)"
        )
    if cal.speed_rounding is not None:
        how = "towards 0: half a step low on the mean" if cal.speed_rounding == "truncate" else "to the nearest step"
        lines.append(f'speed_rounding = "{cal.speed_rounding}"  # the CAN speed\'s whole steps, {how}')
    bias = cal.yaw_rate_bias_dps
    scales = {"speed": cal.speed_factor, "yaw_rate": cal.yaw_rate_scale.value}
    if bias.value is not None:
        folded = bias.value * (scales["yaw_rate"] or 1.0)
        lines.append(
            f"# yaw-rate bias {folded:+.3f} deg/s once the scale below is applied: the estimators' bias state learns "
            f"it (within yaw_rate_bias_max_rps = {config.sensors.can.yaw_rate_bias_max_rps:g} rad/s)"
        )
    mapped = [(q, s) for q, s in scales.items() if s is not None and q in config.can.signals]
    if mapped:
        lines += ["", "[can.signals]"]
        for quantity, found in mapped:
            spec = config.can.signals[quantity]
            lines.append(f"{quantity} = {_spec_toml(spec, spec.scale * found)}")
    return "\n".join(lines) + "\n"
