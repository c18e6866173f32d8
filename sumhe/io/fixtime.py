"""When a GNSS fix's position was measured, on the service clock (see :class:`sumhe.config.GpsSettings`)."""

from __future__ import annotations

import dataclasses

from sumhe.config import GpsSettings
from sumhe.messages import GnssFix


def fix_time(fix: GnssFix, gps: GpsSettings) -> float:
    """The UTC time of fix when allowed and plausible (within ``max_clock_offset_s`` of the receive time
    ``fix.t``), else the receive time minus the receiver latency (s)."""
    if gps.time == "utc" and fix.time_utc is not None:
        utc = fix.time_utc.timestamp()
        if abs(fix.t - utc) <= gps.max_clock_offset_s:
            return utc
    return fix.t - gps.latency_s


def stamp_fix(fix: GnssFix, gps: GpsSettings) -> GnssFix:
    """The fix with ``t`` moved from its receive time to its measurement time (done once, where fixes enter)."""
    return dataclasses.replace(fix, t=fix_time(fix, gps))
