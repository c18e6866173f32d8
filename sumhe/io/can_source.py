"""Live CAN input on any python-can interface, as :class:`~sumhe.io.source.ThreadedSource` s.

:class:`CanFrameSource` yields raw :class:`can.Message` s (for ``sumhe record``); :class:`CanBusSource` yields
SI :class:`~sumhe.messages.CanSample` s (and, with ``gps.source = "can"``, :class:`~sumhe.messages.GnssFix` es)
through a :class:`~sumhe.io.can.CanDecoder`, with kernel/hardware filters for the ids in use. The reader thread
calls ``bus.recv`` itself (python-can's ``Notifier`` thread would just die on a bus error): a
:class:`can.CanOperationError` (socketcan: the link went down) or a bus-off error frame closes the bus, and the
base class reopens it with capped back-off.

Open failures (:func:`explain_open_error`, :func:`is_permanent`). Retried, with the reason and the fix in the log:
the link is down (``ENETDOWN``), the device is busy or not ready (python-can's ``CanInitializationError``,
``CanOperationError``), any other errno, and every failure once the bus has been open (an adapter unplugged and
plugged back in). Permanent at start-up, so ``sumhe run`` exits 1 with the message: the kernel has no SocketCAN
(``EAFNOSUPPORT``, ``EPROTONOSUPPORT``), the interface does not exist (``ENODEV``: a typo, or vcan0 not created),
no permission (``EPERM``, ``EACCES``), and a missing driver (python-can's ``CanInterfaceNotImplementedError``, an
import failure, an ``OSError`` without errno such as pcan's "pcanbasic library not found", or any other error that
is not python-can's or the system's). The messages name the interface and channel and say how to fix it.

SocketCAN buses are opened with CAN FD frames enabled, so FD frames on the bus reach the decoder, which counts
and ignores those on classic messages' ids; error frames are counted there too (a bus-off one reopens the bus).

Frames lost before they were read (:class:`FrameGaps`): when the service stalls, the socket's receive buffer
overflows and the kernel drops frames. SocketCAN counts them (``SO_RXQ_OVFL``), but python-can does not read that
ancillary data, and buses over UDP (udp_multicast) have no such count; so the loss is inferred from the gaps in
each id's periodic frames and counted ``lost`` (a sender that pauses for up to ``MAX_LOST_GAP_S`` looks the same).

Timestamps (:class:`ClockRebase`): frame times must be Unix time on the host clock (the kernel's are). An adapter
whose first frame after opening is more than :data:`REBASE_AFTER_S` away from the host clock counts from
something else (python-can's pcan without the ``uptime`` package: time since boot); its times are then re-based
on the host clock, logged once.
"""

from __future__ import annotations

import errno
import logging
import time
from abc import abstractmethod
from collections import deque
from collections.abc import Callable
from typing import Any, TypeVar

import can

from sumhe.config import CanSettings, Config
from sumhe.errors import ConfigError, SourceError
from sumhe.io.can import CanDecoder
from sumhe.io.source import ThreadedSource
from sumhe.messages import Sample

log = logging.getLogger(__name__)

T = TypeVar("T")

CAN_ERR_BUSOFF = 0x40
"""Error class bit of a socketcan error frame (``linux/can/error.h``): the controller went bus-off."""

POLL_S = 0.2
"""Longest blocking ``recv``: how soon the reader thread notices a stop request."""

BATCH = 64
"""Most frames handed to the event loop per wake-up (frames already waiting are read without blocking)."""

REBASE_AFTER_S = 60.0
"""A first frame further than this from the host clock is not stamped in Unix time (s). Larger than any stall
(frames waiting in a socket buffer), which the service's stale-sample check handles."""

REBASE_WINDOW_S = 10.0
"""The re-basing offset is the smallest (receive time - adapter time) of the frames of this last span (s): the
frames that waited least, so the adapter's clock drift never accumulates."""

NO_AF_CAN = (errno.EAFNOSUPPORT, errno.EPROTONOSUPPORT)
NO_PERMISSION = (errno.EPERM, errno.EACCES)


GAP_PERIODS = 2.5
"""A silence of an id longer than this many of its periods counts the frames it missed as ``lost``."""
MAX_LOST_GAP_S = 10.0
"""Longer silences are a sender that stopped (or a bus that went quiet), not lost frames."""
PERIOD_SMOOTHING = 0.1
"""Weight of a new regular interval in an id's period estimate."""


class FrameGaps:
    """Frames lost before they were read, inferred from the gaps in each id's periodic frames (module docstring)."""

    def __init__(self) -> None:
        self._last: dict[int, float] = {}
        self._period: dict[int, float] = {}
        self.lost = 0

    def see(self, arbitration_id: int, t: float) -> None:
        """A frame of ``arbitration_id`` received at ``t`` (s)."""
        last = self._last.get(arbitration_id)
        self._last[arbitration_id] = t
        if last is None or not t > last:
            return
        dt = t - last
        period = self._period.get(arbitration_id)
        if period is None:
            self._period[arbitration_id] = dt
        elif GAP_PERIODS * period < dt <= MAX_LOST_GAP_S:
            self.lost += round(dt / period) - 1
        elif dt <= GAP_PERIODS * period:
            self._period[arbitration_id] = period + PERIOD_SMOOTHING * (dt - period)


class ClockRebase:
    """Maps adapter timestamps to the host clock when they are not Unix time (see the module docstring)."""

    def __init__(self, name: str, clock: Callable[[], float] = time.time) -> None:
        self.name = name
        self.clock = clock
        self.active: bool | None = None
        """None until the first frame after :meth:`restart`; then whether times are re-based."""
        self.logged = False
        self._delays: deque[tuple[float, float]] = deque()

    def restart(self) -> None:
        """A new connection: the adapter's clock may have restarted; decide again at the next frame."""
        self.active = None
        self._delays.clear()

    def __call__(self, stamp: float) -> float:
        """The frame time on the host clock (s)."""
        now = self.clock()
        if self.active is None:
            self.active = abs(now - stamp) > REBASE_AFTER_S
            if self.active and not self.logged:
                self.logged = True
                log.info(
                    "%s: frame times are not Unix time (first frame at %.3f s, host clock %.3f s): "
                    "re-based on the host clock (logged once)",
                    self.name,
                    stamp,
                    now,
                )
        if not self.active:
            return stamp
        delay = now - stamp
        delays = self._delays
        while delays and delays[-1][1] >= delay:
            delays.pop()
        delays.append((now, delay))
        while delays[0][0] < now - REBASE_WINDOW_S:
            delays.popleft()
        return stamp + delays[0][1]


def _errno(err: BaseException) -> int | None:
    """The errno of an OSError, or of the OSError python-can wrapped (its ``__cause__``/``error_code``)."""
    seen: BaseException | None = err
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno is not None:
            return seen.errno
        code = getattr(seen, "error_code", None)
        if isinstance(seen, can.CanError) and isinstance(code, int):
            return code
        seen = seen.__cause__
    return None


RESTART_MS = 100
"""Bus-off auto-recovery delay of a real controller (ms) set by :func:`link_commands` (the daemon also reopens
the bus after bus-off)."""


def link_commands(channel: str, bitrate: int | str, exists: bool, up: bool) -> list[list[str]]:
    """The commands that make a SocketCAN ``channel`` exist and be up: a ``vcan*`` is created (``modprobe vcan``,
    ``ip link add``) and set up; a real one is (re)started at ``bitrate`` with bus-off auto-recovery."""
    if channel.startswith("vcan"):
        create = [] if exists else [["modprobe", "vcan"], ["ip", "link", "add", "dev", channel, "type", "vcan"]]
        return [*create, *([] if up else [["ip", "link", "set", "up", channel]])]
    bring_up = ["ip", "link", "set", channel, "up", "type", "can", "bitrate", str(bitrate)]
    bring_up += ["restart-ms", str(RESTART_MS)]
    return [*([["ip", "link", "set", channel, "down"]] if up else []), bring_up]


def bring_up_hint(settings: CanSettings) -> str:
    """The shell commands that create and bring up the configured SocketCAN channel."""
    commands = link_commands(settings.channel, settings.bitrate or "BITRATE", exists=False, up=False)
    return "; ".join(" ".join(cmd) for cmd in commands)


def explain_open_error(settings: CanSettings, err: BaseException) -> str:
    """What a failure to open (or read) the bus means, naming interface and channel, with the fix."""
    where = f"{settings.interface} channel {settings.channel!r}"
    code = _errno(err)
    fix = ""
    if settings.interface == "socketcan":
        if code in NO_AF_CAN:
            fix = (
                "this kernel has no SocketCAN (AF_CAN): load it (modprobe can_raw), or set can.interface to one "
                "that needs none (virtual, udp_multicast, pcan, ...)"
            )
        elif code == errno.ENODEV:
            fix = f"no such interface: create it (`{bring_up_hint(settings)}`, or `sumhe can-up --config FILE`)"
            if not settings.channel.startswith("vcan"):
                fix = f"no such interface: plug in the adapter, load its driver, then `{bring_up_hint(settings)}`"
        elif code == errno.ENETDOWN:
            up = link_commands(settings.channel, settings.bitrate or "BITRATE", exists=True, up=False)
            fix = f"the interface is down: `{'; '.join(' '.join(c) for c in up)}`"
    if code in NO_PERMISSION:
        fix = "permission denied: run as a user allowed to open it"
    if isinstance(err, can.CanInterfaceNotImplementedError | ImportError) or (
        isinstance(err, OSError) and err.errno is None
    ):
        fix = f"the {settings.interface} driver is missing (install its library; see python-can's interface docs)"
    return f"cannot use {where}: {err}" + (f" ({fix})" if fix else "")


def is_permanent(settings: CanSettings, err: BaseException, connected_before: bool) -> bool:
    """Whether an open failure cannot mend by retrying (see the module docstring)."""
    if connected_before:
        return False
    code = _errno(err)
    if isinstance(err, can.CanInterfaceNotImplementedError):
        return True
    if isinstance(err, can.CanError):
        return code in NO_AF_CAN or code in NO_PERMISSION
    if isinstance(err, OSError):
        if code is None or code in NO_AF_CAN or code in NO_PERMISSION:
            return True
        return code == errno.ENODEV and settings.interface == "socketcan"
    return True


class _CanSource(ThreadedSource[T]):
    """Opens ``can.Bus(interface, channel, bitrate, can_filters, **bus)`` and reads it; subclasses convert frames."""

    name = "can"

    def __init__(
        self,
        settings: CanSettings,
        can_filters: list[dict[str, Any]] | None = None,
        origin: str = "<config>",
        clock: Callable[[], float] = time.time,
    ) -> None:
        if settings.interface not in can.VALID_INTERFACES:
            known = ", ".join(sorted(can.VALID_INTERFACES))
            raise ConfigError(f"{origin}: can.interface: unknown python-can interface {settings.interface!r} ({known})")
        super().__init__(settings.receive_timeout_s, settings.queue_size, settings.reconnect_max_s)
        self.settings = settings
        self.can_filters = can_filters
        self.bus: can.BusABC | None = None
        self.rebase = ClockRebase(self.name, clock)
        self.gaps = FrameGaps()

    def _open(self) -> None:
        s = self.settings
        kwargs: dict[str, Any] = {**s.bus, "interface": s.interface, "channel": s.channel}
        kwargs["can_filters"] = self.can_filters
        if s.bitrate is not None:
            kwargs["bitrate"] = s.bitrate
        if s.interface == "socketcan":
            kwargs["fd"] = True  # FD frames reach the decoder, which counts and ignores them on classic ids
        self.bus = can.Bus(**kwargs)
        self.rebase.restart()
        log.info("%s: opened %s %s", self.name, s.interface, s.channel)

    def _read(self) -> list[T]:
        assert self.bus is not None
        out: list[T] = []
        msg = self.bus.recv(POLL_S)
        while msg is not None:
            if msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF:
                raise SourceError(f"{self.settings.channel}: controller is bus-off")
            msg.timestamp = self.rebase(msg.timestamp)
            if not msg.is_error_frame:
                self.gaps.see(msg.arbitration_id, msg.timestamp)
            out.extend(self._convert(msg))
            if len(out) >= BATCH:
                break
            msg = self.bus.recv(0.0)
        return out

    def _close(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            bus.shutdown()

    def _explain(self, err: Exception) -> str:
        return explain_open_error(self.settings, err)

    def _permanent(self, err: Exception, connected_before: bool) -> bool:
        return is_permanent(self.settings, err, connected_before)

    @abstractmethod
    def _convert(self, msg: can.Message) -> list[T]:
        """The items one frame gives (runs in the reader thread)."""


class CanFrameSource(_CanSource[can.Message]):
    """Raw frames of the configured bus (all ids unless ``can_filters`` is given), e.g. for recording."""

    @classmethod
    def from_config(cls, config: Config, can_filters: list[dict[str, Any]] | None = None) -> CanFrameSource:
        return cls(config.can, can_filters, config.blame("can.interface"))

    def _convert(self, msg: can.Message) -> list[can.Message]:
        return [msg]


class CanBusSource(_CanSource[Sample]):
    """Decoded SI samples (and GNSS fixes decoded from CAN) of the configured bus; only the ids in use pass the bus
    filters."""

    def __init__(
        self,
        settings: CanSettings,
        decoder: CanDecoder,
        origin: str = "<config>",
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(settings, decoder.can_filters(), origin, clock)
        self.decoder = decoder

    @classmethod
    def from_config(cls, config: Config, clock: Callable[[], float] = time.time) -> CanBusSource:
        """Load the DBCs and mapping of ``config`` (ConfigError on any mistake) and prepare the source. The live
        bus is one channel: a mapping that names another (as for a logger's multi-bus files) is a ConfigError."""
        decoder = CanDecoder.from_config(config)
        for name, channel in decoder.channels().items():
            if channel != config.can.channel:
                raise config.error(
                    f"{name}.channel",
                    f"{channel!r}, but the live bus is can.channel = {config.can.channel!r} (channels tell apart "
                    "the buses of recorded logs; drop it for a live bus)",
                )
        return cls(config.can, decoder, config.blame("can.interface"), clock)

    def _convert(self, msg: can.Message) -> list[Sample]:
        return self.decoder.decode(msg)

    def counters(self) -> dict[str, object]:
        """The source's counters, the frames lost before they were read (inferred) and the decoder's (frames seen,
        decoded, unused, bad, error, FD and over-long frames)."""
        s = self.decoder.stats
        return {
            **super().counters(),
            "lost": self.gaps.lost,
            "frames": s.frames,
            "decoded": s.decoded,
            "unused": s.unused,
            "decode_errors": s.decode_errors,
            "crc_errors": s.crc_errors,
            "stale": s.stale,
            "error_frames": s.error_frames,
            "fd_frames": s.fd_frames,
            "long_frames": s.long_frames,
            "remote_frames": s.remote_frames,
        }
