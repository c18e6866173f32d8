"""CAN frames to SI samples: the DBCs, the configured signal mapping, end-to-end checks, and log files.

Pure decoding, no bus I/O: the live source (:mod:`sumhe.io.can_source`), the log replay and the ``candump``
command share :class:`CanDecoder`. The decoder is built once from the DBCs, ``can.signals`` and (with
``gps.source = "can"``) ``gps.signals``: each quantity's unit factor to SI is resolved at construction from the
DBC's unit string (or the spec's ``unit`` override), times the spec's ``scale``; frames whose id (on their bus
channel) is not in use are dropped by one dict lookup before any decoding. A yaw rate mapped to a 3-axis IMU's six
signals is its angular rate about the up direction (:mod:`sumhe.io.imu`).

Multiplexed messages (e.g. OBD-II mode 01 replies, multiplexed by PID): the multiplexer is decoded first; a
frame whose multiplexer selects none of the mapped signals (another PID, or one the DBC does not know) carries
nothing for us and is counted as ``other_mux``, not as an error. GNSS quantities go to a
:class:`~sumhe.io.can_gnss.GnssAssembler`, which makes one :class:`~sumhe.messages.GnssFix` per epoch.

End-to-end protection: the messages named in ``can.e2e`` (default none; the reference DBC protects
ESP_YAW_RATE and ESP_VEHICLE_SPEED, as its comments say) carry a CRC-8/SAE-J1850 in byte 0 over the other bytes
and a 4-bit rolling counter in the low nibble of byte 1 (:mod:`sumhe.io.checksum`). A bad CRC drops the frame;
a repeated counter (stale frame) drops it; a counter jump (frames lost) is counted and the frame used. The
scheme is named in configuration, not guessed from DBC comments, because DBCs describe it only in free text.
"""

from __future__ import annotations

import copy
import gzip
import heapq
import importlib.util
import io
import itertools
import logging
import math
import os
import re
import time
from collections import deque
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any, TextIO

import can
import cantools
from cantools.database.can import Database, Message, Signal
from cantools.database.utils import create_encode_decode_formats

from sumhe.config import IMU_QUANTITY, Config, SignalSpec, load_config
from sumhe.errors import ConfigError, SourceError, printable
from sumhe.io.can_gnss import GnssAssembler
from sumhe.io.checksum import is_intact, rolling_counter
from sumhe.io.imu import Mounting, VerticalRate
from sumhe.messages import CAN_QUANTITIES, GNSS_QUANTITIES, CanSample, GnssFix, Sample

log = logging.getLogger(__name__)

EXTENDED_FLAG = 0x80000000
"""Added to a 29-bit id to form the lookup key, so an 11-bit and a 29-bit id never collide."""

REFERENCE_SIGNALS: dict[str, str] = {
    "speed": "ESP_VEHICLE_SPEED.VEHICLE_SPEED",
    "yaw_rate": "ESP_YAW_RATE.YAW_RATE",
    "wheel_speed_fl": "ESP_WHEEL_SPEEDS.WHEEL_SPEED_FL",
    "wheel_speed_fr": "ESP_WHEEL_SPEEDS.WHEEL_SPEED_FR",
    "wheel_speed_rl": "ESP_WHEEL_SPEEDS.WHEEL_SPEED_RL",
    "wheel_speed_rr": "ESP_WHEEL_SPEEDS.WHEEL_SPEED_RR",
    "steering_angle": "EPS_STEERING.STEERING_ANGLE",
    "lat_accel": "ESP_YAW_RATE.LAT_ACCEL",
    "lon_accel": "ESP_YAW_RATE.LON_ACCEL",
}
"""The mapping for ``dbc/sumhe_ref.dbc`` (as in ``configs/default.toml``), used when no config is given."""

REFERENCE_E2E: tuple[str, ...] = ("ESP_YAW_RATE", "ESP_VEHICLE_SPEED")
"""The messages of ``dbc/sumhe_ref.dbc`` that carry CRC and rolling counter."""


def reference_config() -> Config:
    """Defaults plus the reference vehicle's signal mapping and end-to-end protected messages (what the commands
    use without ``--config``)."""
    return load_config(None, overrides={"can.signals": REFERENCE_SIGNALS, "can.e2e": list(REFERENCE_E2E)})


_DEG = math.pi / 180.0
_KMH = 1.0 / 3.6
_UNITS: dict[str, dict[str, float]] = {
    "speed": {
        "m/s": 1.0,
        "mps": 1.0,
        "m/sec": 1.0,
        "km/h": _KMH,
        "kph": _KMH,
        "kmh": _KMH,
        "kmph": _KMH,
        "mph": 0.44704,
    },
    "angular rate": {
        "rad/s": 1.0,
        "rad/sec": 1.0,
        "deg/s": _DEG,
        "deg/sec": _DEG,
        "°/s": _DEG,
        "degree/s": _DEG,
        "degrees/s": _DEG,
        "dps": _DEG,
    },
    "angle": {"rad": 1.0, "deg": _DEG, "°": _DEG, "degree": _DEG, "degrees": _DEG},
    "acceleration": {"m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0, "m/s/s": 1.0, "mps2": 1.0, "g": 9.80665},
    "latitude/longitude (deg)": {"deg": 1.0, "°": 1.0, "degree": 1.0, "degrees": 1.0, "rad": 1.0 / _DEG},
    "length": {"m": 1.0, "cm": 0.01, "mm": 0.001, "km": 1000.0, "ft": 0.3048},
    "time": {"s": 1.0, "sec": 1.0, "second": 1.0, "seconds": 1.0, "ms": 0.001},
    "count": {"": 1.0},
}
_KIND_OF: dict[str, str] = {
    "speed": "speed",
    "wheel_speed_fl": "speed",
    "wheel_speed_fr": "speed",
    "wheel_speed_rl": "speed",
    "wheel_speed_rr": "speed",
    "yaw_rate": "angular rate",
    "steering_angle": "angle",
    "lat_accel": "acceleration",
    "lon_accel": "acceleration",
    "lat": "latitude/longitude (deg)",
    "lon": "latitude/longitude (deg)",
    "alt": "length",
    "accuracy": "length",
    "course": "angle",
    "heading": "angle",
    "heading_accuracy": "angle",
    "time": "time",
    "sats": "count",
}
"""The kind of unit of each quantity (the GNSS ``speed`` shares the CAN one's)."""
assert set(_KIND_OF) == set(CAN_QUANTITIES) | set(GNSS_QUANTITIES)

_WARN_INTERVAL_S = 10.0


def si_factor(unit: str | None, quantity: str) -> float | None:
    """Factor from a DBC unit string to the SI unit of ``quantity`` (degrees for ``lat``/``lon``, as
    :class:`~sumhe.messages.GnssFix` holds them); None if unknown or missing (a count needs no unit).

    Case and spaces are ignored: ``"km/h"``, ``"KPH"`` and ``"Km / h"`` are all 1/3.6.
    """
    return _UNITS[_KIND_OF[quantity]].get((unit or "").strip().lower().replace(" ", ""))


def load_dbc(path: str | PathLike[str], strict: bool = True, max_mb: float = 32.0) -> Database:
    """Load a CAN database (DBC, KCD, SYM, ARXML by suffix); ConfigError naming the file on any failure, its text
    safe for a terminal (:func:`~sumhe.config.printable`: a binary file's bytes come out escaped).

    ``strict=False`` accepts databases with overlapping signals or signals past the message end, which
    several public DBCs have. A file larger than ``max_mb`` MB (``can.dbc_max_mb``) is refused unread.
    """
    try:
        size = os.stat(path).st_size
        if size > max_mb * 1e6:
            raise ConfigError(
                f"{path}: {size / 1e6:.1f} MB, larger than can.dbc_max_mb = {max_mb:g} MB: not a CAN database? "
                "(raise can.dbc_max_mb for a database this large)"
            )
        db = cantools.database.load_file(str(path), strict=strict)
    except FileNotFoundError as e:
        raise ConfigError(f"{path}: DBC file not found") from e
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read DBC: {printable(str(e))}") from e
    except cantools.database.Error as e:
        hint = " (can.dbc_strict = false accepts it)" if strict and _loads_leniently(path) else ""
        raise ConfigError(f"{path}: not a valid CAN database: {printable(str(e))}{hint}") from e
    if not isinstance(db, Database):
        raise ConfigError(f"{path}: not a CAN database")
    return db


def _loads_leniently(path: str | PathLike[str]) -> bool:
    try:
        cantools.database.load_file(str(path), strict=False)
    except cantools.database.Error:
        return False
    return True


def frame_key(arbitration_id: int, is_extended: bool) -> int:
    """The lookup key of a frame id: the id, plus :data:`EXTENDED_FLAG` for a 29-bit id."""
    return arbitration_id | EXTENDED_FLAG if is_extended else arbitration_id


class Throttle:
    """True at most once per ``interval_s`` (monotonic clock): keeps a flood of bad frames to a few log lines."""

    def __init__(self, interval_s: float = _WARN_INTERVAL_S) -> None:
        self.interval_s = interval_s
        self._next = 0.0

    def ready(self) -> bool:
        now = time.monotonic()
        if now < self._next:
            return False
        self._next = now + self.interval_s
        return True


@dataclass
class DecodeStats:
    """Counters of one decoder. ``frames`` counts every frame seen (timestamps of the first and last in
    ``first_t``/``last_t``, s; frames per bus channel in ``channels``); ``decoded`` those that gave samples;
    ``other_mux`` frames of a message in use whose multiplexer selected none of the mapped signals (another or an
    unknown PID: not an error); ``invalid`` values their ``valid`` flag signal marked invalid."""

    frames: int = 0
    first_t: float = 0.0
    last_t: float = 0.0
    unused: int = 0
    decoded: int = 0
    decode_errors: int = 0
    crc_errors: int = 0
    counter_jumps: int = 0
    frames_lost: int = 0
    stale: int = 0
    error_frames: int = 0
    fd_frames: int = 0
    """CAN FD frames on ids of classic messages (or unused ids): ignored."""
    long_frames: int = 0
    """Frames of a classic message with a longer payload than its DBC length (e.g. a 64-byte FD payload from a log
    or an MF4 record without the FD flag): refused, never decoded from their first bytes."""
    remote_frames: int = 0
    other_mux: int = 0
    invalid: int = 0
    per_message: dict[str, int] = field(default_factory=dict)
    per_quantity: dict[str, int] = field(default_factory=dict)
    channels: dict[str, int] = field(default_factory=dict)
    """Frame counts by bus channel (as text, "" for frames without one; the first :data:`MAX_CHANNELS` channels)."""
    unused_ids: dict[int, int] = field(default_factory=dict)
    """Frame counts of unused ids by :func:`frame_key` (the first :data:`MAX_UNUSED_IDS` distinct ids)."""


MAX_UNUSED_IDS = 512
MAX_CHANNELS = 64

_Condition = tuple[tuple[str, frozenset[int]], ...]
"""The multiplexer values a signal needs: (multiplexer signal, raw values selecting it) for each level."""


@dataclass(frozen=True, slots=True)
class _Field:
    """One mapped quantity of a message: its signal, factor to SI (times the spec's scale), flag signal, whether
    it is a GNSS quantity (for the :class:`GnssAssembler`) and the multiplexer values that carry it; or, for a yaw
    rate from a 3-axis IMU, the :class:`~sumhe.io.imu.VerticalRate` that makes it of the IMU's signals."""

    name: str
    """``can.signals.<quantity>`` or ``gps.signals.<quantity>``."""
    quantity: str
    signal: str
    factor: float
    valid: str | None
    gnss: bool
    needs: _Condition
    vertical: VerticalRate | None = None

    @property
    def signals(self) -> tuple[str, ...]:
        """The signals it reads (its flag signal aside)."""
        return self.vertical.signals if self.vertical is not None else (self.signal,)


@dataclass(slots=True)
class _Route:
    """How to turn the frames of one message in use (on one channel, or on all) into samples."""

    name: str
    message: Message
    length: int
    fields: tuple[_Field, ...]
    e2e: bool
    mux: Message | None
    """The message's multiplexer signals alone (decoded first: a frame carrying no mapped signal goes no further);
    None when the message is not multiplexed."""
    top: str | None
    """The name of the top multiplexer signal (None when the message is not multiplexed)."""
    mux_ids: frozenset[int]
    """The values of the top multiplexer the DBC knows."""
    gnss: bool
    """Whether the message carries GNSS quantities."""
    used: Message
    """What :meth:`CanDecoder.decode` decodes: of a message that is not multiplexed, the signals its fields read
    alone (the same values, without decoding the others: an IMU message carries a dozen); else the message."""
    unpack: Decode
    """``used`` decoding a payload (:func:`_decoding`)."""
    whole: Decode
    """``message`` decoding a payload, every signal (:func:`_decoding`; :meth:`CanDecoder.decode_signals`)."""
    last_counter: int | None = None


@dataclass(frozen=True, slots=True)
class _Mapped:
    """One quantity of the configuration: where it is set, its spec and target (CAN sample or GNSS fix)."""

    source: str
    quantity: str
    spec: SignalSpec
    gnss: bool

    @property
    def name(self) -> str:
        return f"{'gps' if self.gnss else 'can'}.signals.{self.quantity}"

    @property
    def key(self) -> str:
        """The key as config errors name it."""
        return f"{self.source}: {self.name}"


class CanDecoder:
    """Decodes the frames of the mapped messages into SI :class:`CanSample` s and, with a GNSS mapping, into
    :class:`GnssFix` es (:mod:`sumhe.io.can_gnss`); see the module docstring.

    ``dbs`` is one database or several (a message name is looked up in all of them). A spec with a ``channel``
    takes only the frames of that bus channel (``str(msg.channel)``); a spec without one the frames of every
    channel, unless a spec names that channel for the same id. With ``every_message=True`` every message of the
    databases is in use (for :meth:`decode_signals`, ``candump --all``) and ``signals`` may be empty.
    """

    def __init__(
        self,
        dbs: Database | Sequence[Database],
        signals: Mapping[str, SignalSpec],
        e2e: Iterable[str] = (),
        source: str = "<config>",
        every_message: bool = False,
        gnss: Mapping[str, SignalSpec] | None = None,
        gnss_span_s: float = 0.1,
    ) -> None:
        """Resolve the mapping against ``dbs``; ConfigError naming ``can.signals.<quantity>``,
        ``gps.signals.<quantity>`` (and their ``.valid``) or ``can.e2e``."""
        self.dbs: tuple[Database, ...] = (dbs,) if isinstance(dbs, Database) else tuple(dbs)
        gnss = gnss or {}
        if not signals and not gnss and not every_message:
            raise ConfigError(f"{source}: can.signals: no quantity mapped (e.g. speed = 'MESSAGE.SIGNAL')")
        protected = set(e2e)
        for name in sorted(protected):
            if _message(self.dbs, name, f"{source}: can.e2e").length < 2:
                raise ConfigError(f"{source}: can.e2e: {name} is shorter than CRC byte + counter byte")
        mapped = [_Mapped(source, q, spec, False) for q, spec in signals.items()]
        mapped += [_Mapped(source, q, spec, True) for q, spec in gnss.items()]
        self._mapped = mapped
        groups: dict[tuple[str | None, str], list[_Field]] = {}
        messages: dict[str, Message] = {}
        for m in mapped:
            message = _message(self.dbs, m.spec.message, m.key)
            messages[message.name] = message
            groups.setdefault((m.spec.channel, message.name), []).append(_field(message, m))
        self.stats = DecodeStats(per_message={name: 0 for name in messages}, per_quantity={m.name: 0 for m in mapped})
        self._routes: dict[tuple[str | None, int], _Route] = {}
        for (channel, name), fields in groups.items():
            if channel is not None:  # the channel's route also takes the fields mapped on every channel
                fields = fields + groups.get((None, name), [])
            self._add_route(channel, messages[name], fields, name in protected, source)
        if every_message:
            for message in (msg for db in self.dbs for msg in db.messages):
                if (None, frame_key(message.frame_id, message.is_extended_frame)) not in self._routes:
                    self.stats.per_message.setdefault(message.name, 0)
                    self._add_route(None, message, [], message.name in protected, source)
        self._by_channel = any(channel is not None for channel, _ in self._routes)
        self.gnss: GnssAssembler | None = None
        if gnss:
            if not {"lat", "lon"} <= set(gnss):
                raise ConfigError(f"{source}: gps.signals: lat and lon are needed")
            self.gnss = GnssAssembler({spec.message for spec in gnss.values()}, gnss["lat"].message, gnss_span_s)
        self._throttle = Throttle()

    @classmethod
    def from_config(
        cls, config: Config, every_message: bool = False, quantities: Collection[str] | None = None
    ) -> CanDecoder:
        """Load ``can.dbc`` (honouring ``can.dbc_strict``) and resolve ``can.signals``, ``can.e2e`` and, with
        ``gps.source = "can"``, ``gps.signals``. ``quantities`` keeps only those CAN quantities of the mapping (a
        replay decodes nothing its estimator does not read); None keeps all."""
        dbs = [load_dbc(path, config.can.dbc_strict, config.can.dbc_max_mb) for path in config.dbc_paths]
        gnss = config.gps.signals if config.gps.source == "can" else None
        signals = {q: s for q, s in config.can.signals.items() if quantities is None or q in quantities}
        return cls(dbs, signals, config.can.e2e, config.source, every_message, gnss, config.gps.epoch_span_s)

    def _add_route(self, channel: str | None, message: Message, fields: list[_Field], e2e: bool, source: str) -> None:
        key = (channel, frame_key(message.frame_id, message.is_extended_frame))
        other = self._routes.get(key)
        if other is not None:
            where = f" on channel {channel}" if channel is not None else ""
            raise ConfigError(
                f"{source}: can.signals: {other.name} and {message.name} share the id 0x{message.frame_id:X}{where}; "
                "name each quantity's bus with channel = ..."
            )
        muxes = [s for s in message.signals if s.is_multiplexer]
        mux = None
        if muxes:
            bare = [copy.copy(s) for s in muxes]
            for s in bare:
                s.is_multiplexer, s.multiplexer_ids, s.multiplexer_signal = False, None, None
            mux = _with_signals(message, bare)
        top = next((s.name for s in muxes if s.multiplexer_signal is None), None)
        known = {i for s in message.signals if s.multiplexer_signal == top for i in s.multiplexer_ids or ()}
        gnss = any(f.gnss for f in fields)
        names = {n for f in fields for n in f.signals} | {f.valid for f in fields if f.valid is not None}
        used = _in_use(message, names)
        self._routes[key] = _Route(
            message.name,
            message,
            message.length,
            tuple(fields),
            e2e,
            mux,
            top,
            frozenset(known),
            gnss,
            used,
            _decoding(used),
            _decoding(message),
        )

    def can_filters(self) -> list[dict[str, int | bool]]:
        """python-can filters passing exactly the ids in use (for kernel or hardware filtering)."""
        ids = {(r.message.frame_id, bool(r.message.is_extended_frame)) for r in self._routes.values()}
        return [
            {"can_id": frame_id, "can_mask": 0x1FFFFFFF if extended else 0x7FF, "extended": extended}
            for frame_id, extended in sorted(ids)
        ]

    def imu_mountings(self) -> dict[str, Mounting | None]:
        """Per quantity from a 3-axis IMU (``can.signals.yaw_rate``): how the IMU sits, as found so far (None while
        its accelerations point no one way)."""
        return {
            f.name: f.vertical.mounting() for r in self._routes.values() for f in r.fields if f.vertical is not None
        }

    def message_names(self) -> dict[str, str]:
        """CAN quantity -> name of the message that carries it."""
        return {m.quantity: m.spec.message for m in self._mapped if not m.gnss}

    def channels(self) -> dict[str, str]:
        """The bus channels the mapping names: ``can.signals.<quantity>`` (or ``gps.``) -> channel."""
        return {m.name: m.spec.channel for m in self._mapped if m.spec.channel is not None}

    def decode(self, msg: can.Message) -> list[Sample]:
        """SI samples of one frame at ``t = msg.timestamp``, and the GNSS fixes of the epochs it completes or
        closes; [] for frames not in use, bad or stale."""
        t = msg.timestamp
        route = self._route(msg)
        out: list[Sample] = self.gnss.tick(t) if self.gnss is not None else []
        if route is None:
            return out
        data = self._data(route, msg)
        if data is None:
            return out
        fields = route.fields
        if route.mux is not None:
            selected = self._mux_values(route, data)
            fields = tuple(f for f in fields if all(selected.get(s) in ids for s, ids in f.needs))
            if not fields:
                self.stats.other_mux += 1
                return out
        values = self._decode(route.unpack, route.name, data)
        if values is None:
            return out
        gnss: dict[str, float | None] = {}
        per_quantity = self.stats.per_quantity
        used = False
        for f in fields:
            if f.vertical is None:
                raw = values.get(f.signal)
                if raw is None:  # a multiplexed signal absent from this frame
                    continue
            if f.valid is not None and not values.get(f.valid):
                self.stats.invalid += 1
                if f.gnss:
                    gnss[f.quantity] = None
                continue
            if f.vertical is not None:
                raw = f.vertical(values)
                if raw is None:
                    self.stats.decode_errors += 1
                    self._warn("%s: the IMU's accelerations point no one way: no up, no yaw rate", f.name)
                    continue
            value = float(raw) * f.factor
            if not math.isfinite(value):
                self.stats.decode_errors += 1
                self._warn("%s.%s: non-finite value %r", route.name, f.signal, raw)
                continue
            per_quantity[f.name] += 1
            used = True
            if f.gnss:
                gnss[f.quantity] = value
            else:
                out.append(CanSample(t, f.quantity, value))
        if route.gnss and self.gnss is not None:
            out.extend(self.gnss.add(t, route.name, gnss))
        self.stats.decoded += used
        return out

    def flush(self) -> list[GnssFix]:
        """The end of the input: the fix of the GNSS epoch still open, if any."""
        return self.gnss.flush() if self.gnss is not None else []

    def decode_signals(self, msg: can.Message) -> tuple[str, dict[str, float]] | None:
        """Every signal of one frame in use, in DBC units (value tables not applied): (message name, values).

        None for frames not in use, bad or stale, and for a multiplexer value the DBC does not know.
        """
        route = self._route(msg)
        data = self._data(route, msg) if route is not None else None
        if route is None or data is None:
            return None
        if route.mux is not None and self._mux_values(route, data).get(route.top) not in route.mux_ids:
            self.stats.other_mux += 1
            return None
        values = self._decode(route.whole, route.name, data)
        if values is None:
            return None
        self.stats.decoded += 1
        return route.name, {name: float(v) for name, v in values.items()}

    def silent(self) -> list[str]:
        """One line per mapped quantity that has given no value yet, naming its key (and the channels the frames
        came on, when it names one): a mapping to check, said once at the end of a log (nothing before any frame)."""
        if not self.stats.frames:
            return []
        out = []
        seen = ", ".join(sorted(c or "(none)" for c in self.stats.channels)) or "none"
        for m in self._mapped:
            if self.stats.per_quantity.get(m.name):
                continue
            where = f" on channel {m.spec.channel} (frames came on channels: {seen})" if m.spec.channel else ""
            out.append(f"{m.key}: no value from {m.spec.name}{where}")
        return out

    def _route(self, msg: can.Message) -> _Route | None:
        """Count the frame; its route, or None for error, remote and unused frames."""
        stats = self.stats
        stats.frames += 1
        if stats.frames == 1:
            stats.first_t = msg.timestamp
        stats.last_t = msg.timestamp
        channel = "" if msg.channel is None else str(msg.channel)
        if channel in stats.channels or len(stats.channels) < MAX_CHANNELS:
            stats.channels[channel] = stats.channels.get(channel, 0) + 1
        if msg.is_error_frame:
            stats.error_frames += 1
            return None
        if msg.is_remote_frame:
            stats.remote_frames += 1
            return None
        key = frame_key(msg.arbitration_id, msg.is_extended_id)
        route = self._routes.get((channel, key)) if self._by_channel else None
        if route is None:
            route = self._routes.get((None, key))
        if msg.is_fd and (route is None or not route.message.is_fd):
            stats.fd_frames += 1
            return None
        if route is None:
            stats.unused += 1
            ids = stats.unused_ids
            if key in ids or len(ids) < MAX_UNUSED_IDS:
                ids[key] = ids.get(key, 0) + 1
            return None
        stats.per_message[route.name] += 1
        return route

    def _data(self, route: _Route, msg: can.Message) -> bytes | None:
        """The payload, or None (counted) when it is short, longer than a classic message's DBC length, or fails
        its E2E check."""
        data = bytes(msg.data)
        if len(data) < route.length:
            self.stats.decode_errors += 1
            self._warn("%s: short payload (%d of %d bytes)", route.name, len(data), route.length)
            return None
        if len(data) > route.length and not route.message.is_fd:
            self.stats.long_frames += 1
            self._warn("%s: %d-byte payload on a %d-byte classic message: refused", route.name, len(data), route.length)
            return None
        if route.e2e and not self._check_e2e(route, data):
            return None
        return data

    def _mux_values(self, route: _Route, data: bytes) -> Mapping[str, Any]:
        assert route.mux is not None
        return route.mux.decode(data, decode_choices=False, scaling=False)

    def _decode(self, decode: Decode, name: str, data: bytes) -> Mapping[str, Any] | None:
        try:
            return decode(data)
        except Exception as e:  # one bad frame must never stop the stream
            self.stats.decode_errors += 1
            self._warn("%s: cannot decode %s: %s", name, data.hex(), e)
            return None

    def _check_e2e(self, route: _Route, data: bytes) -> bool:
        stats = self.stats
        if not is_intact(data):
            stats.crc_errors += 1
            self._warn("%s: CRC mismatch in %s", route.name, data.hex())
            return False
        counter = rolling_counter(data)
        last, route.last_counter = route.last_counter, counter
        if last is None:
            return True
        step = (counter - last) % 16
        if step == 0:
            stats.stale += 1
            self._warn("%s: repeated counter %d (stale frame)", route.name, counter)
            return False
        if step > 1:
            stats.counter_jumps += 1
            stats.frames_lost += step - 1
        return True

    def _warn(self, fmt: str, *args: object) -> None:
        if self._throttle.ready():
            s = self.stats
            log.warning(
                fmt + " (so far: %d decode errors, %d CRC errors, %d stale of %d frames)",
                *args,
                s.decode_errors,
                s.crc_errors,
                s.stale,
                s.frames,
            )


def _with_signals(message: Message, signals: Sequence[Signal]) -> Message:
    """``message`` (its id, name and length) with these signals alone."""
    return Message(
        frame_id=message.frame_id,
        name=message.name,
        length=message.length,
        signals=list(signals),
        is_extended_frame=message.is_extended_frame,
        strict=False,
    )


def _in_use(message: Message, names: Collection[str]) -> Message:
    """``message`` with only the signals ``names``: it decodes them as ``message`` does. The message itself where
    it is multiplexed or cannot be decoded at all (signals beyond its length, a DBC loaded with
    ``can.dbc_strict = false``: each frame stays a counted decode error)."""
    try:
        message.decode(bytes(message.length), decode_choices=False)
    except Exception:  # what fails here fails for every payload: the unpacking formats do not fit the length
        return message
    if message.is_multiplexed():
        return message
    return _with_signals(message, [copy.copy(s) for s in message.signals if s.name in names])


Decode = Callable[[bytes], Mapping[str, Any]]
"""A payload's signal values in DBC units, value tables not applied (``Message.decode(data, decode_choices=False)``);
cantools' errors raised as it raises them."""


def _whole(message: Message) -> Decode:
    """``message.decode(data, decode_choices=False)``."""
    return lambda data: message.decode(data, decode_choices=False)


def _decoding(message: Message) -> Decode:
    """:func:`_whole` of ``message``; where it is not multiplexed, the same values (the same conversion of the same
    unpacked raw values, in the same order) without cantools' layers of calls around them: its big- and
    little-endian unpacking formats built once, called on the payload, each signal's value scaled. Half the time a
    frame (the real drive's IMU message: 2.2 -> 1.0 us; ``tests/test_can_decode.py`` holds it to cantools on every
    message of the DBCs at hand). A payload not of the message's length, or one the formats cannot unpack, goes
    to cantools, which decodes or refuses it as before."""
    whole = _whole(message)
    if message.is_multiplexed() or message.is_container:
        return whole
    formats = create_encode_decode_formats(message.signals, message.length)
    big, little, length = formats.big_endian.unpack, formats.little_endian.unpack, message.length
    scaling = [(s.name, s.conversion.raw_to_scaled) for s in message.signals]

    def decode(data: bytes) -> Mapping[str, Any]:
        if len(data) != length:
            return whole(data)
        try:
            raw = {**big(data), **little(data[::-1])}
        except Exception:  # cantools' DecodeError, as cantools words it
            return whole(data)
        return {name: scaled(value, False) for name, scaled in scaling if (value := raw.get(name)) is not None}

    return decode


def _message(dbs: Sequence[Database], name: str, key: str) -> Message:
    """The message ``name`` of the one database that has it; ConfigError naming ``key`` if none or several do."""
    found = []
    for db in dbs:
        try:
            found.append(db.get_message_by_name(name))
        except KeyError:
            continue
    if len(found) == 1:
        return found[0]
    if found:
        raise ConfigError(f"{key}: message {name!r} is in {len(found)} of the databases (can.dbc): rename one")
    known = ", ".join(sorted(m.name for db in dbs for m in db.messages))
    raise ConfigError(f"{key}: no message {name!r} in the DBC (known: {known})")


def _field(message: Message, mapped: _Mapped) -> _Field:
    """Resolve one mapped quantity against its message: the signal, its unit factor, the flag signal, the
    multiplexer values that carry it; ConfigError naming the key."""
    spec, key, quantity = mapped.spec, mapped.key, mapped.quantity
    known_quantities = GNSS_QUANTITIES if mapped.gnss else CAN_QUANTITIES
    if quantity not in known_quantities:
        raise ConfigError(f"{key}: unknown quantity (known: {', '.join(known_quantities)})")
    if spec.rates and (mapped.gnss or quantity != IMU_QUANTITY):
        raise ConfigError(f"{key}: rates and accelerations (a 3-axis IMU) give can.signals.{IMU_QUANTITY} only")
    if spec.valid is not None:
        _signal_of(message, spec.valid, f"{key}.valid")
    vertical = None
    if spec.rates:
        if message.is_multiplexed():
            raise ConfigError(f"{key}: {message.name} is multiplexed: an IMU's six signals come in one frame")
        signal = _signal_of(message, spec.rates[0], f"{key}.rates")
        units = {_signal_of(message, name, f"{key}.rates").unit for name in spec.rates}
        if spec.unit is None and len(units) > 1:
            raise ConfigError(f"{key}.rates: the signals' units differ ({', '.join(sorted(map(str, units)))})")
        units = {_signal_of(message, name, f"{key}.accelerations").unit for name in spec.accelerations}
        if len(units) > 1:  # only the direction counts, not the unit: one unit for the three
            raise ConfigError(f"{key}.accelerations: the signals' units differ ({', '.join(sorted(map(str, units)))})")
        vertical = VerticalRate(spec.rates, spec.accelerations, key)
    else:
        signal = _signal_of(message, spec.signal, key)
    unit = spec.unit if spec.unit is not None else signal.unit
    factor = si_factor(unit, quantity)
    if factor is None:
        kind = _KIND_OF[quantity]
        known = ", ".join(_UNITS[kind])
        what = f"unit {unit!r}" if unit else "no unit"
        article = "an" if kind[0] in "aeiou" else "a"
        raise ConfigError(
            f"{key}: {spec.name} has {what}, not {article} {kind} unit; set unit = '...' (one of: {known})"
        )
    needs = []
    s = signal
    while s.multiplexer_signal is not None:
        needs.append((s.multiplexer_signal, frozenset(s.multiplexer_ids or ())))
        s = message.get_signal_by_name(s.multiplexer_signal)
    return _Field(
        mapped.name, quantity, spec.signal, factor * spec.scale, spec.valid, mapped.gnss, tuple(needs), vertical
    )


def _signal_of(message: Message, name: str, key: str) -> Signal:
    """The signal ``name`` of ``message``; ConfigError naming ``key`` and the message's signals if it has none."""
    try:
        return message.get_signal_by_name(name)
    except KeyError as e:
        known = ", ".join(s.name for s in message.signals)
        raise ConfigError(f"{key}: no signal {name!r} in message {message.name} ({known})") from e


@dataclass
class LogStats:
    """Counters of a log read (one file or several): files, frames yielded, malformed lines skipped, the errors
    that ended files early, and the first frame's timestamp (s; NaN until known)."""

    files: int = 0
    frames: int = 0
    malformed: int = 0
    rebases: int = 0
    """Clock jumps inside a file that were re-based (:class:`LogClock`)."""
    pauses: int = 0
    """Steps of a file's clock kept as a pause of the bus (:class:`LogClock`'s ``is_pause``)."""
    error: str = ""
    first_t: float = math.nan

    def add_error(self, path: Path, error: str) -> None:
        self.error = "; ".join(filter(None, (self.error, f"{path.name}: {error}")))


_CANDUMP_LINE = re.compile(
    r"\(\d+(?:\.\d+)?\)\s+\S+\s+(?:[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#"
    r"(?:#[0-9A-Fa-f])?(?:(?:[0-9A-Fa-f]{2}){0,64}|[Rr]\d{0,2})(?:\s+[RrTt])?"
)
"""One ``candump -L`` line, as :class:`can.CanutilsLogReader` parses it (CAN FD ``##`` and remote ``#R`` too)."""

MF4_EXTRA = "pip install 'sumhe[mf4]'"
"""How to install what MF4 logs need (asammdf, which python-can's MF4 reader uses)."""


def read_log(
    path: str | PathLike[str], stats: LogStats | None = None, is_pause: PauseJudge | None = None
) -> Iterator[can.Message]:
    """Frames of a CAN log in any format python-can reads (by suffix, any case: candump -L ``.log``, ``.asc``,
    ``.blf``, ``.trc``, ``.csv``, each optionally ``.gz``; ASAM MDF 4 ``.mf4`` with the ``mf4`` extra).

    Raises SourceError at once for a missing, unreadable or unknown-format file, and for an MF4 file without
    asammdf installed. In candump logs a malformed line is counted in ``stats.malformed`` and skipped; in other
    formats a read error ends the file early (counted, logged, ``stats.error`` set), since their readers cannot
    resume.
    """
    p = Path(path)
    stats = stats if stats is not None else LogStats()
    if not p.is_file():
        raise SourceError(f"{p}: CAN log not found")
    name = p.name.lower()
    if name.endswith(".mf4") and importlib.util.find_spec("asammdf") is None:
        raise SourceError(f"{p}: reading MF4 logs needs the asammdf package: {MF4_EXTRA}")
    try:
        if name.endswith((".log", ".log.gz")):
            opener = gzip.open if name.endswith(".gz") else open
            # opened here so an unreadable file fails now; the reader owns and closes it
            text: TextIO = opener(p, "rt", encoding="utf-8", errors="replace")
            reader: can.io.generic.MessageReader | _CandumpReader = _CandumpReader(text, p, stats)
        elif name.endswith(".mf4"):
            from sumhe.io.mf4 import BulkMF4Reader

            reader = BulkMF4Reader(p)
        else:
            reader = can.LogReader(p)
    except Exception as e:  # OSError, or a reader rejecting the file (BLFParseError, MdfException, ValueError, ...)
        if isinstance(e, ValueError) and _suffix(p) not in can.io.player.MESSAGE_READERS:
            raise SourceError(f"{p}: unsupported CAN log format ({e})") from e
        raise SourceError(f"{p}: cannot read CAN log: {type(e).__name__}: {e}") from e
    stats.files += 1
    return _frames(reader, p, stats, is_pause)


def _suffix(path: Path) -> str:
    """The suffix that names a log's format (``.asc`` of ``drive.asc.gz``), lower case."""
    suffixes = [x.lower() for x in path.suffixes]
    return suffixes[-2] if len(suffixes) > 1 and suffixes[-1] == ".gz" else (suffixes[-1] if suffixes else "")


_CLASSIC_LINE = re.compile(
    r"\((\d+(?:\.\d+)?)\)\s+(\S+)\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#([0-9A-Fa-f]{0,16})(?:\s+([RrTt]))?"
)
"""A ``candump -L`` line of a classic data frame (nearly every line; the payload's digits paired by the reader,
a third faster than pairing them in the pattern): parsed here in one match. python-can's reader, which parses the
payload a byte at a time, takes the rest (CAN FD, remote and error frames)."""
_CAN_ERR_FLAG = 0x20000000


class _CandumpReader:
    """Frames of a ``candump -L`` text (closed at the end): the same ``can.Message`` s as
    :class:`can.CanutilsLogReader`, three times faster; malformed lines counted in ``stats`` and skipped."""

    def __init__(self, text: TextIO, path: Path, stats: LogStats) -> None:
        self.text, self.path, self.stats = text, path, stats

    def __enter__(self) -> _CandumpReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.text.close()

    def __iter__(self) -> Iterator[can.Message]:
        throttle = Throttle()
        classic, general, message = _CLASSIC_LINE.fullmatch, _CANDUMP_LINE.fullmatch, can.Message
        for n, line in enumerate(self.text, 1):
            stripped = line.strip()
            if not stripped:
                continue
            m = classic(stripped)
            if m is not None and not len(m[4]) % 2:
                t, channel, can_id, data, flag = m.groups()
                arbitration_id = int(can_id, 16)
                if not arbitration_id & _CAN_ERR_FLAG:
                    yield message(  # positional: matching keywords made a Message twice as dear (0.5 us)
                        float(t),  # timestamp
                        arbitration_id & 0x1FFFFFFF,
                        len(can_id) > 3,  # is_extended_id
                        False,  # is_remote_frame
                        False,  # is_error_frame
                        int(channel) if channel.isdigit() else channel,
                        len(data) // 2,  # dlc
                        bytearray.fromhex(data),
                        False,  # is_fd
                        flag is None or flag in "Rr",  # is_rx
                    )
                    continue
            if general(stripped):
                try:
                    frames = list(can.CanutilsLogReader(io.StringIO(stripped)))
                except ValueError:  # python-can reads the FD flags digit as decimal: ``##A`` to ``##F`` fail
                    frames = []
                if frames:
                    yield from frames
                    continue
            self.stats.malformed += 1
            if throttle.ready():
                log.warning(
                    "%s:%d: skipping malformed candump line %.60r (%d so far)", self.path, n, line, self.stats.malformed
                )


LOG_JUMP_S = 60.0
"""A step between consecutive frames of one log file larger than this (s, either way) is the logger's clock
jumping (an NTP step, an RTC set), not the bus: :class:`LogClock` re-bases the frames after it."""

PauseJudge = Callable[[float, float], bool]
"""``judge(before, after) -> bool``: whether a step of a CAN log's clock from ``before`` to ``after`` (s) is time
that really passed (a pause of the bus: kept) rather than the logger's clock jumping (re-based); the drive's other
logs can tell (:meth:`sumhe.io.replay.RecordedDrive.can_pause`)."""


class LogClock:
    """Re-bases one log file's timestamps across clock jumps: a frame more than :data:`LOG_JUMP_S` after (or
    before) the previous one continues the timeline one frame step after it, and so do the frames that follow.

    A bus that fell silent for longer than that inside one file (a logger running through a parked hour) looks
    the same from the file alone: ``is_pause`` (the drive's NMEA logs, which ran on through the pause) tells the two
    apart, and a pause keeps its times (the estimator restarts at the next fix, ``TimeGuard``'s ``jump_s``;
    counted in ``stats.pauses``). Without it every step is re-based. Each re-based jump is counted in
    ``stats.rebases`` and logged (a warning at most every 10 s, the others at debug level).
    """

    def __init__(self, path: Path, stats: LogStats, is_pause: PauseJudge | None = None) -> None:
        self.path, self.stats, self.is_pause = path, stats, is_pause
        self._throttle = Throttle()
        self.offset = 0.0
        self._last = math.nan
        self._step = 0.0

    def __call__(self, stamp: float) -> float:
        """The frame time on the file's continuous timeline (s)."""
        step = stamp - self._last
        if (
            abs(step) > LOG_JUMP_S
            and self.is_pause is not None
            and self.is_pause(self._last + self.offset, stamp + self.offset)
        ):
            self.stats.pauses += 1
            log.info(
                "%s: the bus was silent for %.1f s at %.6f (the NMEA log ran on): times kept", self.path, step, stamp
            )
        elif abs(step) > LOG_JUMP_S:
            shifted = self._last + self.offset + self._step
            self.stats.rebases += 1
            log.log(
                logging.WARNING if self._throttle.ready() else logging.DEBUG,
                "%s: the log's clock jumps by %+.3f s at %.6f: the frames after it are re-based to %.6f (%d so far)",
                self.path,
                step,
                stamp,
                shifted,
                self.stats.rebases,
            )
            self.offset = shifted - stamp
        elif step >= 0.0:
            self._step = step
        self._last = stamp
        return stamp + self.offset


def _frames(
    reader: can.io.generic.MessageReader | _CandumpReader, path: Path, stats: LogStats, is_pause: PauseJudge | None
) -> Iterator[can.Message]:
    clock = LogClock(path, stats, is_pause)
    with reader:
        frames = 0
        try:
            for msg in reader:
                frames += 1
                stats.frames += 1
                msg.timestamp = clock(msg.timestamp)
                yield msg
        except Exception as e:  # a corrupt file must end the read, never the program
            stats.malformed += 1
            stats.add_error(path, f"{type(e).__name__}: {e}")
            log.warning("%s: stopped reading after %d frames: %s: %s", path, frames, type(e).__name__, e)


def first_timestamp(path: str | PathLike[str]) -> float | None:
    """The timestamp (s) of the first frame of a CAN log, None if it has none; SourceError as :func:`read_log`."""
    frames = read_log(path, LogStats())
    try:
        return next((float(msg.timestamp) for msg in frames), None)
    finally:
        frames.close()  # type: ignore[attr-defined]


def read_logs(
    paths: Sequence[str | PathLike[str]], stats: LogStats | None = None, is_pause: PauseJudge | None = None
) -> Iterator[can.Message]:
    """The frames of one drive's CAN logs (one file or several, in any order), as one stream in time order.

    The files are ordered by their first timestamps (read now: SourceError at once for a missing or unreadable
    file, and ``stats.first_t`` set) and merged by timestamp; a file is opened when the stream reaches its first
    frame, so consecutive files are read one after the other and files of parallel buses side by side. A file
    without frames is left out (with a warning when there are others).
    """
    stats = stats if stats is not None else LogStats()
    heads = []
    for i, path in enumerate(paths):
        first = first_timestamp(path)
        if first is None:
            if len(paths) > 1:
                log.warning("%s: no CAN frames", path)
            continue
        heads.append((first, i, Path(path)))
    heads.sort()
    if heads:
        stats.first_t = heads[0][0]
    return _merged(deque(heads), stats, is_pause)


def _merged(
    pending: deque[tuple[float, int, Path]], stats: LogStats, is_pause: PauseJudge | None
) -> Iterator[can.Message]:
    if len(pending) == 1:  # one file: its frames as they come, without the heap
        yield from read_log(pending[0][2], stats, is_pause)
        return
    active: list[tuple[float, int, can.Message, Iterator[can.Message]]] = []
    order = itertools.count()
    while pending or active:
        while pending and (not active or pending[0][0] <= active[0][0]):
            frames = read_log(pending.popleft()[2], stats, is_pause)
            msg = next(frames, None)
            if msg is not None:
                heapq.heappush(active, (msg.timestamp, next(order), msg, frames))
        if not active:
            continue
        _, _, msg, frames = active[0]
        yield msg
        nxt = next(frames, None)
        if nxt is None:
            heapq.heappop(active)
        else:
            heapq.heapreplace(active, (nxt.timestamp, next(order), nxt, frames))
