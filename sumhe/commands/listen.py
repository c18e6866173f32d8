"""``sumhe listen [HOST:PORT ...]``: print the positions sumhe sends over UDP, JSON or NMEA, as one line each.

A client to check a daemon (or a container) works, and the shortest example of reading sumhe's output: bind a UDP
socket, parse each datagram (one JSON object, or GGA + RMC sentences). By default it prints the newest position
once a second with the number of datagrams since the last line; ``--every 0`` prints every datagram. It binds
127.0.0.1:5005 (the default ``output.json``) unless told other addresses; it never sends anything.

UDP keeps neither order nor delivery: sumhe numbers its JSON datagrams (``seq``), and per address a datagram
numbered below one already received (overtaken on the way, or repeated) is not taken as the newest position; the
datagrams lost, overtaken and repeated are counted in the last line (a ``seq`` of 0 after others: the daemon
started again).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import selectors
import signal
import socket
import sys
import time
from dataclasses import dataclass, field
from typing import Any

import pynmea2

from sumhe.config import parse_host_port
from sumhe.errors import ConfigError
from sumhe.io.nmea import KNOT_MPS
from sumhe.io.udp import GGA_DEAD_RECKONING


@dataclass(frozen=True, slots=True)
class Position:
    """What one datagram said; ``None`` where it did not say it."""

    t: float | None
    lat: float
    lon: float
    alt: float | None
    speed: float | None
    track: float | None
    gps: str
    mode: str
    seq: int | None = None
    """The datagram's number (JSON from ``sumhe run``), None where it has none."""


REMEMBERED = 10_000
"""Missing numbers remembered per address: a datagram overtaken by more than this many is counted as repeated."""


@dataclass
class Numbering:
    """The ``seq`` numbers of one address's datagrams: those lost on the way (gaps not filled since), those that
    arrived after a later one (overtaken: they fill a gap) and those that arrived again (repeated on the way, which
    UDP allows but rarely does)."""

    top: int | None = None
    lost: int = 0
    overtaken: int = 0
    repeated: int = 0
    missing: set[int] = field(default_factory=set)
    """The numbers of the gaps not filled yet (the newest :data:`REMEMBERED` of them)."""

    def see(self, seq: int) -> bool:
        """Count datagram ``seq``; True when it is the newest so far (a 0 after others: the sender started again;
        the same number twice is not new)."""
        if self.top is not None and 0 < seq <= self.top:
            if seq in self.missing:
                self.missing.remove(seq)
                self.overtaken += 1
                self.lost -= 1  # it fills a gap counted as lost
            else:
                self.repeated += 1
            return False
        if self.top is None or seq <= self.top:  # the first, or a 0 after others: numbering starts again
            self.missing.clear()
        else:
            self.lost += seq - self.top - 1
            self.missing.update(range(max(self.top + 1, seq - REMEMBERED), seq))
            if len(self.missing) > 2 * REMEMBERED:
                self.missing = {k for k in self.missing if k >= seq - REMEMBERED}
        self.top = seq
        return True


def parse_datagram(data: bytes) -> Position | None:
    """A position from one datagram of sumhe's output (JSON ``TPV`` or NMEA GGA/RMC); None if it has none."""
    text = data.strip()
    if text.startswith(b"{"):
        try:
            obj: Any = json.loads(text)
        except ValueError:
            return None
        if not isinstance(obj, dict) or not _finite(obj.get("lat")) or not _finite(obj.get("lon")):
            return None
        return Position(
            obj.get("t"),
            obj["lat"],
            obj["lon"],
            obj.get("alt"),
            obj.get("speed"),
            obj.get("track"),
            str(obj.get("gps", "")),
            str(obj.get("mode", "")),
            seq if isinstance(seq := obj.get("seq"), int) and not isinstance(seq, bool) and seq >= 0 else None,
        )
    return _nmea_position(text.decode("ascii", "replace"))


def _nmea_position(text: str) -> Position | None:
    """GGA (time, position, altitude, quality 6 = dead reckoning) and RMC (speed, course) of one datagram, read
    with pynmea2 (sumhe's own decoder takes a quality-6 fix as no fix, as a receiver's input should be)."""
    gga = rmc = None
    for line in text.splitlines():
        try:
            msg = pynmea2.parse(line.strip(), check=True)
        except pynmea2.ParseError:
            continue
        if isinstance(msg, pynmea2.GGA):
            gga = msg
        elif isinstance(msg, pynmea2.RMC):
            rmc = msg
    if gga is None or not gga.lat or not gga.lon:
        return None
    when = None
    if rmc is not None and rmc.datestamp and gga.timestamp:
        when = dt.datetime.combine(rmc.datestamp, gga.timestamp.replace(tzinfo=dt.timezone.utc)).timestamp()
    dead_reckoning = int(gga.gps_qual or 0) == GGA_DEAD_RECKONING
    speed = float(rmc.spd_over_grnd) * KNOT_MPS if rmc is not None and rmc.spd_over_grnd is not None else None
    course = float(rmc.true_course) if rmc is not None and rmc.true_course is not None else None
    return Position(
        when,
        gga.latitude,
        gga.longitude,
        float(gga.altitude) if gga.altitude is not None else None,
        speed,
        course,
        "outage" if dead_reckoning else "ok",
        "nmea (dead reckoning)" if dead_reckoning else "nmea",
    )


def _finite(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _num(value: float | None, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def format_position(p: Position, where: str, count: int) -> str:
    """One printed line: time, position, speed, track, GPS status, mode, and where it came from."""
    when = time.strftime("%H:%M:%S", time.gmtime(p.t)) + f".{int((p.t % 1) * 10)}Z" if p.t is not None else "-"
    return (
        f"{when}  lat {p.lat:.7f} lon {p.lon:.7f} alt {_num(p.alt, '.1f')} m  speed {_num(p.speed, '.2f')} m/s  "
        f"track {_num(p.track, '.1f')} deg  gps {p.gps}  mode {p.mode}  [{where}, {count} datagrams]"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "addresses", nargs="*", metavar="HOST:PORT", help="UDP addresses to bind (default 127.0.0.1:5005)"
    )
    parser.add_argument("--every", type=float, default=1.0, metavar="S", help="print at most every S s (0: all)")
    parser.add_argument("--count", type=int, metavar="N", help="stop after N datagrams with a position")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")


def _bind(text: str) -> socket.socket:
    try:
        host, port = parse_host_port(text)
        family, kind, proto, _, addr = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
        sock = socket.socket(family, kind, proto)
    except (ValueError, OSError) as e:
        raise ConfigError(f"listen: {e}") from e
    try:
        sock.bind(addr)
    except OSError as e:
        sock.close()
        raise ConfigError(f"listen: cannot bind {text}: {e.strerror}") from e
    sock.setblocking(False)
    return sock


def run(args: argparse.Namespace) -> int:
    addresses = args.addresses or ["127.0.0.1:5005"]
    sel = selectors.DefaultSelector()
    for text in addresses:
        sel.register(_bind(text), selectors.EVENT_READ, text)
    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))
    print(f"listening on {', '.join(addresses)}", file=sys.stderr, flush=True)
    end = time.monotonic() + args.duration if args.duration is not None else math.inf
    received = since = 0
    next_line = 0.0
    newest: tuple[Position, str] | None = None
    numbering: dict[str, Numbering] = {}
    try:
        while not stop[0] and time.monotonic() < end and (args.count is None or received < args.count):
            for key, _ in sel.select(timeout=min(0.2, max(end - time.monotonic(), 0.0))):
                data = key.fileobj.recv(65535)  # type: ignore[union-attr]
                position = parse_datagram(data)
                if position is None:
                    continue
                received += 1
                since += 1
                fresh = position.seq is None or numbering.setdefault(key.data, Numbering()).see(position.seq)
                if fresh or args.every <= 0:  # --every 0 prints every datagram, an overtaken one too
                    newest = (position, key.data)
                if args.every <= 0 or (args.count is not None and received >= args.count):
                    break
            now = time.monotonic()
            if newest is not None and (now >= next_line or args.every <= 0 or received == args.count):
                print(format_position(*newest, since), flush=True)
                next_line = now + args.every
                newest, since = None, 0
    finally:
        for key in list(sel.get_map().values()):
            key.fileobj.close()  # type: ignore[union-attr]
        sel.close()
    numbered = ""
    if numbering:
        lost = sum(n.lost for n in numbering.values())
        overtaken = sum(n.overtaken for n in numbering.values())
        repeated = sum(n.repeated for n in numbering.values())
        numbered = f" ({lost} lost, {overtaken} out of order by their seq, {repeated} repeated)"
    print(f"{received} datagrams with a position{numbered}", file=sys.stderr)
    return 0
