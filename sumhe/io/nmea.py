"""NMEA-0183 decoding: sentences of any talker assembled into one :class:`GnssFix` per epoch.

pynmea2 parses and checks each sentence; this module decides what a stream of sentences means. The decoder
does no I/O (serial ports, replay and tests all feed it lines); only :func:`iter_fixes` opens a file.

Lines. A line may carry a receive-time prefix ``(1700000000.123) $GPGGA,...`` (our log format, like
``candump -L``); that time becomes the fix's ``t``. ``#`` lines are comments. A line is split at every ``$``
and ``!``, so binary packets, ``$$`` prefixes and sentences that collided on one line cost only the broken
piece. Each piece ("fragment") is counted exactly once in :class:`NmeaCounters`: a good ``sentence``
(``unknown`` when we do not use its type: GSV, GBS, TXT, proprietary, AIS; not an error), a
``checksum_error`` (bad or missing ``*hh``: a truncated sentence usually lands here) or ``garbled``
(binary, non-ASCII, unparseable, a field that is not a number or out of range). A bad piece is dropped whole.

Epochs. GGA, RMC, GNS, GLL, GST and ZDA carry the UTC time of fix; all sentences with the same time form one
epoch. VTG, HDT, THS and GSA carry no time and belong to the epoch being assembled (a timeless sentence
that comes first opens an epoch that the next timed sentence names). An epoch ends when a sentence with
another time arrives, when its *cycle ender* arrives, on :meth:`NmeaDecoder.close_epoch` (the caller saw
an idle gap on a live port) and on :meth:`NmeaDecoder.flush` (end of input). The cycle ender is learned as
gpsd does: when two consecutive epochs that ended on a time change had the same last used sentence
(e.g. the 3rd GNGSA), that sentence ends the following epochs at once, which saves one epoch of latency.
A sentence that arrives for an epoch already emitted is ``late``: it is dropped and the ender unlearned.
Only epochs with a fix sentence (GGA, GNS, RMC, GLL) become fixes; a ZDA- or GST-only epoch still sets the date.

Values. Each quantity comes from the best sentence that has it: GGA/GNS/RMC/GLL before VTG/GSA; then talker
GN (combined solution) before GP before single constellations (GL, GA, GB, BD, QZ, ...); then GGA before
GNS before RMC before GLL. So a receiver sending GPGGA and GNGGA (or GNGNS) of one epoch reports the GN values.
Altitude is GGA/GNS altitude above mean sea level (geoid separation not applied).

Validity ("invalid wins"). Per fix sentence type (GGA, GNS, RMC, GLL) the sentence of the best talker
gives a verdict: GGA quality 1..5; RMC and GLL status A with a mode indicator (if any) of quality 1..5;
GNS any constellation mode A/D/P/R/F. A GGA or GNS claiming a fix from 0 satellites is no fix (as gpsd
says). Quality 6 (dead reckoning), 7 (manual) and 8 (simulator) are not GNSS measurements and not valid.
If any verdict says no fix, or there is no position, the fix has ``valid=False`` and no latitude,
longitude or altitude, so it can never be used as a position. Sentences
that report no fix contribute no position, speed or course.

Plausibility. A value outside what a GNSS receiver can report (:data:`LIMITS`: speed above the 1000 kn export
limit, altitude outside [-1 km, 18 km], DOP above 100, ...) is counted ``implausible`` and ignored: that field is
dropped as if it were empty, the rest of the sentence is used (a position is range-checked already: a bad one makes
the sentence ``garbled``). A date (RMC or ZDA) more than :data:`MAX_DATE_OFFSET_S` from both the line's receive
time and the previous epoch's time (before any: ahead of the host clock by more) is ``implausible`` too: the epoch
takes its date as if the sentence had none, until :data:`RESYNC_AFTER` epochs in a row bring such dates (the
receiver's date really changed). The first of each kind is logged as a warning, the rest at debug level.

Time. ``time_utc`` is the epoch's time of day on a date from RMC or ZDA; once a date is known, later
epochs take the date nearest to the previous epoch, which rolls over at midnight. Before any date is
known the decoder uses the ``date`` it was given; without one, a fix with a receive time is emitted with
``time_utc=None`` (its ``t`` is the receive time), and a fix without one is held (at most ``MAX_HELD``
epochs) until a date arrives, or dropped as ``undated`` at the end of the input. An epoch whose UTC time
is not after the last emitted one is dropped as ``backwards``, unless ``RESYNC_AFTER`` such epochs come in
a row (the receiver's clock really jumped back), when the decoder follows the new time.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import functools
import logging
import math
import os
import re
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field

import pynmea2
import pynmea2.nmea_utils

from sumhe.errors import DecodeError, SourceError
from sumhe.messages import GnssFix

log = logging.getLogger(__name__)

KNOT_MPS = 1852.0 / 3600.0
"""One knot in m/s."""
KMH_MPS = 1.0 / 3.6
"""One km/h in m/s."""
MAX_HELD = 64
"""Epochs held while waiting for a date (no receive time, no date yet)."""
RESYNC_AFTER = 3
"""Consecutive backwards epochs after which the decoder follows the receiver's new time."""

LIMITS: Mapping[str, tuple[float, float]] = {
    "speed_mps": (0.0, 1000.0 * KNOT_MPS),
    "alt_m": (-1000.0, 18000.0),
    "hdop": (0.0, 100.0),
    "sats": (0, 255),
    "sigma_lat_m": (0.0, 1e6),
    "sigma_lon_m": (0.0, 1e6),
    "sigma_alt_m": (0.0, 1e6),
}
"""Physical limits [low, high] of the values a GNSS receiver reports (the COCOM limits of 1000 kn and 18 km bound
what any civil receiver outputs); a value outside is ignored and counted ``implausible``."""
MAX_DATE_OFFSET_S = 86400.0
"""A date of fix further than this from the previous epoch (or ahead of the host clock) is not believed (s)."""

GOOD_QUALITY = range(1, 6)
"""GGA fix qualities that are GNSS positions: GPS, DGPS, PPS, RTK fixed, RTK float."""
MODE_QUALITY: Mapping[str, int] = {"N": 0, "A": 1, "D": 2, "P": 3, "R": 4, "F": 5, "E": 6, "M": 7, "S": 8}
"""RMC/GNS/VTG mode indicator -> the GGA quality it means."""

_TALKER_RANK: Mapping[str, int] = {"GN": 3, "GP": 2}
_KIND_RANK: Mapping[str, int] = {"GGA": 4, "GNS": 3, "RMC": 2, "GLL": 1}
_FIX_KINDS = frozenset(_KIND_RANK)
_DAY = dt.timedelta(days=1)
_RX_PREFIX = re.compile(r"\((\d{1,12}(?:\.\d{0,9})?)\)\s?")
_FRAGMENT_START = re.compile(r"(?=[$!])")
_BAD_FIELD_ERRORS = (ValueError, TypeError, ArithmeticError, AttributeError, IndexError)
_BLANK = "\x00 \t\r\n\x0b\x0c"

if "THS" not in pynmea2.TalkerSentence.sentence_types:

    class THS(pynmea2.TalkerSentence):
        """True heading and status (NMEA 4.x; not in pynmea2 1.19). Subclassing registers it with pynmea2."""

        fields = (("True heading", "heading", float), ("Mode indicator", "mode_indicator"))


@dataclass
class NmeaCounters:
    """What a decoder has seen. ``fragments == sentences + checksum_errors + garbled`` always holds."""

    lines: int = 0
    comments: int = 0
    fragments: int = 0
    sentences: int = 0
    unknown: int = 0
    checksum_errors: int = 0
    garbled: int = 0
    late: int = 0
    fixes: int = 0
    no_fix: int = 0
    backwards: int = 0
    undated: int = 0
    implausible: int = 0
    rebases: int = 0
    """Jumps of a log's receive clock re-based (:func:`rebase_receive_times`)."""

    def summary(self) -> str:
        """One line ``name=value ...`` of every counter."""
        return " ".join(f"{f.name}={getattr(self, f.name)}" for f in dataclasses.fields(self))


@dataclass(frozen=True, slots=True)
class _Part:
    """What one sentence says about its epoch. ``fix`` is None for sentences that say nothing about it."""

    kind: str
    talker: str
    tod: dt.time | None = None
    date: dt.date | None = None
    fix: bool | None = None
    values: Mapping[str, float | int] = field(default_factory=dict)

    @property
    def key(self) -> str:
        return self.talker + self.kind

    @property
    def rank(self) -> tuple[int, int, int]:
        return (self.kind in _FIX_KINDS, _TALKER_RANK.get(self.talker, 1), _KIND_RANK.get(self.kind, 0))


def _number(value: object, name: str) -> float | None:
    """A finite float from a pynmea2 field (None when empty; pynmea2 hands back raw text it failed to convert)."""
    if value is None or value == "":
        return None
    x = float(value)  # type: ignore[arg-type]  # raises ValueError/TypeError on text: the sentence is garbled
    if not math.isfinite(x):
        raise DecodeError(f"{name}: not finite: {value!r}")
    return x


def _non_negative(value: object, name: str) -> float | None:
    x = _number(value, name)
    if x is not None and x < 0.0:
        raise DecodeError(f"{name}: negative: {value!r}")
    return x


def _count(value: object, name: str) -> int | None:
    if value is None or value == "":
        return None
    n = int(value)  # type: ignore[call-overload]
    if n < 0:
        raise DecodeError(f"{name}: negative: {value!r}")
    return n


def _angle_rad(value: object, name: str) -> float | None:
    """Degrees clockwise from north -> radians in [0, 2 pi)."""
    deg = _number(value, name)
    if deg is None:
        return None
    deg %= 360.0
    return 0.0 if deg == 360.0 else math.radians(deg)  # a tiny negative angle wraps to 360.0 in floating point


def _text(msg: pynmea2.TalkerSentence, name: str) -> str:
    """The text of the field ``name`` ("" when empty or missing): what pynmea2's attribute converts, for the fields
    whose conversion (float, int, none) :func:`_number` and :func:`_count` redo with the same result and errors (an
    attribute is an ``__getattr__`` call that converts; the text is an index). VTG and HDT (Decimal fields) and ZDA
    (int fields used as they come) keep the attributes."""
    i = type(msg).name_to_idx[name]
    data = msg.data
    return data[i] if i < len(data) else ""


def _tod(msg: pynmea2.TalkerSentence) -> dt.time | None:
    """The time of fix, parsed through a cache (the sentences of an epoch share it: 2 us a parse)."""
    text = _text(msg, "timestamp")
    value = _converted(pynmea2.nmea_utils.timestamp, text) if text else None
    if value is None:
        return None
    if not isinstance(value, dt.time):
        raise DecodeError(f"time: not hhmmss.ss: {value!r}")
    return value


@functools.lru_cache(maxsize=32)
def _converted(convert: Callable[[str], object], text: str) -> object:
    """pynmea2's ``convert`` (``nmea_utils.timestamp`` or ``datestamp``) of a field's text, the text itself where
    it fails (as pynmea2 gives it back); cached, as an epoch's sentences share the time and a day's fixes the date."""
    try:
        return convert(text)
    except Exception:  # pynmea2 gives the field's text back for any failure
        return text


def _position(msg: pynmea2.TalkerSentence) -> tuple[float, float] | None:
    """(lat, lon) in degrees, None when both are empty; pynmea2 converts (``dm_to_sd``, signed by the hemisphere as
    its ``latitude`` and ``longitude`` do), we check directions and ranges. Each field is read once, as text
    (pynmea2's properties read them again: 10 reads a sentence)."""
    lat_dm, lon_dm = _text(msg, "lat"), _text(msg, "lon")
    lat_dir, lon_dir = _text(msg, "lat_dir"), _text(msg, "lon_dir")
    if not lat_dm and not lon_dm:
        return None
    if lat_dir not in ("N", "S") or lon_dir not in ("E", "W"):
        raise DecodeError(f"position: bad hemisphere {lat_dir!r}/{lon_dir!r}")
    for raw in (lat_dm, lon_dm):
        if divmod(float(raw), 100.0)[1] >= 60.0:
            raise DecodeError(f"position: minutes >= 60 in {raw!r}")
    lat, lon = pynmea2.nmea_utils.dm_to_sd(lat_dm), pynmea2.nmea_utils.dm_to_sd(lon_dm)
    lat, lon = (lat if lat_dir == "N" else -lat), (lon if lon_dir == "E" else -lon)
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise DecodeError(f"position: out of range: {lat}, {lon}")
    return lat, lon


def _fix_values(fix: bool, pos: tuple[float, float] | None, **values: float | int | None) -> dict[str, float | int]:
    """The values a sentence contributes: position and motion only when it reports a fix."""
    out = {k: v for k, v in values.items() if v is not None}
    if not fix:
        for k in ("alt_m", "speed_mps", "course_rad"):
            out.pop(k, None)
    elif pos is not None:
        out["lat_deg"], out["lon_deg"] = pos
    return out


def _gga(msg: pynmea2.TalkerSentence) -> _Part:
    quality = _count(_text(msg, "gps_qual"), "quality") or 0
    pos = _position(msg)
    sats = _count(_text(msg, "num_sats"), "sats")
    fix = quality in GOOD_QUALITY and pos is not None and sats != 0
    values = _fix_values(
        fix,
        pos,
        quality=quality,
        alt_m=_number(_text(msg, "altitude"), "altitude"),
        sats=sats,
        hdop=_non_negative(_text(msg, "horizontal_dil"), "hdop"),
    )
    return _Part("GGA", msg.talker, _tod(msg), fix=fix, values=values)


def _gns(msg: pynmea2.TalkerSentence) -> _Part:
    qualities = [MODE_QUALITY[c] for c in _text(msg, "mode_indicator") if c in MODE_QUALITY]
    good = [q for q in qualities if q in GOOD_QUALITY]
    quality = max(good) if good else max(qualities, default=0)
    pos = _position(msg)
    sats = _count(_text(msg, "num_sats"), "sats")
    fix = bool(good) and pos is not None and sats != 0
    values = _fix_values(
        fix,
        pos,
        quality=quality,
        alt_m=_number(_text(msg, "altitude"), "altitude"),
        sats=sats,
        hdop=_non_negative(_text(msg, "hdop"), "hdop"),
    )
    return _Part("GNS", msg.talker, _tod(msg), fix=fix, values=values)


def _rmc(msg: pynmea2.TalkerSentence) -> _Part:
    status = _text(msg, "status")
    quality = MODE_QUALITY.get(_text(msg, "mode_indicator"), 1) if status == "A" else 0
    pos = _position(msg)
    fix = quality in GOOD_QUALITY and pos is not None
    speed_kn = _non_negative(_text(msg, "spd_over_grnd"), "speed")
    date = _datestamp(msg)
    if date is not None and not isinstance(date, dt.date):
        raise DecodeError(f"date: not ddmmyy: {date!r}")
    values = _fix_values(
        fix,
        pos,
        quality=quality,
        speed_mps=None if speed_kn is None else speed_kn * KNOT_MPS,
        course_rad=_angle_rad(_text(msg, "true_course"), "course"),
    )
    return _Part("RMC", msg.talker, _tod(msg), date=date, fix=fix, values=values)


def _datestamp(msg: pynmea2.TalkerSentence) -> object:
    """``msg.datestamp`` (pynmea2's: None for an empty field, the text where it is not a date), through a cache
    (the date repeats for every fix of a day, and ``strptime`` was a tenth of the NMEA decoding)."""
    text = _text(msg, "datestamp")
    return _converted(pynmea2.nmea_utils.datestamp, text) if text else None


def _gll(msg: pynmea2.TalkerSentence) -> _Part:
    quality = MODE_QUALITY.get(_text(msg, "faa_mode"), 1) if _text(msg, "status") == "A" else 0
    pos = _position(msg)
    fix = quality in GOOD_QUALITY and pos is not None
    return _Part("GLL", msg.talker, _tod(msg), fix=fix, values=_fix_values(fix, pos, quality=quality))


def _vtg(msg: pynmea2.TalkerSentence) -> _Part:
    knots = _non_negative(msg.spd_over_grnd_kts, "speed")
    kmh = _non_negative(msg.spd_over_grnd_kmph, "speed")
    course = _angle_rad(msg.true_track, "course")
    if msg.faa_mode == "N":
        return _Part("VTG", msg.talker)
    speed = knots * KNOT_MPS if knots is not None else None if kmh is None else kmh * KMH_MPS
    values = {k: v for k, v in (("speed_mps", speed), ("course_rad", course)) if v is not None}
    return _Part("VTG", msg.talker, values=values)


def _hdt(msg: pynmea2.TalkerSentence) -> _Part:
    heading = _angle_rad(msg.heading, "heading")
    return _Part("HDT", msg.talker, values={} if heading is None else {"heading_rad": heading})


def _ths(msg: pynmea2.TalkerSentence) -> _Part:
    heading = _angle_rad(_text(msg, "heading"), "heading")
    usable = heading is not None and _text(msg, "mode_indicator") != "V"
    return _Part("THS", msg.talker, values={"heading_rad": heading} if usable else {})


def _gsa(msg: pynmea2.TalkerSentence) -> _Part:
    hdop = _non_negative(_text(msg, "hdop"), "hdop")
    return _Part("GSA", msg.talker, values={} if hdop is None else {"hdop": hdop})


def _gst(msg: pynmea2.TalkerSentence) -> _Part:
    sigmas = {
        "sigma_lat_m": _non_negative(_text(msg, "std_dev_latitude"), "sigma_lat"),
        "sigma_lon_m": _non_negative(_text(msg, "std_dev_longitude"), "sigma_lon"),
        "sigma_alt_m": _non_negative(_text(msg, "std_dev_altitude"), "sigma_alt"),
    }
    return _Part("GST", msg.talker, _tod(msg), values={k: v for k, v in sigmas.items() if v is not None})


def _zda(msg: pynmea2.TalkerSentence) -> _Part:
    ymd = (msg.year, msg.month, msg.day)
    date = None if None in ymd else dt.date(*ymd)
    if date is not None and not 1980 <= date.year <= 2200:
        raise DecodeError(f"date: year out of range: {date.year}")
    return _Part("ZDA", msg.talker, _tod(msg), date=date)


_EXTRACTORS: Mapping[str, Callable[[pynmea2.TalkerSentence], _Part]] = {
    "GGA": _gga,
    "GNS": _gns,
    "RMC": _rmc,
    "GLL": _gll,
    "VTG": _vtg,
    "HDT": _hdt,
    "THS": _ths,
    "GSA": _gsa,
    "GST": _gst,
    "ZDA": _zda,
}


class _Epoch:
    """The sentences of one UTC time of fix, in arrival order."""

    __slots__ = ("counts", "last", "parts", "rx", "tod")

    def __init__(self) -> None:
        self.tod: dt.time | None = None
        self.rx: float | None = None
        self.parts: list[_Part] = []
        self.counts: dict[str, int] = {}
        self.last: tuple[str, int] | None = None

    def add(self, part: _Part, rx: float | None) -> None:
        if self.tod is None:
            self.tod = part.tod
        if self.rx is None:
            self.rx = rx
        self.parts.append(part)
        n = self.counts[part.key] = self.counts.get(part.key, 0) + 1
        self.last = (part.key, n)


def _nearest_day(ref: dt.datetime, tod: dt.time) -> dt.datetime:
    """``tod`` on the day (ref's, the one before or after) that puts it nearest to ``ref``."""
    base = dt.datetime.combine(ref.date(), tod)
    return min((base - _DAY, base, base + _DAY), key=lambda c: abs(c - ref))


def _utc(date: dt.date, tod: dt.time) -> dt.datetime:
    return dt.datetime.combine(date, tod.replace(tzinfo=dt.timezone.utc))


def _assemble(parts: Iterable[_Part], t: float, time_utc: dt.datetime | None) -> GnssFix:
    """One fix from the parts of one epoch (rules in the module docstring)."""
    best: dict[str, tuple[tuple[int, int, int], float | int, _Part]] = {}
    verdicts: dict[str, _Part] = {}
    for p in parts:
        rank = p.rank
        for name, value in p.values.items():
            if name not in best or rank > best[name][0]:
                best[name] = (rank, value, p)
        if p.fix is not None and (p.kind not in verdicts or rank > verdicts[p.kind].rank):
            verdicts[p.kind] = p
    valid = bool(verdicts) and all(p.fix for p in verdicts.values()) and "lat_deg" in best

    def get(name: str) -> float | None:
        return float(best[name][1]) if name in best else None

    def count(name: str) -> int | None:
        return int(best[name][1]) if name in best else None

    quality = count("quality") or 0
    if not valid and quality in GOOD_QUALITY:
        quality = 0
    source = best["lat_deg"][2] if valid else max(verdicts.values(), key=lambda p: p.rank, default=None)
    return GnssFix(
        t=t,
        time_utc=time_utc,
        lat_deg=get("lat_deg") if valid else None,
        lon_deg=get("lon_deg") if valid else None,
        alt_m=get("alt_m") if valid else None,
        quality=quality,
        valid=valid,
        sats=count("sats"),
        hdop=get("hdop"),
        speed_mps=get("speed_mps"),
        course_rad=get("course_rad"),
        heading_rad=get("heading_rad"),
        sigma_lat_m=get("sigma_lat_m"),
        sigma_lon_m=get("sigma_lon_m"),
        sigma_alt_m=get("sigma_alt_m"),
        talker=source.talker if source is not None else "",
    )


class NmeaDecoder:
    """Stateful NMEA decoder: ``feed`` lines, get :class:`GnssFix` es; ``flush`` at the end of the input.

    ``date`` is the UTC date assumed until the input supplies one (RMC or ZDA). Not thread-safe.
    """

    def __init__(self, date: dt.date | None = None) -> None:
        self.date = date
        self.counters = NmeaCounters()
        self._open: _Epoch | None = None
        self._closed_by_ender = False
        self._last_tod: dt.time | None = None
        self._ender: tuple[str, int] | None = None
        self._ender_seen: tuple[str, int] | None = None
        self._ref: dt.datetime | None = None
        self._input_dated = False
        """Whether a date has come from the input (not only the ``date`` given): then dates are judged against it."""
        self._last_when: dt.datetime | None = None
        self._behind = 0
        self._odd_dates = 0
        self._held: deque[_Epoch] = deque()
        self._warned: set[str] = set()

    def feed(self, line: bytes | str, t: float | None = None) -> list[GnssFix]:
        """Decode one line (or several, split at CR/LF); return the fixes of the epochs it completed.

        ``t`` is the receive time (s); it overrides a ``(t)`` prefix on the line.
        """
        text = line.decode("latin-1") if isinstance(line, bytes | bytearray) else line
        out: list[GnssFix] = []
        for row in text.splitlines():
            out.extend(self._feed_row(row, t))
        return out

    @property
    def assembling(self) -> bool:
        """Whether an epoch is being assembled: lines of it fed, its fix not yet emitted."""
        return self._open is not None

    def close_epoch(self) -> list[GnssFix]:
        """The epoch being assembled is complete (e.g. the port has been idle): emit it."""
        return self._close(ender=False)

    def flush(self) -> list[GnssFix]:
        """End of input: emit the open epoch; fixes still waiting for a date are dropped as ``undated``."""
        out = self._close(ender=False)
        if self._held:
            self.counters.undated += len(self._held)
            log.warning("%d fixes dropped: no date in the input (RMC or ZDA); give the date", len(self._held))
            self._held.clear()
        return out

    def _feed_row(self, row: str, t: float | None) -> list[GnssFix]:
        row = row.strip(_BLANK)
        if not row:
            return []
        self.counters.lines += 1
        rx = t
        prefix = _RX_PREFIX.match(row)
        if prefix is not None:
            row = row[prefix.end() :]
            rx = float(prefix[1]) if t is None else t
        if row.startswith("#"):
            self.counters.comments += 1
            return []
        out: list[GnssFix] = []
        for fragment in _FRAGMENT_START.split(row):
            fragment = fragment.strip(_BLANK)
            if fragment in ("", "$", "!"):
                continue
            self.counters.fragments += 1
            part = self._parse(fragment)
            if part is not None:
                out.extend(self._add(part, rx))
        return out

    def _parse(self, fragment: str) -> _Part | None:
        if fragment[0] not in "$!" or not (fragment.isascii() and fragment.isprintable()):
            return self._bad("garbled", "not a sentence: %r", fragment[:80])
        try:
            msg = pynmea2.parse("$" + fragment[1:], check=True)
        except pynmea2.ChecksumError as e:
            return self._bad("checksum_errors", "%s: %r", e.args[0][0], fragment[:80])
        except pynmea2.SentenceTypeError:
            msg = None
        except _BAD_FIELD_ERRORS as e:  # pynmea2.ParseError, or a proprietary type choking on its fields
            return self._bad("garbled", "%s: %r", e, fragment[:80])
        extract = _EXTRACTORS.get(msg.sentence_type) if isinstance(msg, pynmea2.TalkerSentence) else None
        if extract is None:
            self.counters.sentences += 1
            self.counters.unknown += 1
            return None
        try:
            part = extract(msg)
        except _BAD_FIELD_ERRORS as e:
            return self._bad("garbled", "bad field (%s): %r", e, fragment[:80])
        self.counters.sentences += 1
        return self._plausible(part, fragment)

    def _plausible(self, part: _Part, fragment: str) -> _Part:
        """``part`` without the values outside :data:`LIMITS` (each counted ``implausible``)."""
        bad = [k for k, v in part.values.items() if k in LIMITS and not LIMITS[k][0] <= v <= LIMITS[k][1]]
        if not bad:
            return part
        for k in bad:
            self._bad(
                "implausible", "%s = %g outside %s; field ignored: %r", k, part.values[k], LIMITS[k], fragment[:80]
            )
        return dataclasses.replace(part, values={k: v for k, v in part.values.items() if k not in bad})

    def _bad(self, counter: str, fmt: str, *args: object) -> None:
        """Count one bad input; the first of each kind is logged as a warning, the rest at debug level."""
        setattr(self.counters, counter, getattr(self.counters, counter) + 1)
        if counter in self._warned:
            log.debug("NMEA %s: " + fmt, counter, *args)
        else:
            self._warned.add(counter)
            log.warning("NMEA %s: " + fmt + " (further ones are counted, logged at debug level)", counter, *args)

    def _add(self, part: _Part, rx: float | None) -> list[GnssFix]:
        out: list[GnssFix] = []
        epoch = self._open
        if part.tod is not None:
            if epoch is not None and epoch.tod is not None and part.tod != epoch.tod:
                out.extend(self._close(ender=False, time_change=True))
                epoch = None
            if (epoch is None or epoch.tod is None) and part.tod == self._last_tod:
                return out + self._late(part)
        elif epoch is None and self._closed_by_ender:
            return self._late(part)
        if epoch is None:
            epoch = self._open = _Epoch()
        epoch.add(part, rx)
        if self._ender is not None and epoch.last == self._ender:
            out.extend(self._close(ender=True))
        return out

    def _late(self, part: _Part) -> list[GnssFix]:
        self.counters.late += 1
        self._ender = self._ender_seen = None
        log.debug("NMEA late %s: its epoch was already emitted; cycle ender unlearned", part.key)
        return []

    def _close(self, ender: bool, time_change: bool = False) -> list[GnssFix]:
        epoch, self._open = self._open, None
        self._closed_by_ender = ender
        if epoch is None:
            return []
        if time_change:
            self._ender = epoch.last if epoch.last == self._ender_seen else None
            self._ender_seen = epoch.last
        if epoch.tod is not None:
            self._last_tod = epoch.tod
        return self._finish(epoch)

    def _finish(self, epoch: _Epoch) -> list[GnssFix]:
        when = self._resolve(epoch)
        out = self._release_held() if self._held and self._ref is not None else []
        if not any(p.fix is not None for p in epoch.parts):
            return out
        if when is None and epoch.rx is None:
            if epoch.tod is None:
                self._bad("undated", "a fix with neither UTC time nor receive time is dropped")
            else:
                self._hold(epoch)
            return out
        fix = self._emit(epoch, when)
        return out if fix is None else [*out, fix]

    def _resolve(self, epoch: _Epoch) -> dt.datetime | None:
        """The epoch's UTC date and time, or None while no date is known; advances the date reference."""
        if epoch.tod is None:
            return None
        date = next((p.date for p in reversed(epoch.parts) if p.date is not None), None)
        if date is not None and not self._date_plausible(date, epoch):
            date = None
        if date is not None:
            when = _utc(date, epoch.tod)
            self._input_dated = True
        elif self._ref is not None:
            when = _nearest_day(self._ref, epoch.tod)
        elif self.date is not None:
            when = _utc(self.date, epoch.tod)
        else:
            return None
        self._ref = when
        return when

    def _date_plausible(self, date: dt.date, epoch: _Epoch) -> bool:
        """Whether the epoch's date of fix lies within :data:`MAX_DATE_OFFSET_S` of its receive time or of the
        previous epoch's time dated by the input (before any: not ahead of the host clock by more); else
        ``implausible``, until :data:`RESYNC_AFTER` epochs in a row say so (the receiver's date really changed)."""
        assert epoch.tod is not None
        when = _utc(date, epoch.tod)
        if epoch.rx is not None and abs(when.timestamp() - epoch.rx) <= MAX_DATE_OFFSET_S:
            ok, clock = True, "the receive time"
        elif self._ref is not None and self._input_dated:
            ok, clock = abs((when - self._ref).total_seconds()) <= MAX_DATE_OFFSET_S, "the last epoch"
        else:
            ok, clock = when.timestamp() <= time.time() + MAX_DATE_OFFSET_S, "the host clock"
        self._odd_dates = 0 if ok else self._odd_dates + 1
        if ok or self._odd_dates >= RESYNC_AFTER:
            self._odd_dates = 0
            return True
        self._bad("implausible", "date %s more than %g s from %s; date ignored", date, MAX_DATE_OFFSET_S, clock)
        return False

    def _hold(self, epoch: _Epoch) -> None:
        if len(self._held) >= MAX_HELD:
            self._held.popleft()
            self._bad("undated", "no date (RMC or ZDA) after %d epochs; the oldest is dropped", MAX_HELD)
        self._held.append(epoch)

    def _release_held(self) -> list[GnssFix]:
        assert self._ref is not None
        ref, dated = self._ref, []
        for epoch in reversed(self._held):
            assert epoch.tod is not None
            ref = _nearest_day(ref, epoch.tod)
            dated.append((epoch, ref))
        self._held.clear()
        return [fix for epoch, when in reversed(dated) if (fix := self._emit(epoch, when)) is not None]

    def _emit(self, epoch: _Epoch, when: dt.datetime | None) -> GnssFix | None:
        if when is not None and self._last_when is not None and when <= self._last_when:
            self._behind += 1
            if self._behind < RESYNC_AFTER:
                return self._bad("backwards", "UTC time went back from %s to %s; epoch dropped", self._last_when, when)
            log.warning("NMEA: UTC time stays behind %s; following the receiver's new time %s", self._last_when, when)
        self._behind = 0
        if when is not None:
            self._last_when = when
        if epoch.rx is not None:
            t = epoch.rx
        else:
            assert when is not None, "epochs with neither receive time nor date are held"
            t = when.timestamp()
        fix = _assemble(epoch.parts, t, when)
        self.counters.fixes += 1
        if not fix.valid:
            self.counters.no_fix += 1
        return fix


def iter_fixes(
    source: str | os.PathLike[str] | Iterable[bytes | str], decoder: NmeaDecoder | None = None
) -> Iterator[GnssFix]:
    """Fixes from an NMEA log file (a path) or from lines (e.g. ``sys.stdin.buffer``), flushed at the end.

    A file that cannot be read raises :class:`~sumhe.errors.SourceError`.
    """
    dec = NmeaDecoder() if decoder is None else decoder
    if isinstance(source, str | os.PathLike):
        try:
            with open(source, "rb") as f:
                yield from iter_fixes(f, dec)
        except OSError as e:
            raise SourceError(f"{os.fsdecode(source)}: cannot read: {e.strerror or e}") from e
        return
    for line in source:
        yield from dec.feed(line)
    yield from dec.flush()


LOG_JUMP_S = 60.0
"""A log's receive clock moving this far (s) against the receiver's UTC (or, without a UTC date, between
consecutive fixes) has jumped: :func:`rebase_receive_times`."""


def rebase_receive_times(fixes: Iterable[GnssFix], name: str, counters: NmeaCounters) -> Iterator[GnssFix]:
    """The fixes of a logged NMEA stream with their receive times re-based across jumps of the logger's clock (an
    NTP step, an RTC set): where ``receive time - UTC`` changes by more than :data:`LOG_JUMP_S` from one fix to the
    next while the receive time itself steps by as much, the fixes after keep the old difference (counted in
    ``counters.rebases``, logged). A pause of the log (receiver or logger off) moves both clocks alike and is kept;
    a jump of the receiver's own UTC leaves the receive times steady and is left to the decoder. Fixes without a
    UTC date are judged by the step between receive times alone. The first jump is logged as a warning, the others
    at debug level."""
    offset = 0.0
    last_rx = last_lag = math.nan
    for fix in fixes:
        rx = fix.t
        lag = rx - fix.time_utc.timestamp() if fix.time_utc is not None else math.nan
        jump = lag - last_lag if math.isfinite(lag) and math.isfinite(last_lag) else rx - last_rx
        if abs(jump) > LOG_JUMP_S and abs(rx - last_rx) > LOG_JUMP_S:
            offset -= jump
            counters.rebases += 1
            log.log(
                logging.WARNING if counters.rebases == 1 else logging.DEBUG,
                "%s: the log's clock jumps by %+.3f s at %.3f: the fixes after it are re-based (%d so far)",
                name,
                jump,
                rx,
                counters.rebases,
            )
        last_rx = rx
        if math.isfinite(lag):
            last_lag = lag
        yield fix if offset == 0.0 else dataclasses.replace(fix, t=rx + offset)


def format_log_line(t: float, raw: bytes) -> bytes:
    """One line of our NMEA log format: ``(t) sentence\\n`` with the receive time ``t`` (s, 6 decimals)."""
    return b"(%.6f) %s\n" % (t, raw.rstrip(b"\r\n"))
