"""GNSS fixes from CAN frames (``[gps] source = "can"``): the GNSS quantities of one epoch assembled into one fix.

A receiver or logger on CAN sends an epoch as several frames (position, time, speed, attitude, ...), usually in
a burst of a few milliseconds once per epoch. :class:`CanDecoder <sumhe.io.can.CanDecoder>` decodes the mapped
signals (``gps.signals``) and hands each frame's values here, message by message. No I/O, no clock: the time is
the frames' timestamps.

Epochs (``M`` = the messages that carry a mapped GNSS quantity):

* the first frame of a message of ``M`` opens an epoch;
* a frame of a message the open epoch already holds, or any frame (GNSS or not, :meth:`GnssAssembler.tick`)
  more than ``span_s`` after the epoch opened, closes the open epoch first;
* when the epoch holds every message of ``M`` it is complete and closes at once (no added latency);
* :meth:`GnssAssembler.flush` closes it at the end of the input.

A closed epoch becomes a :class:`~sumhe.messages.GnssFix` if it holds the message carrying ``lat``; the fix's
``t`` is that frame's timestamp (its receive time on the frame clock; :func:`~sumhe.io.fixtime.stamp_fix` then
applies ``gps.time`` and ``gps.latency_s``, as for NMEA). An epoch without it is dropped (``no_position``); an
epoch closed before every message of ``M`` arrived is counted ``incomplete`` (its fix lacks their quantities).

Validity and values: the fix is valid when it has ``lat`` and ``lon`` within range and not flagged invalid (a
mapping's ``valid`` flag signal decoded as 0: the decoder passes None). As for NMEA, an invalid fix carries no
position, speed, course or heading. A value out of range (latitude beyond +-90 deg, longitude beyond +-180 deg,
accuracy or heading accuracy not positive, a negative speed or satellite count, a time not after 1970, anything not
finite) is left out and counted (``bad_values``); ``course``/``heading`` are wrapped to [0, 2 pi). ``accuracy``
(horizontal, 1 sigma) becomes both ``sigma_lat_m`` and ``sigma_lon_m``; ``heading_accuracy`` (1 sigma) the fix's
``heading_sigma_rad``, with a heading only.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from sumhe.messages import GnssFix

log = logging.getLogger(__name__)

TALKER = "CAN"
"""``GnssFix.talker`` of fixes decoded from CAN frames."""

_RANGES: Mapping[str, tuple[float, float]] = {
    "lat": (-90.0, 90.0),
    "lon": (-180.0, 180.0),
    "speed": (0.0, math.inf),
    "sats": (0.0, math.inf),
    "time": (0.0, math.inf),
}
"""Closed ranges of the quantities that have one; ``accuracy`` must be positive, every value finite."""


def checked_value(quantity: str, value: float) -> float | None:
    """``value`` of a GNSS quantity as the fix holds it, or None when it is out of range (module docstring)."""
    if not math.isfinite(value):
        return None
    if quantity in ("accuracy", "heading_accuracy"):
        return value if value > 0.0 else None
    if quantity in ("course", "heading"):
        return value % (2.0 * math.pi)
    lo, hi = _RANGES.get(quantity, (-math.inf, math.inf))
    return value if lo <= value <= hi else None


@dataclass
class GnssStats:
    """Counters of one assembler: fixes emitted (``valid_fixes`` of them valid), epochs closed before every
    message arrived, epochs dropped for lacking the position message, values left out as out of range."""

    fixes: int = 0
    valid_fixes: int = 0
    incomplete: int = 0
    no_position: int = 0
    bad_values: int = 0


class GnssAssembler:
    """Assembles the GNSS values of CAN frames into one fix per epoch (see the module docstring).

    ``messages`` are the names of the messages carrying mapped GNSS quantities, ``position`` the one carrying
    ``lat``; ``span_s`` (s) how long after its first frame an epoch may still take frames.
    """

    def __init__(self, messages: Iterable[str], position: str, span_s: float) -> None:
        self.messages = frozenset(messages)
        if position not in self.messages:
            raise ValueError(f"position: {position!r} is not among the messages {sorted(self.messages)}")
        if not span_s > 0.0:
            raise ValueError("span_s: must be positive")
        self.position = position
        self.span_s = span_s
        self.stats = GnssStats()
        self._start = math.nan
        self._t_position = math.nan
        self._held: set[str] = set()
        self._values: dict[str, float | None] = {}

    def add(self, t: float, message: str, values: Mapping[str, float | None]) -> list[GnssFix]:
        """One frame of ``message`` at ``t`` (s) with its GNSS values (None: flagged invalid); the fixes of the
        epochs it closes (none, the previous one, this one, or both)."""
        out = self.tick(t)
        if message in self._held:
            out.extend(self._close())
        if not self._held:
            self._start = t
        self._held.add(message)
        if message == self.position:
            self._t_position = t
        for quantity, value in values.items():
            self._values[quantity] = value if value is None else self._checked(quantity, value)
        if self._held == self.messages:
            out.extend(self._close())
        return out

    def tick(self, t: float) -> list[GnssFix]:
        """Time has reached ``t`` (s; any frame): the open epoch's fix if that closes it (``span_s`` passed)."""
        if self._held and t - self._start > self.span_s:
            return self._close()
        return []

    def flush(self) -> list[GnssFix]:
        """The end of the input: the open epoch's fix, if any."""
        return self._close() if self._held else []

    def _checked(self, quantity: str, value: float) -> float | None:
        checked = checked_value(quantity, value)
        if checked is None:
            self.stats.bad_values += 1
            log.debug("GNSS %s = %r out of range: left out", quantity, value)
        return checked

    def _close(self) -> list[GnssFix]:
        held, values, t = self._held, self._values, self._t_position
        self._held, self._values, self._t_position = set(), {}, math.nan
        if held != self.messages:
            self.stats.incomplete += 1
        if self.position not in held:
            self.stats.no_position += 1
            return []
        fix = to_fix(t, values)
        self.stats.fixes += 1
        self.stats.valid_fixes += fix.valid
        return [fix]


def to_fix(t: float, values: Mapping[str, float | None]) -> GnssFix:
    """The fix of one epoch's checked values (None or absent: not known) received at ``t`` (s)."""
    lat, lon = values.get("lat"), values.get("lon")
    valid = lat is not None and lon is not None
    utc = values.get("time")
    sats = values.get("sats")

    def if_valid(quantity: str) -> float | None:
        return values.get(quantity) if valid else None

    sigma = if_valid("accuracy")
    heading = if_valid("heading")

    return GnssFix(
        t=t,
        time_utc=dt.datetime.fromtimestamp(utc, dt.timezone.utc) if utc is not None else None,
        lat_deg=lat if valid else None,
        lon_deg=lon if valid else None,
        alt_m=if_valid("alt"),
        quality=1 if valid else 0,
        valid=valid,
        sats=round(sats) if sats is not None else None,
        speed_mps=if_valid("speed"),
        course_rad=if_valid("course"),
        heading_rad=heading,
        sigma_lat_m=sigma,
        sigma_lon_m=sigma,
        talker=TALKER,
        heading_sigma_rad=if_valid("heading_accuracy") if heading is not None else None,
    )
