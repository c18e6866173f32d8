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

Receive times after a stall: a terminal gives no kernel receive time for its bytes (``SO_TIMESTAMP`` is for
sockets; pyserial reads a tty), so a line is stamped when it is read. When the service stalls (``SIGSTOP``, a
swapped-out process, a long garbage collection) the receiver's epochs pile up in the port's buffer and are read
at once, all with one time: the front-end would drop all but the first as "back in time". :class:`ReceiveTimes`
mends that from the fixes' own UTC time: it keeps the lowest recent offset of read time minus UTC time (the
quickest delivery seen, over ``OFFSET_HISTORY`` fixes); a fix read more than ``BACKLOG_S`` later than that offset
says, or read together with a later epoch, was read from a backlog and is stamped ``UTC + offset`` instead
(counted ``restamped``). Fixes without a date
(GGA alone) keep their read time.

A read error or end of file (device unplugged, pseudo-terminal closed) makes the base class close the port and
reopen it with capped back-off, so the source resumes when the device comes back at the same path.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import time
from collections import deque
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

BACKLOG_S = 0.5
"""A fix read this much later than its UTC time and the lowest recent offset say is from a backlog (s)."""
MIN_STEP_S = 0.001
"""A fix stamped anew comes at least this long after the previous one (s)."""
OFFSET_HISTORY = 64
"""Fixes whose read-time-minus-UTC offsets are remembered (6 s at 10 Hz)."""

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


class ReceiveTimes:
    """Stamps a fix read from a backlog with the time it was most likely received (the module docstring)."""

    def __init__(self) -> None:
        self._offsets: deque[float] = deque(maxlen=OFFSET_HISTORY)
        self._last_t = -math.inf
        self.restamped = 0

    def stamp(self, fix: GnssFix, queued: bool = False) -> GnssFix:
        """``fix`` with ``t`` moved back to ``UTC + lowest recent offset`` if it was read from a backlog: read
        ``BACKLOG_S`` later than that, or ``queued`` (a later epoch came in the same read); never before the
        previous fix's time."""
        if fix.time_utc is None:
            return fix
        utc = fix.time_utc.timestamp()
        offset = fix.t - utc
        self._offsets.append(offset)
        lowest = min(self._offsets)
        if offset - lowest > BACKLOG_S or (queued and offset > lowest):
            self.restamped += 1
            fix = dataclasses.replace(fix, t=max(utc + lowest, self._last_t + MIN_STEP_S))
        self._last_t = fix.t
        return fix


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
        self.receive_times = ReceiveTimes()
        self.report_every_s = report_every_s
        self._reported_bad = 0
        self._next_report = time.monotonic() + report_every_s

    def counters(self) -> dict[str, object]:
        """The source's counters and the fixes stamped anew after a backlog (``restamped``)."""
        return {**vars(self.stats), "restamped": self.receive_times.restamped}

    def _read(self) -> list[GnssFix]:
        """The fixes the next read completes, each stamped (:class:`ReceiveTimes`) as queued where a later epoch
        came in the same read: a later fix, or the lines of the epoch the decoder is still assembling (whose fix
        comes with a later read, stamped with this read's time too: unmarked, a backlog read in two parts ended with
        two fixes of one time, the second dropped as not newer)."""
        lines, idle = self.port.read()
        fixes = [fix for line in lines for fix in self.decoder.feed(line.raw, t=line.t)]
        followed = not idle and self.decoder.assembling
        if idle:
            fixes.extend(self.decoder.close_epoch())
        self._report()
        last = len(fixes) - 1
        return [self.receive_times.stamp(fix, queued=i < last or followed) for i, fix in enumerate(fixes)]

    def _report(self) -> None:
        """Log the decoder counters now and then when bad input arrived since the last report."""
        now = time.monotonic()
        if now < self._next_report:
            return
        self._next_report = now + self.report_every_s
        c = self.decoder.counters
        bad = c.checksum_errors + c.garbled + c.late + c.backwards + c.implausible
        if bad > self._reported_bad:
            self._reported_bad = bad
            log.warning("%s: bad NMEA input so far: %s", self.name, c.summary())
