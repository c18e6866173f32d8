"""UDP output: each estimate as one JSON object per datagram and/or as NMEA GGA + RMC + GST sentences.

Destinations (:func:`remote_reason`): without ``output.allow_remote`` each must be this host: a loopback address, an
address of one of its interfaces, or an interface-local IPv6 multicast group (``ff01::/16``, ``ff11::/16``); a name
is resolved once, at start, and judged by its address. Broadcast, multicast beyond the host and other hosts are a
ConfigError naming the key unless ``output.allow_remote = true`` (which also lets IPv4 sockets broadcast).

Sending never blocks (non-blocking sockets; a full socket buffer drops the datagram and counts it) and a missing
receiver is not an error (counted, logged once per destination). JSON keys are documented in the README.
"""

from __future__ import annotations

import datetime as dt
import functools
import ipaddress
import json
import logging
import math
import socket
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from sumhe.config import OutputSettings, parse_host_port
from sumhe.errors import ConfigError
from sumhe.io.nmea_format import format_gga, format_gst, format_rmc
from sumhe.messages import ErrorEstimate, Estimate

log = logging.getLogger(__name__)


def iso_utc(t: float) -> str:
    """Unix seconds -> ISO 8601 UTC with milliseconds, e.g. ``2026-06-01T08:00:00.100Z``: the microseconds
    rounded half to even, as :meth:`datetime.datetime.fromtimestamp` rounds them, then cut to milliseconds."""
    fraction, whole = math.modf(t)
    us = round(fraction * 1e6)
    if us >= 1_000_000:
        us, whole = us - 1_000_000, whole + 1.0
    elif us < 0:
        us, whole = us + 1_000_000, whole - 1.0
    return f"{_utc_second(int(whole))}.{us // 1000:03d}Z"


@functools.lru_cache(maxsize=16)
def _utc_second(t: int) -> str:
    """Whole Unix seconds -> ``2026-06-01T08:00:00`` (cached: estimates come many to a second)."""
    return dt.datetime.fromtimestamp(t, tz=dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S")


def estimate_to_json(est: Estimate) -> dict[str, Any]:
    """The JSON object sent for one estimate (:func:`json_line`, read back)."""
    out: dict[str, Any] = json.loads(json_line(est))
    return out


_COMPACT = json.JSONEncoder(separators=(",", ":"))
"""``json.dumps(..., separators=(",", ":"))`` without building an encoder per call."""


def _number(value: float | int | None) -> str:
    """A number (or None) as JSON text, as :mod:`json` writes it (a float's ``repr``)."""
    kind = type(value)
    if kind is float and math.isfinite(value):  # type: ignore[arg-type]
        return float.__repr__(value)  # type: ignore[arg-type]
    return int.__repr__(value) if kind is int else _COMPACT.encode(value)  # type: ignore[arg-type]


SHORTEST_DIGITS = 15
"""Significant digits any decimal number of at most this many has as its float's ``repr`` (10**15 < 2**53)."""
_FORMATS = {digits: (10.0 ** (SHORTEST_DIGITS - digits), f".{digits}f") for digits in range(SHORTEST_DIGITS)}
"""Per number of decimals: the magnitude below which :func:`_fixed`'s text has at most :data:`SHORTEST_DIGITS`
significant digits, and the format."""


def _fixed(value: float | None, digits: int) -> str:
    """``value`` rounded to ``digits`` decimals as JSON text (as :func:`_number` writes ``round(value, digits)``);
    null for None and non-finite values.

    Where it can, the text is the decimal ``format`` rounds to, its trailing zeros cut (``12.340`` -> ``12.34``,
    ``-0.000`` -> ``-0.0``): three times faster than ``repr(round(...))``, for 17 fields per estimate (the
    bundled drive's 12 602 lines in 0.12 s instead of 0.20 s). Both round the float's exact binary value half to
    even, and a decimal of at most :data:`SHORTEST_DIGITS` significant digits is its own float's shortest
    ``repr``. Not where ``repr`` writes an exponent (below 1e-4), beyond that many digits, nor for ints, NaN and
    infinities (tests/test_udp.py checks the two paths agree at these edges)."""
    limit, spec = _FORMATS[digits]
    if type(value) is float and 1e-4 <= abs(value) < limit:
        text = format(value, spec).rstrip("0")
        return text + "0" if text[-1] == "." else text
    if value is None or not math.isfinite(value):
        return "null"
    rounded = round(value, digits)
    return float.__repr__(rounded) if type(rounded) is float else _number(rounded)


def json_line(est: Estimate) -> str:
    """One estimate as compact JSON text (no newline): what a datagram and a line of ``sumhe replay --out`` hold.

    A gpsd-like ``TPV`` object; ``track`` in degrees clockwise from north; numbers rounded (non-finite: null); the
    error figures, bounds, satellites and HDOP only where the estimate has them. Written from a template (the same
    text as encoding the object with :mod:`json`, a few times faster: one line per estimate)."""
    text = (
        f'{{"class":"TPV","time":"{iso_utc(est.t)}","t":{_fixed(est.t, 4)},"lat":{_fixed(est.lat_deg, 9)},'
        f'"lon":{_fixed(est.lon_deg, 9)},"alt":{_fixed(est.alt_m, 3)},"east":{_fixed(est.east_m, 3)},'
        f'"north":{_fixed(est.north_m, 3)},"track":{_fixed(math.degrees(est.track_rad) % 360.0, 3)},'
        f'"speed":{_fixed(est.speed_mps, 3)},"yaw_rate":{_fixed(est.yaw_rate_rps, 5)},'
        f'"gps":{_COMPACT.encode(est.gps)},"mode":{_COMPACT.encode(est.mode)},"window":{_number(est.window)},'
        f'"solve_ms":{_fixed(est.solve_ms, 3)}'
    )
    error = est.error
    if error is not None:
        text += (
            f',"eph":{_fixed(error.eph_m, 3)},"epx":{_fixed(error.epx_m, 3)},"epy":{_fixed(error.epy_m, 3)},'
            f'"eps":{_fixed(error.eps_mps, 3)},"epd":{_fixed(math.degrees(error.epd_rad), 3)}'
        )
    if est.bound_east_m is not None and est.bound_north_m is not None:
        text += f',"bound_east":{_fixed(est.bound_east_m, 3)},"bound_north":{_fixed(est.bound_north_m, 3)}'
    if est.sats is not None:
        text += f',"sats":{_number(est.sats)}'
    if est.hdop is not None:
        text += f',"hdop":{_fixed(est.hdop, 2)}'
    return text + "}"


def encode_json(est: Estimate, seq: int | None = None) -> bytes:
    """One datagram: compact JSON, UTF-8, no trailing newline; ``seq`` (the datagram's number, where given) its last
    key."""
    text = json_line(est)
    return (f'{text[:-1]},"seq":{seq}}}' if seq is not None else text).encode()


GGA_GPS = 1
GGA_DEAD_RECKONING = 6


def encode_nmea(est: Estimate) -> bytes:
    """GGA + RMC + GST of one estimate, CRLF-terminated, in one datagram. While GPS is not used (outage or rejected
    fix) GGA says quality 6 and RMC mode E (dead reckoning), the way gpsd understands. GGA carries the satellites
    and HDOP of :class:`~sumhe.messages.Estimate`; GST the estimator's 1-sigma error ellipse and per-axis sigmas
    (no pseudorange RMS, no altitude sigma: those fields are empty); no GST without an error estimate."""
    dead_reckoning = est.gps != "ok"
    hdop = est.hdop if est.hdop is not None and math.isfinite(est.hdop) else None
    gga = format_gga(
        est.t,
        est.lat_deg,
        est.lon_deg,
        GGA_DEAD_RECKONING if dead_reckoning else GGA_GPS,
        sats=None if est.sats is None else min(max(est.sats, 0), 99),
        hdop=None if hdop is None else min(hdop, 99.99),
        alt_msl_m=est.alt_m,
    )
    rmc = format_rmc(
        est.t,
        est.lat_deg,
        est.lon_deg,
        mode="E" if dead_reckoning else "A",
        speed_mps=max(est.speed_mps, 0.0) if math.isfinite(est.speed_mps) else None,
        course_rad=est.track_rad if math.isfinite(est.track_rad) else None,
    )
    lines = [gga, rmc]
    if est.error is not None:
        lines.append(gst_of(est.t, est.error))
    return "".join(f"{line}\r\n" for line in lines).encode("ascii")


def gst_of(t: float, error: ErrorEstimate) -> str:
    """The GST sentence of an error estimate: 1-sigma semi-major and semi-minor axes, the orientation of the
    semi-major axis, the latitude (north) and longitude (east) sigmas."""
    return format_gst(
        t,
        rms_m=None,
        sigma_lat_m=error.sigma_north_m,
        sigma_lon_m=error.sigma_east_m,
        sigma_major_m=error.sigma_major_m,
        sigma_minor_m=error.sigma_minor_m,
        orientation_rad=error.orient_rad,
    )


LIMITED_BROADCAST = ipaddress.IPv4Address("255.255.255.255")


def _is_own_address(family: int, addr: tuple[Any, ...]) -> bool:
    """Whether ``addr`` is an address of this host (a socket can be bound to it)."""
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((addr[0], 0, *addr[2:]))
        except OSError:
            return False
    return True


def remote_reason(family: int, addr: tuple[Any, ...]) -> str | None:
    """What the resolved destination ``addr`` is when it is not this host (``"broadcast"``, ``"another host"``,
    ...), None when it is: loopback, an address of the host's own, an interface-local IPv6 multicast group."""
    ip = ipaddress.ip_address(str(addr[0]).partition("%")[0])
    if ip.is_loopback:
        return None
    if ip.is_multicast:
        interface_local = ip.version == 6 and ip.packed[1] & 0x0F == 1
        return None if interface_local else "a multicast group reaching beyond this host"
    if ip == LIMITED_BROADCAST:
        return "broadcast"
    if ip.is_unspecified:
        return "the unspecified address"
    return None if _is_own_address(family, addr) else "another host"


@dataclass
class UdpStats:
    sent: int = 0
    dropped: int = 0
    refused: int = 0
    errors: int = 0


class UdpSender:
    """Fire-and-forget datagrams to fixed ``host:port`` destinations (IPv4 or IPv6).

    Names are resolved once, here; one that does not resolve, and without ``allow_remote`` one that is not this
    host (:func:`remote_reason`), is a ConfigError naming ``key`` (and ``origin``, where it was set).
    """

    def __init__(
        self, destinations: Iterable[str], key: str = "output", origin: str = "<config>", allow_remote: bool = False
    ) -> None:
        self.stats = UdpStats()
        self._dests: list[tuple[socket.socket, tuple[Any, ...], str]] = []
        self._socks: dict[int, socket.socket] = {}
        self._warned: set[str] = set()
        for text in destinations:
            host, port = parse_host_port(text)
            try:
                family, _, _, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
            except (socket.gaierror, UnicodeError) as e:
                self.close()
                why = e.strerror if isinstance(e, socket.gaierror) else str(e)
                raise ConfigError(f"{origin}: {key}: cannot resolve {host!r} ({why})") from e
            remote = None if allow_remote else remote_reason(family, addr)
            if remote is not None:
                self.close()
                raise ConfigError(
                    f"{origin}: {key}: {text} ({addr[0]}) is {remote}, not this host: set output.allow_remote = true "
                    "to send there"
                )
            sock = self._socks.get(family)
            if sock is None:
                sock = socket.socket(family, socket.SOCK_DGRAM)
                sock.setblocking(False)
                if allow_remote and family == socket.AF_INET:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
                self._socks[family] = sock
            self._dests.append((sock, addr, text))

    def send(self, payload: bytes) -> None:
        """Send ``payload`` to every destination; never blocks, never raises for a network condition."""
        for sock, addr, text in self._dests:
            try:
                sock.sendto(payload, addr)
                self.stats.sent += 1
            except BlockingIOError:
                self.stats.dropped += 1
            except ConnectionRefusedError:
                self.stats.refused += 1
                self._warn_once(text, "no receiver")
            except OSError as e:
                self.stats.errors += 1
                self._warn_once(text, str(e))

    def _warn_once(self, dest: str, why: str) -> None:
        if dest not in self._warned:
            self._warned.add(dest)
            log.warning("udp %s: %s (counted; further occurrences are not logged)", dest, why)

    def close(self) -> None:
        """Close the sockets (idempotent)."""
        for sock in self._socks.values():
            sock.close()
        self._socks.clear()
        self._dests.clear()

    def __enter__(self) -> UdpSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class UdpSink:
    """The configured output: each estimate, encoded in each format, to that format's destinations
    (``output.json``, ``output.nmea``). The JSON datagrams are numbered (``seq``: 0, 1, ... in the order sent, the
    same number to every destination): UDP keeps neither order nor delivery, even over loopback (on a loaded
    machine two datagrams sent one after the other from different CPUs can arrive the other way round), so a
    consumer tells a datagram lost (a gap) or overtaken (a number below one already received)."""

    def __init__(self, settings: OutputSettings, blame: Callable[[str], str] | None = None) -> None:
        self.formats = settings.formats
        self.senders: dict[str, UdpSender] = {}
        for fmt, dests in settings.formats.items():
            key = f"output.{fmt}"
            try:
                self.senders[fmt] = UdpSender(dests, key, blame(key) if blame else "<config>", settings.allow_remote)
            except ConfigError:
                self.close()
                raise
        self.seq = 0
        """The number the next JSON datagram carries."""

    def send(self, est: Estimate) -> None:
        for fmt, sender in self.senders.items():
            sender.send(encode_json(est, self.seq) if fmt == "json" else encode_nmea(est))
        self.seq += 1

    def describe(self) -> str:
        """``json to 127.0.0.1:5005, nmea to 127.0.0.1:10110`` (for the start-up line)."""
        return ", ".join(f"{fmt} to {' '.join(dests)}" for fmt, dests in self.formats.items()) or "nowhere"

    def close(self) -> None:
        for sender in self.senders.values():
            sender.close()
