"""Live CAN input on any python-can interface, as :class:`~sumhe.io.source.ThreadedSource` s.

:class:`CanFrameSource` yields raw :class:`can.Message` s (for ``sumhe record``); :class:`CanBusSource` yields
SI :class:`~sumhe.messages.CanSample` s (and, with ``gps.source = "can"``, :class:`~sumhe.messages.GnssFix` es)
through a :class:`~sumhe.io.can.CanDecoder`, with kernel/hardware filters for the ids in use. The reader thread
calls ``bus.recv`` itself (python-can's ``Notifier`` thread would just die on a bus error): a
:class:`can.CanOperationError` (socketcan: the link went down) or a bus-off error frame closes the bus, and the
base class reopens it with capped back-off.
"""

from __future__ import annotations

import logging
from abc import abstractmethod
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


class _CanSource(ThreadedSource[T]):
    """Opens ``can.Bus(interface, channel, bitrate, can_filters)`` and reads it; subclasses convert frames."""

    name = "can"

    def __init__(self, settings: CanSettings, can_filters: list[dict[str, Any]] | None = None) -> None:
        if settings.interface not in can.VALID_INTERFACES:
            known = ", ".join(sorted(can.VALID_INTERFACES))
            raise ConfigError(f"can.interface: unknown python-can interface {settings.interface!r} ({known})")
        super().__init__(settings.receive_timeout_s, settings.queue_size, settings.reconnect_max_s)
        self.settings = settings
        self.can_filters = can_filters
        self.bus: can.BusABC | None = None

    def _open(self) -> None:
        s = self.settings
        kwargs: dict[str, Any] = {"interface": s.interface, "channel": s.channel, "can_filters": self.can_filters}
        if s.bitrate is not None:
            kwargs["bitrate"] = s.bitrate
        self.bus = can.Bus(**kwargs)
        log.info("%s: opened %s %s", self.name, s.interface, s.channel)

    def _read(self) -> list[T]:
        assert self.bus is not None
        out: list[T] = []
        msg = self.bus.recv(POLL_S)
        while msg is not None:
            if msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF:
                raise SourceError(f"{self.settings.channel}: controller is bus-off")
            out.extend(self._convert(msg))
            if len(out) >= BATCH:
                break
            msg = self.bus.recv(0.0)
        return out

    def _close(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            bus.shutdown()

    @abstractmethod
    def _convert(self, msg: can.Message) -> list[T]:
        """The items one frame gives (runs in the reader thread)."""


class CanFrameSource(_CanSource[can.Message]):
    """Raw frames of the configured bus (all ids unless ``can_filters`` is given), e.g. for recording."""

    @classmethod
    def from_config(cls, config: Config, can_filters: list[dict[str, Any]] | None = None) -> CanFrameSource:
        return cls(config.can, can_filters)

    def _convert(self, msg: can.Message) -> list[can.Message]:
        return [msg]


class CanBusSource(_CanSource[Sample]):
    """Decoded SI samples (and GNSS fixes decoded from CAN) of the configured bus; only the ids in use pass the bus
    filters."""

    def __init__(self, settings: CanSettings, decoder: CanDecoder) -> None:
        super().__init__(settings, decoder.can_filters())
        self.decoder = decoder

    @classmethod
    def from_config(cls, config: Config) -> CanBusSource:
        """Load the DBCs and mapping of ``config`` (ConfigError on any mistake) and prepare the source. The live
        bus is one channel: a mapping that names another (as for a logger's multi-bus files) is a ConfigError."""
        decoder = CanDecoder.from_config(config)
        for name, channel in decoder.channels().items():
            if channel != config.can.channel:
                raise ConfigError(
                    f"{config.source}: {name}.channel: {channel!r}, but the live bus is can.channel = "
                    f"{config.can.channel!r} (channels tell apart the buses of recorded logs; drop it for a live bus)"
                )
        return cls(config.can, decoder)

    def _convert(self, msg: can.Message) -> list[Sample]:
        return self.decoder.decode(msg)
