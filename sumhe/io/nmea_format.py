"""NMEA-0183 sentence formatting: pure functions from SI values to full sentences ``$...*hh`` (no line ending).

Used by the simulator to write receiver output and by the service to send its own positions as NMEA (GGA
quality 6 and RMC mode E while dead reckoning, the way gpsd understands). Latitude and longitude carry
``decimals`` decimals of minutes (default 7: 0.2 mm); time of day carries centiseconds. Rounding is done once
on integers, so a value never prints as 60 minutes or 60 seconds. Every bad value raises ``ValueError`` naming
the argument.
"""

from __future__ import annotations

import datetime as dt
import math
import re

KNOTS_PER_MPS = 3600.0 / 1852.0
MPS_PER_KNOT = 1852.0 / 3600.0
LATLON_DECIMALS = 7
GGA_QUALITIES = range(9)
"""0 no fix, 1 GPS, 2 DGPS, 3 PPS, 4 RTK fixed, 5 RTK float, 6 dead reckoning, 7 manual, 8 simulation."""
RMC_MODES = frozenset("ADEFMNPRS")
"""FAA mode: A autonomous, D differential, E estimated (dead reckoning), F RTK float, M manual, N not valid,
P precise, R RTK fixed, S simulator."""

_TALKER = re.compile(r"[A-Z]{2}")


def nmea_checksum(body: str) -> str:
    """The two upper-case hex digits of the XOR of ``body`` (the text between ``$`` and ``*``)."""
    value = 0
    for byte in body.encode("ascii"):
        value ^= byte
    return f"{value:02X}"


def sentence(body: str) -> str:
    """``$body*hh``; ``body`` must be printable ASCII without ``$``, ``*``, CR or LF."""
    if not body.isascii() or not body.isprintable() or "$" in body or "*" in body:
        raise ValueError(f"body: not a valid NMEA sentence body: {body!r}")
    return f"${body}*{nmea_checksum(body)}"


def format_gga(
    t_unix_s: float,
    lat_deg: float | None,
    lon_deg: float | None,
    quality: int,
    *,
    sats: int | None = None,
    hdop: float | None = None,
    alt_msl_m: float | None = None,
    geoid_sep_m: float | None = None,
    dgps_age_s: float | None = None,
    dgps_station: str = "",
    talker: str = "GP",
    decimals: int = LATLON_DECIMALS,
) -> str:
    """GGA: time of fix, position, quality (0 no fix ... 6 dead reckoning), satellites, HDOP, altitude (m MSL).

    ``lat_deg``/``lon_deg`` None (as with quality 0) leaves the position fields empty.
    """
    if isinstance(quality, bool) or quality not in GGA_QUALITIES:
        raise ValueError(f"quality: must be an integer 0-8, got {quality!r}")
    if sats is not None and not 0 <= sats <= 99:
        raise ValueError(f"sats: must be 0-99, got {sats!r}")
    if not re.fullmatch(r"[0-9]{0,4}", dgps_station):
        raise ValueError(f"dgps_station: must be up to 4 digits, got {dgps_station!r}")
    fields = [
        _talker(talker) + "GGA",
        _time_of_day(t_unix_s),
        *_latlon(lat_deg, lon_deg, decimals),
        str(quality),
        "" if sats is None else f"{sats:02d}",
        _number(hdop, 2, "hdop"),
        _number(alt_msl_m, 3, "alt_msl_m"),
        "" if alt_msl_m is None else "M",
        _number(geoid_sep_m, 3, "geoid_sep_m"),
        "" if geoid_sep_m is None else "M",
        _number(dgps_age_s, 1, "dgps_age_s"),
        dgps_station,
    ]
    return sentence(",".join(fields))


def format_rmc(
    t_unix_s: float,
    lat_deg: float | None,
    lon_deg: float | None,
    *,
    status: str = "A",
    mode: str = "A",
    speed_mps: float | None = None,
    course_rad: float | None = None,
    talker: str = "GP",
    decimals: int = LATLON_DECIMALS,
) -> str:
    """RMC (NMEA 2.3, with the FAA mode): status A valid / V not valid, speed over ground (sent in knots),
    course over ground (sent in degrees clockwise from true north, in [0, 360)); None leaves a field empty."""
    if status not in ("A", "V"):
        raise ValueError(f"status: must be 'A' or 'V', got {status!r}")
    if len(mode) != 1 or mode not in RMC_MODES:
        raise ValueError(f"mode: must be one of {''.join(sorted(RMC_MODES))}, got {mode!r}")
    if speed_mps is not None and not (math.isfinite(speed_mps) and speed_mps >= 0.0):
        raise ValueError(f"speed_mps: must be finite and >= 0, got {speed_mps!r}")
    t = _centiseconds(t_unix_s)
    fields = [
        _talker(talker) + "RMC",
        _time_of_day(t_unix_s),
        status,
        *_latlon(lat_deg, lon_deg, decimals),
        _number(None if speed_mps is None else speed_mps * KNOTS_PER_MPS, 3, "speed_mps"),
        _angle_deg(course_rad, "course_rad"),
        _utc(t).strftime("%d%m%y"),
        "",
        "",
        mode,
    ]
    return sentence(",".join(fields))


def format_gst(
    t_unix_s: float,
    *,
    rms_m: float | None,
    sigma_lat_m: float | None,
    sigma_lon_m: float | None,
    sigma_alt_m: float | None = None,
    sigma_major_m: float | None = None,
    sigma_minor_m: float | None = None,
    orientation_rad: float | None = None,
    talker: str = "GP",
) -> str:
    """GST: pseudorange residual RMS and 1-sigma position errors (m); None leaves a field empty (no fix)."""
    for name, value in (("sigma_lat_m", sigma_lat_m), ("sigma_lon_m", sigma_lon_m), ("sigma_alt_m", sigma_alt_m)):
        if value is not None and not (math.isfinite(value) and value >= 0.0):
            raise ValueError(f"{name}: must be finite and >= 0, got {value!r}")
    fields = [
        _talker(talker) + "GST",
        _time_of_day(t_unix_s),
        _number(rms_m, 3, "rms_m"),
        _number(sigma_major_m, 3, "sigma_major_m"),
        _number(sigma_minor_m, 3, "sigma_minor_m"),
        _angle_deg(orientation_rad, "orientation_rad"),
        _number(sigma_lat_m, 3, "sigma_lat_m"),
        _number(sigma_lon_m, 3, "sigma_lon_m"),
        _number(sigma_alt_m, 3, "sigma_alt_m"),
    ]
    return sentence(",".join(fields))


def format_hdt(heading_rad: float | None, *, talker: str = "GP") -> str:
    """HDT: true heading of the vehicle (sent in degrees clockwise from north, [0, 360)); None: empty."""
    return sentence(",".join([_talker(talker) + "HDT", _angle_deg(heading_rad, "heading_rad"), "T"]))


def split_minutes(value_deg: float, decimals: int = LATLON_DECIMALS) -> tuple[int, int]:
    """|value| as (whole degrees, minutes in units of 10^-decimals), rounded once: never 60 minutes."""
    per_degree = 60 * 10**decimals
    total = round(abs(value_deg) * per_degree)
    return divmod(total, per_degree)


def quantize_latlon(value_deg: float, decimals: int = LATLON_DECIMALS) -> float:
    """The latitude or longitude (deg) that a sentence with ``decimals`` decimals of minutes carries."""
    deg, units = split_minutes(value_deg, decimals)
    return math.copysign(deg + units / (60 * 10**decimals), value_deg)


def quantize_angle_rad(value_rad: float) -> float:
    """The angle (rad, wrapped to [0, 2 pi)) that a sentence's course or heading field carries."""
    return math.radians(_millidegrees(value_rad) / 1000.0)


def _millidegrees(value_rad: float) -> int:
    return round(math.degrees(value_rad) * 1000.0) % 360_000


def _talker(talker: str) -> str:
    if not _TALKER.fullmatch(talker):
        raise ValueError(f"talker: must be two upper-case letters, got {talker!r}")
    return talker


def _centiseconds(t_unix_s: float) -> int:
    if not (math.isfinite(t_unix_s) and t_unix_s >= 0.0):
        raise ValueError(f"t_unix_s: must be a finite time >= 0, got {t_unix_s!r}")
    return round(t_unix_s * 100.0)


def _utc(centiseconds: int) -> dt.datetime:
    return dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc) + dt.timedelta(microseconds=centiseconds * 10_000)


def _time_of_day(t_unix_s: float) -> str:
    cs = _centiseconds(t_unix_s) % 8_640_000
    hours, rest = divmod(cs, 360_000)
    minutes, rest = divmod(rest, 6_000)
    seconds, hundredths = divmod(rest, 100)
    return f"{hours:02d}{minutes:02d}{seconds:02d}.{hundredths:02d}"


def _latlon(lat_deg: float | None, lon_deg: float | None, decimals: int) -> list[str]:
    if (lat_deg is None) != (lon_deg is None):
        raise ValueError("lat_deg: latitude and longitude must both be given or both be None")
    if lat_deg is None or lon_deg is None:
        return ["", "", "", ""]
    if not 1 <= decimals <= 9:
        raise ValueError(f"decimals: must be 1-9, got {decimals!r}")
    if not (math.isfinite(lat_deg) and -90.0 <= lat_deg <= 90.0):
        raise ValueError(f"lat_deg: not a latitude: {lat_deg!r}")
    if not (math.isfinite(lon_deg) and -180.0 <= lon_deg <= 180.0):
        raise ValueError(f"lon_deg: not a longitude: {lon_deg!r}")
    lat_d, lat_u = split_minutes(lat_deg, decimals)
    lon_d, lon_u = split_minutes(lon_deg, decimals)
    scale = 10**decimals
    lat_m, lat_f = divmod(lat_u, scale)
    lon_m, lon_f = divmod(lon_u, scale)
    return [
        f"{lat_d:02d}{lat_m:02d}.{lat_f:0{decimals}d}",
        "S" if lat_deg < 0 and lat_u + lat_d > 0 else "N",
        f"{lon_d:03d}{lon_m:02d}.{lon_f:0{decimals}d}",
        "W" if lon_deg < 0 and lon_u + lon_d > 0 else "E",
    ]


def _number(value: float | None, decimals: int, name: str) -> str:
    if value is None:
        return ""
    if not math.isfinite(value):
        raise ValueError(f"{name}: must be finite, got {value!r}")
    text = f"{value:.{decimals}f}"
    return text[1:] if text.startswith("-") and float(text) == 0.0 else text


def _angle_deg(value_rad: float | None, name: str) -> str:
    """Degrees in [0, 360) with 3 decimals, wrapped after rounding (359.9996 -> 0.000)."""
    if value_rad is None:
        return ""
    if not math.isfinite(value_rad):
        raise ValueError(f"{name}: must be finite, got {value_rad!r}")
    millideg = _millidegrees(value_rad)
    return f"{millideg // 1000}.{millideg % 1000:03d}"
