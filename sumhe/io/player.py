"""Play a recorded drive onto live interfaces: CAN frames onto a python-can bus, NMEA lines into a pseudo-terminal.

The player is what makes the live path testable without a car: ``sumhe demo`` plays the bundled drive in-process
(``virtual`` bus), the end-to-end tests play a drive from another process (``udp_multicast`` bus), and the docker
compose file plays a log onto the host's ``vcan0``.

Timing: an event stamped ``t`` in the logs is sent at wall time ``wall0 + (t - t0) / speed``. CAN frames are
re-stamped ``start_t + (t - t0)``, where ``start_t`` is the service clock when playing starts; where the bus keeps
the sender's timestamps (python-can's ``virtual`` bus with ``preserve_timestamps``), a service that runs on the
scaled clock ``start_t + (wall - wall0) * speed`` sees a consistent drive at any speed. Buses that stamp on
receive (socketcan, udp_multicast) need ``speed = 1``.

The pseudo-terminal is reached through a symlink (``link``), so it can be closed and a new one opened at the
same path mid-drive (:meth:`Player.reopen_pty`), like a USB receiver unplugged and plugged back in.
"""

from __future__ import annotations

import contextlib
import heapq
import logging
import os
import re
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import can

log = logging.getLogger(__name__)

_PREFIX = re.compile(rb"^\((\d+(?:\.\d*)?)\)\s?(.*)$")


@dataclass(frozen=True, slots=True)
class TimedLine:
    """An NMEA line of a log with its receive time ``t`` (s)."""

    t: float
    raw: bytes


def read_nmea_log(path: str | os.PathLike[str]) -> list[TimedLine]:
    """The receive-time-prefixed lines of an NMEA log (lines without a prefix are skipped)."""
    out = []
    with open(path, "rb") as f:
        for line in f:
            m = _PREFIX.match(line.rstrip(b"\r\n"))
            if m:
                out.append(TimedLine(float(m.group(1)), m.group(2)))
    return out


class Pty:
    """A pseudo-terminal whose slave is reachable at ``link`` (a symlink re-pointed on every reopen)."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master = -1
        self.slave = -1
        self.open()

    def open(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        tmp = self.link.with_name(self.link.name + ".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(os.ttyname(self.slave))
        os.replace(tmp, self.link)

    def write(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except OSError as e:  # nobody reading (yet): a receiver talks whether or not anyone listens
            log.debug("pty write failed: %s", e)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self.slave = -1

    def unlink(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.link.unlink()


class TcpNmeaServer:
    """NMEA over TCP (like a networked receiver or ser2net): every line goes to every connected client.

    A service reads it with ``gps.port = "socket://HOST:PORT"`` (pyserial's URL handler).
    """

    def __init__(self, host: str, port: int) -> None:
        self._server = socket.create_server((host, port), reuse_port=False)
        self._server.settimeout(0.2)
        self.address = self._server.getsockname()[:2]
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, name="sumhe-nmea-tcp", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with self._lock:
                self._clients.append(conn)

    def write(self, data: bytes) -> None:
        with self._lock:
            for conn in list(self._clients):
                try:
                    conn.sendall(data)
                except OSError:
                    self._clients.remove(conn)
                    conn.close()

    def close(self) -> None:
        self._stop.set()
        self._server.close()
        self._thread.join(1.0)
        with self._lock:
            for conn in self._clients:
                conn.close()
            self._clients.clear()


class Player:
    """Plays CAN frames and NMEA lines in time order in a thread; ``stop()`` ends it early."""

    def __init__(
        self,
        frames: Iterable[can.Message],
        lines: Iterable[TimedLine],
        bus: can.BusABC | None,
        pty: Pty | TcpNmeaServer | None,
        speed: float = 1.0,
        clock: Callable[[], float] = time.time,
    ) -> None:
        if speed <= 0:
            raise ValueError("speed: must be positive")
        self.frames = list(frames)
        self.lines = list(lines)
        self.bus = bus
        self.pty = pty
        self.speed = speed
        self.clock = clock
        self.sent_frames = 0
        self.sent_lines = 0
        self.send_errors = 0
        self.t0 = min([f.timestamp for f in self.frames[:1]] + [ln.t for ln in self.lines[:1]], default=0.0)
        self.paused_can = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.start_t = 0.0
        self.on_start: Callable[[], None] | None = None

    def _events(self) -> Iterator[tuple[float, can.Message | TimedLine]]:
        frames = ((f.timestamp, f) for f in self.frames)
        lines = ((ln.t, ln) for ln in self.lines)
        return heapq.merge(frames, lines, key=lambda e: e[0])

    def run(self) -> None:
        """Play everything (blocking)."""
        wall0 = time.monotonic()
        self.start_t = self.clock()
        if self.on_start is not None:
            self.on_start()
        for t, event in self._events():
            delay = wall0 + (t - self.t0) / self.speed - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            if self._stop.is_set():
                return
            if isinstance(event, TimedLine):
                if self.pty is not None:
                    self.pty.write(event.raw + b"\r\n")
                    self.sent_lines += 1
            elif self.bus is not None and not self.paused_can.is_set():
                self._send(event, self.start_t + (t - self.t0))

    def _send(self, frame: can.Message, stamp: float) -> None:
        msg = can.Message(
            timestamp=stamp,
            arbitration_id=frame.arbitration_id,
            is_extended_id=frame.is_extended_id,
            data=frame.data,
            dlc=frame.dlc,
        )
        try:
            assert self.bus is not None
            self.bus.send(msg)
            self.sent_frames += 1
        except can.CanError as e:
            self.send_errors += 1
            log.debug("CAN send failed: %s", e)

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="sumhe-player", daemon=True)
        self._thread.start()

    def request_stop(self) -> None:
        """Ask the playing loop to end (safe from a signal handler)."""
        self._stop.set()

    def stop(self) -> None:
        self.request_stop()
        if self._thread is not None:
            self._thread.join(2.0)

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the end of the drive; True when it ended."""
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def reopen_pty(self) -> None:
        """Close the pseudo-terminal and open a new one at the same link (a receiver unplugged and back)."""
        if isinstance(self.pty, Pty):
            self.pty.close()
            self.pty.open()
