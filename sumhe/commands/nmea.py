"""``sumhe nmea FILE|- [--date YYYY-MM-DD]``: decode NMEA sentences into fixes, one JSON line each.

Each line has ``t`` (s: receive time, or UTC as Unix time), ``time`` (ISO 8601 UTC or null), ``lat``, ``lon``
(deg), ``alt`` (m above mean sea level), ``quality`` (GGA fix quality), ``sats``, ``hdop``, ``speed`` (m/s),
``course`` and ``heading`` (deg clockwise from north), ``sigma_lat``, ``sigma_lon``, ``sigma_alt`` (m, from
GST), ``talker`` and ``valid``; absent values are null. A summary of what was read goes to stderr.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
from typing import Any

from sumhe.io.nmea import NmeaCounters, NmeaDecoder, iter_fixes
from sumhe.messages import GnssFix


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="NMEA log (raw receiver output or '(t) sentence' lines); '-' reads stdin")
    parser.add_argument(
        "--date",
        type=dt.date.fromisoformat,
        metavar="YYYY-MM-DD",
        help="UTC date of the first fix, for receivers that send neither RMC nor ZDA",
    )


def run(args: argparse.Namespace) -> int:
    decoder = NmeaDecoder(date=args.date)
    source = sys.stdin.buffer if args.file == "-" else args.file
    for fix in iter_fixes(source, decoder):
        sys.stdout.write(json.dumps(fix_to_json(fix)) + "\n")
    sys.stdout.flush()
    sys.stderr.write(summary(decoder.counters))
    return 0


def _deg(rad: float | None) -> float | None:
    return None if rad is None else math.degrees(rad)


def fix_to_json(fix: GnssFix) -> dict[str, Any]:
    """The JSON object of one fix (degrees for angles, SI otherwise)."""
    return {
        "t": fix.t,
        "time": None if fix.time_utc is None else fix.time_utc.strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z",
        "lat": fix.lat_deg,
        "lon": fix.lon_deg,
        "alt": fix.alt_m,
        "quality": fix.quality,
        "sats": fix.sats,
        "hdop": fix.hdop,
        "speed": fix.speed_mps,
        "course": _deg(fix.course_rad),
        "heading": _deg(fix.heading_rad),
        "sigma_lat": fix.sigma_lat_m,
        "sigma_lon": fix.sigma_lon_m,
        "sigma_alt": fix.sigma_alt_m,
        "talker": fix.talker,
        "valid": fix.valid,
    }


def summary(c: NmeaCounters) -> str:
    """The stderr summary: what was read and what became of it."""
    return (
        f"lines: {c.lines} ({c.comments} comments); sentences: {c.sentences} ({c.unknown} of unused types); "
        f"checksum errors: {c.checksum_errors}; garbled: {c.garbled}; implausible values ignored: {c.implausible}\n"
        f"fixes: {c.fixes} ({c.no_fix} without a position); dropped: {c.late} late sentences, "
        f"{c.backwards} epochs with time going backwards, {c.undated} fixes without a date\n"
    )
