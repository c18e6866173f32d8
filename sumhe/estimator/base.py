"""The one interface every estimator answers to (MHE, batch replays, EKF, UKF, particle filter, IMM).

The service, the replay and the benchmark feed samples in time order and collect estimates; they never branch
on which estimator runs. Positions are in the local east/north frame (a :class:`FixConverter` turns
:class:`~sumhe.messages.GnssFix` into :class:`LocalFix` with the datum policy; a
:class:`StateEstimate` becomes a geodetic :class:`~sumhe.messages.Estimate` with :func:`to_estimate`).

Contract of :meth:`Estimator.push`:

* a :class:`LocalFix` (valid or not) is a GNSS epoch: the estimator returns exactly one estimate for it, with
  ``gps`` ``"ok"`` (fix used), ``"rejected"`` (fix failed the gate) or ``"outage"`` (no valid fix);
* a :class:`~sumhe.messages.CanSample` updates the motion inputs; for each ``speed`` sample the estimator returns
  one estimate at the sample's time (the newest state propagated with the newest CAN data), so the output runs at
  CAN rate between GNSS epochs; when GNSS is silent for more than ``1.5`` nominal periods, the estimator itself
  takes the missed epochs as outage epochs (returned as estimates with ``gps="outage"``);
* nothing is returned before the first valid fix ("no fix yet");
* an estimator never raises for bad data in the stream: samples going back in time are dropped and counted.

Offline smoothers (``su-batch``) also provide ``finish() -> list[StateEstimate]``, called once at the end of a
recorded drive; the pipeline calls it where it exists (:meth:`sumhe.service.pipeline.Pipeline.finish`).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from sumhe.config import DatumSettings
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, Estimate, GnssFix, GpsStatus

HDOP_UERE_M = 1.5
"""Receiver range error (m, 1 sigma) assumed when only HDOP describes a fix's accuracy."""
MAX_FIX_SIGMA_M = 1000.0
"""The largest 1-sigma accuracy (m) a usable fix may claim."""


@dataclass(frozen=True, slots=True)
class LocalFix:
    """A GNSS epoch in the local frame. ``t`` is the time of the measurement on the service clock.

    ``sigma_m`` is the receiver's 1-sigma horizontal accuracy (GST, else HDOP x UERE, else None).
    ``course_rad``/``heading_rad`` clockwise from north.
    """

    t: float
    valid: bool
    east_m: float = math.nan
    north_m: float = math.nan
    up_m: float = 0.0
    quality: int = 0
    sigma_m: float | None = None
    speed_mps: float | None = None
    course_rad: float | None = None
    heading_rad: float | None = None
    fix: GnssFix | None = field(default=None, compare=False, repr=False)
    frame: LocalFrame | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True, slots=True)
class StateEstimate:
    """An estimator's answer in the local frame: east/north (m), azimuth (rad, clockwise from north),
    speed (m/s), yaw rate (rad/s, anticlockwise). ``bound_*`` are half-widths of the set of positions
    consistent with model and data, where the estimator knows them."""

    t: float
    east_m: float
    north_m: float
    azimuth_rad: float
    speed_mps: float
    yaw_rate_rps: float
    gps: GpsStatus
    mode: str
    window: int = 0
    solve_ms: float = 0.0
    bound_east_m: float | None = None
    bound_north_m: float | None = None


@runtime_checkable
class Estimator(Protocol):
    """What the service, replay and benchmark call. See the module docstring for the contract of ``push``."""

    name: str

    def reset(self) -> None:
        """Forget everything (a clock jump or a new drive); the next valid fix starts over."""

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        """Feed one sample (time-ordered); returns the estimates it produced."""

    def stats(self) -> Mapping[str, float | int | str]:
        """Counters and figures for the status line (e.g. solves, failures, rejected fixes, window)."""


def bad_epoch_time(t: object, last_epoch: float | None) -> tuple[str, str, tuple[float, ...]] | None:
    """Why a GNSS epoch at ``t`` cannot be taken, as (counter, log message, message args), or None when it can:
    a non-finite time, or a time not after the previous epoch's."""
    if not (isinstance(t, int | float) and math.isfinite(t)):
        return "bad_samples", "GNSS epoch with a non-finite time", ()
    if last_epoch is not None and t <= last_epoch:
        return "dropped_backwards", "GNSS epoch %.3f s back in time dropped", (last_epoch - t,)
    return None


def has_usable_position(fix: LocalFix) -> bool:
    """A fix flagged valid whose position is finite and whose sigma, if given, is positive and at most
    ``MAX_FIX_SIGMA_M`` (a larger one overflows a filter's variance and says the position is unknown anyway)."""
    sigma_ok = fix.sigma_m is None or 0 < fix.sigma_m <= MAX_FIX_SIGMA_M
    return fix.valid and math.isfinite(fix.east_m) and math.isfinite(fix.north_m) and sigma_ok


class BadInputCounter:
    """What the streaming estimators share about bad input: ``_count`` counts an event in ``_counts`` (their
    ``stats()``) and logs it, on the estimator's module logger, at its 1st, 10th, 100th, ... occurrence;
    ``_usable`` says whether a fix's position can be used, counting a valid fix without one (taken as no fix)."""

    name: str
    _counts: Counter[str]

    def _count(self, key: str, msg: str, *args: object) -> None:
        self._counts[key] += 1
        n = self._counts[key]
        if n == 10 ** int(math.log10(n)):
            logging.getLogger(type(self).__module__).warning("%s: " + msg + " (%d so far)", self.name, *args, n)

    def _usable(self, fix: LocalFix) -> bool:
        if has_usable_position(fix) or not fix.valid:
            return fix.valid
        self._count("bad_fixes", "valid fix without a usable position or sigma taken as no fix")
        return False


def fix_sigma_m(fix: GnssFix) -> float | None:
    """The receiver's own 1-sigma horizontal accuracy (m): GST lat/lon sigmas, else HDOP x UERE."""
    if fix.sigma_lat_m is not None and fix.sigma_lon_m is not None:
        return math.hypot(fix.sigma_lat_m, fix.sigma_lon_m) / math.sqrt(2.0)
    if fix.hdop is not None:
        return fix.hdop * HDOP_UERE_M
    return None


class FixConverter:
    """GnssFix (``t`` already its measurement time, see :mod:`sumhe.io.fixtime`) -> LocalFix in the local frame,
    with the datum policy (first valid fix, or fixed)."""

    def __init__(self, datum: DatumSettings) -> None:
        self.frame: LocalFrame | None = None
        if datum.mode == "fixed":
            assert datum.lat is not None and datum.lon is not None  # validated by DatumSettings
            self.frame = LocalFrame(datum.lat, datum.lon, datum.alt)

    def convert(self, fix: GnssFix) -> LocalFix:
        """The fix in the local frame; the first valid fix sets the datum when none is fixed."""
        t = fix.t
        has_position = fix.valid and fix.lat_deg is not None and fix.lon_deg is not None
        if not has_position:
            return LocalFix(t=t, valid=False, quality=fix.quality, fix=fix)
        assert fix.lat_deg is not None and fix.lon_deg is not None
        alt = fix.alt_m if fix.alt_m is not None else 0.0
        if self.frame is None:
            self.frame = LocalFrame(fix.lat_deg, fix.lon_deg, alt)
        east, north, up = self.frame.to_enu(fix.lat_deg, fix.lon_deg, alt)
        return LocalFix(
            t=t,
            valid=True,
            east_m=float(east),
            north_m=float(north),
            up_m=float(up),
            quality=fix.quality,
            sigma_m=fix_sigma_m(fix),
            speed_mps=fix.speed_mps,
            course_rad=fix.course_rad,
            heading_rad=fix.heading_rad,
            fix=fix,
            frame=self.frame,
        )


def to_estimate(state: StateEstimate, frame: LocalFrame, up_m: float = 0.0) -> Estimate:
    """A local-frame estimate as the sinks send it (with WGS84 latitude, longitude and height)."""
    lat, lon, alt = frame.to_geodetic(state.east_m, state.north_m, up_m)
    return Estimate(
        t=state.t,
        east_m=state.east_m,
        north_m=state.north_m,
        lat_deg=float(lat),
        lon_deg=float(lon),
        alt_m=float(alt),
        track_rad=state.azimuth_rad % (2.0 * math.pi),
        speed_mps=state.speed_mps,
        yaw_rate_rps=state.yaw_rate_rps,
        gps=state.gps,
        mode=state.mode,
        window=state.window,
        solve_ms=state.solve_ms,
        bound_east_m=state.bound_east_m,
        bound_north_m=state.bound_north_m,
    )
