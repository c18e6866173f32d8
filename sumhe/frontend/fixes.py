"""GNSS fixes in the local frame: :class:`LocalFix` and the datum policy that makes them (:class:`FixConverter`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from sumhe.config import DatumSettings
from sumhe.frontend.measurements import fix_sigmas, sigmas_usable
from sumhe.geo import LocalFrame
from sumhe.messages import GnssFix
from sumhe.records import quick_init
from sumhe.settings import GnssModel


@quick_init
@dataclass(frozen=True, slots=True)
class LocalFix:
    """A GNSS epoch in the local frame. ``t`` is the time of the measurement on the service clock.

    What the receiver said of its accuracy, as it said it: GGA ``quality`` and ``hdop``, GST's 1-sigma errors per
    axis (``gst_sigma_east_m`` from its longitude sigma, ``gst_sigma_north_m`` from its latitude sigma); the
    front-end turns them into the fix's sigma (:func:`~sumhe.frontend.measurements.fix_sigmas`).
    ``course_rad``/``heading_rad`` clockwise from north; ``heading_sigma_rad`` the receiver's 1-sigma of its heading
    where it rates it (:attr:`~sumhe.messages.GnssFix.heading_sigma_rad`).
    """

    t: float
    valid: bool
    east_m: float = math.nan
    north_m: float = math.nan
    up_m: float = 0.0
    quality: int = 0
    hdop: float | None = None
    gst_sigma_east_m: float | None = None
    gst_sigma_north_m: float | None = None
    speed_mps: float | None = None
    course_rad: float | None = None
    heading_rad: float | None = None
    heading_sigma_rad: float | None = None
    fix: GnssFix | None = field(default=None, compare=False, repr=False)
    frame: LocalFrame | None = field(default=None, compare=False, repr=False)

    def sigmas(self, gnss: GnssModel) -> tuple[float, float]:
        """1-sigma position error (east, north), m, by the one policy (:func:`~sumhe.frontend.measurements.
        fix_sigmas`)."""
        return fix_sigmas(self.quality, self.hdop, self.gst_sigma_east_m, self.gst_sigma_north_m, gnss)  # type: ignore[return-value]

    def usable(self, sigmas: tuple[float, float]) -> bool:
        """A fix flagged valid whose position is finite and whose ``sigmas`` (:meth:`sigmas`) are positive and at
        most :data:`~sumhe.frontend.measurements.MAX_FIX_SIGMA_M` (a larger one overflows a filter's variance and
        says the position is unknown anyway)."""
        finite = math.isfinite(self.east_m) and math.isfinite(self.north_m)
        return self.valid and finite and sigmas_usable(*sigmas)


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
            hdop=fix.hdop,
            gst_sigma_east_m=fix.sigma_lon_m,
            gst_sigma_north_m=fix.sigma_lat_m,
            speed_mps=fix.speed_mps,
            course_rad=fix.course_rad,
            heading_rad=fix.heading_rad,
            heading_sigma_rad=fix.heading_sigma_rad,
            fix=fix,
            frame=self.frame,
        )
