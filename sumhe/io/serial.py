"""The live GNSS receiver on a serial port (pyserial), as :class:`~sumhe.io.source.ThreadedSource` s.

:class:`SerialLineSource` yields every line as received (:class:`NmeaLine`, for ``sumhe record``);
:class:`SerialNmeaSource` yields :class:`~sumhe.messages.GnssFix` es decoded by :class:`~sumhe.io.nmea.NmeaDecoder`,
each stamped with the source clock (``time.time()`` unless another is given) when its first line arrived.

The reader reads whatever bytes are waiting, splits them at CR or LF and stamps each completed line with the arrival
time of the chunk that completed it. A read that waits ``idle_s`` (default 50 ms) without a byte is an *idle gap*:
receivers send an epoch's sentences as one burst, so the gap closes the epoch being assembled and its fix is emitted
``idle_s`` after its last line rather than when the next epoch starts. Where bursts follow each other with no idle
gap (high rates), the epochs end on a time change, the decoder learns the receiver's last sentence of a cycle and
from then on emits each epoch on that sentence. (Emitting as soon as GGA and RMC are in would drop what many
receivers send after them: GST sigmas on the u-blox F9P and the Quectel L70, HDT heading on the Saab R4.) A line
longer than ``MAX_LINE`` bytes (binary noise) is cut there.

A read error or end of file (device unplugged, pseudo-terminal closed) makes the base class close the port and
reopen it with capped back-off, so the source resumes when the device comes back at the same path.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import serial

from sumhe.config import GpsSettings
from sumhe.errors import ConfigError
from sumhe.io.nmea import NmeaDecoder
from sumhe.io.source import ThreadedSource
from sumhe.messages import GnssFix

log = logging.getLogger(__name__)

IDLE_S = 0.05
"""Silence on the line after which the epoch being assembled is complete (s)."""
MAX_LINE = 4096
"""Longest line kept whole (bytes); longer runs without CR/LF are binary noise and are cut."""
REPORT_EVERY_S = 60.0
"""How often :class:`SerialNmeaSource` logs its decoder counters, if bad input arrived meanwhile (s)."""

T = TypeVar("T")
_LINE_END = re.compile(rb"[\r\n]+")


@dataclass(frozen=True, slots=True)
class NmeaLine:
    """One line as received: ``t`` is its receive time (s, the source clock), ``raw`` its bytes without CR/LF."""

    t: float
    raw: bytes


class SerialLines:
    """A serial port read as lines stamped with their arrival time (blocking; used by the reader thread)."""

    def __init__(
        self, port: str, baudrate: int, idle_s: float = IDLE_S, clock: Callable[[], float] = time.time
    ) -> None:
        if idle_s <= 0:
            raise ValueError("idle_s: must be positive")
        self.port = port
        self.baudrate = baudrate
        self.idle_s = idle_s
        self.clock = clock
        self._serial: serial.Serial | None = None
        self._pending = b""

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    def open(self) -> None:
        """Open the port (raises ``serial.SerialException`` when it is not there)."""
        self.close()
        self._serial = serial.serial_for_url(self.port, self.baudrate, timeout=self.idle_s)
        self._pending = b""

    def read(self) -> tuple[list[NmeaLine], bool]:
        """The lines completed by the next chunk, and whether the port was idle for ``idle_s`` instead.

        After an idle gap a pending unterminated line is returned as it is. Raises on a vanished device.
        """
        if self._serial is None:
            raise serial.SerialException(f"{self.port}: not open")
        data = self._serial.read(max(1, self._serial.in_waiting))
        t = self.clock()
        if not data:
            rest, self._pending = self._pending.strip(b"\r\n"), b""
            return ([NmeaLine(t, rest)] if rest else []), True
        *lines, self._pending = _LINE_END.split(self._pending + data)
        if len(self._pending) > MAX_LINE:
            lines.append(self._pending)
            self._pending = b""
        return [NmeaLine(t, raw) for raw in lines if raw], False

    def close(self) -> None:
        """Close the port (idempotent)."""
        port, self._serial = self._serial, None
        if port is not None:
            port.close()


class _SerialSource(ThreadedSource[T]):
    """Shared open/close of the two serial sources; subclasses read."""

    def __init__(self, settings: GpsSettings, idle_s: float = IDLE_S, clock: Callable[[], float] = time.time) -> None:
        if not settings.port:
            raise ConfigError("gps.port: no serial port configured")
        super().__init__(settings.receive_timeout_s, settings.queue_size, settings.reconnect_max_s)
        self.name = f"gps {settings.port}"
        self.port = SerialLines(settings.port, settings.baudrate, idle_s, clock)

    def _open(self) -> None:
        self.port.open()

    def _close(self) -> None:
        self.port.close()


class SerialLineSource(_SerialSource[NmeaLine]):
    """Every line the receiver sends, with its receive time (for recording)."""

    def _read(self) -> list[NmeaLine]:
        return self.port.read()[0]


class SerialNmeaSource(_SerialSource[GnssFix]):
    """Fixes decoded from the receiver; ``decoder.counters`` says what was seen on the line."""

    def __init__(
        self,
        settings: GpsSettings,
        idle_s: float = IDLE_S,
        decoder: NmeaDecoder | None = None,
        report_every_s: float = REPORT_EVERY_S,
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(settings, idle_s, clock)
        self.decoder = NmeaDecoder() if decoder is None else decoder
        self.report_every_s = report_every_s
        self._reported_bad = 0
        self._next_report = time.monotonic() + report_every_s

    def _read(self) -> list[GnssFix]:
        lines, idle = self.port.read()
        fixes = [fix for line in lines for fix in self.decoder.feed(line.raw, t=line.t)]
        if idle:
            fixes.extend(self.decoder.close_epoch())
        self._report()
        return fixes

    def _report(self) -> None:
        """Log the decoder counters now and then when bad input arrived since the last report."""
        now = time.monotonic()
        if now < self._next_report:
            return
        self._next_report = now + self.report_every_s
        c = self.decoder.counters
        bad = c.checksum_errors + c.garbled + c.late + c.backwards
        if bad > self._reported_bad:
            self._reported_bad = bad
            log.warning("%s: bad NMEA input so far: %s", self.name, c.summary())
