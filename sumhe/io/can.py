"""CAN frames to SI samples: the DBC, the configured signal mapping, end-to-end checks, and log files.

Pure decoding, no bus I/O: the live source (:mod:`sumhe.io.can_source`), the log replay and the ``candump``
command share :class:`CanDecoder`. The decoder is built once from the DBC and ``can.signals``: each quantity's
unit factor to SI is resolved at construction from the DBC's unit string (or the spec's ``unit`` override),
times the spec's ``scale``; frames whose id is not in use are dropped by one dict lookup before any decoding.

End-to-end protection: the messages named in ``can.e2e`` (default none; the reference DBC protects
ESP_YAW_RATE and ESP_VEHICLE_SPEED, as its comments say) carry a CRC-8/SAE-J1850 in byte 0 over the other bytes
and a 4-bit rolling counter in the low nibble of byte 1 (:mod:`sumhe.io.checksum`). A bad CRC drops the frame;
a repeated counter (stale frame) drops it; a counter jump (frames lost) is counted and the frame used. The
scheme is named in configuration, not guessed from DBC comments, because DBCs describe it only in free text.
"""

from __future__ import annotations

import gzip
import logging
import math
import re
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path
from typing import Any, TextIO

import can
import cantools
from cantools.database.can import Database, Message

from sumhe.config import Config, SignalSpec
from sumhe.errors import ConfigError, SourceError
from sumhe.io.checksum import is_intact, rolling_counter
from sumhe.messages import CAN_QUANTITIES, CanSample

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
}
assert set(_KIND_OF) == set(CAN_QUANTITIES)

_WARN_INTERVAL_S = 10.0


def si_factor(unit: str | None, quantity: str) -> float | None:
    """Factor from a DBC unit string to the SI unit of ``quantity``; None if unknown or missing.

    Case and spaces are ignored: ``"km/h"``, ``"KPH"`` and ``"Km / h"`` are all 1/3.6.
    """
    if not unit:
        return None
    return _UNITS[_KIND_OF[quantity]].get(unit.strip().lower().replace(" ", ""))


def load_dbc(path: str | PathLike[str], strict: bool = True) -> Database:
    """Load a CAN database (DBC, KCD, SYM, ARXML by suffix); ConfigError naming the file on any failure.

    ``strict=False`` accepts databases with overlapping signals or signals past the message end, which
    several public DBCs have.
    """
    try:
        db = cantools.database.load_file(str(path), strict=strict)
    except FileNotFoundError as e:
        raise ConfigError(f"{path}: DBC file not found") from e
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read DBC: {e}") from e
    except cantools.database.Error as e:
        hint = " (can.dbc_strict = false accepts it)" if strict and _loads_leniently(path) else ""
        raise ConfigError(f"{path}: not a valid CAN database: {e}{hint}") from e
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
    ``first_t``/``last_t``, s); ``decoded`` those that gave samples."""

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
    remote_frames: int = 0
    per_message: dict[str, int] = field(default_factory=dict)
    unused_ids: dict[int, int] = field(default_factory=dict)
    """Frame counts of unused ids by :func:`frame_key` (the first :data:`MAX_UNUSED_IDS` distinct ids)."""


MAX_UNUSED_IDS = 512


@dataclass(slots=True)
class _Route:
    """How to turn the frames of one message in use into samples."""

    name: str
    message: Message
    length: int
    fields: tuple[tuple[str, str, float], ...]
    """(quantity, signal, factor to SI including the spec's scale)."""
    e2e: bool
    last_counter: int | None = None


class CanDecoder:
    """Decodes the frames of the mapped messages into SI :class:`CanSample` s (see the module docstring).

    With ``every_message=True`` every message of the DBC is in use (for :meth:`decode_signals`, ``candump --all``)
    and ``signals`` may be empty.
    """

    def __init__(
        self,
        db: Database,
        signals: Mapping[str, SignalSpec],
        e2e: Iterable[str] = (),
        source: str = "<config>",
        every_message: bool = False,
    ) -> None:
        """Resolve the mapping against ``db``; ConfigError naming ``can.signals.<quantity>`` or ``can.e2e``."""
        if not signals and not every_message:
            raise ConfigError(f"{source}: can.signals: no quantity mapped (e.g. speed = 'MESSAGE.SIGNAL')")
        protected = set(e2e)
        for name in sorted(protected):
            if _message(db, name, f"{source}: can.e2e").length < 2:
                raise ConfigError(f"{source}: can.e2e: {name} is shorter than CRC byte + counter byte")
        fields: dict[str, list[tuple[str, str, float]]] = {}
        messages: dict[str, Message] = {m.name: m for m in db.messages} if every_message else {}
        for quantity, spec in signals.items():
            key = f"{source}: can.signals.{quantity}"
            if quantity not in _KIND_OF:
                raise ConfigError(f"{key}: unknown quantity (known: {', '.join(CAN_QUANTITIES)})")
            message = _message(db, spec.message, key)
            try:
                signal = message.get_signal_by_name(spec.signal)
            except KeyError as e:
                known = ", ".join(s.name for s in message.signals)
                raise ConfigError(f"{key}: no signal {spec.signal!r} in message {spec.message} ({known})") from e
            unit = spec.unit if spec.unit is not None else signal.unit
            factor = si_factor(unit, quantity)
            if factor is None:
                kind = _KIND_OF[quantity]
                known = ", ".join(_UNITS[kind])
                what = f"unit {unit!r}" if unit else "no unit"
                raise ConfigError(
                    f"{key}: {spec.name} has {what}, not a {kind} unit; set unit = '...' (one of: {known})"
                )
            messages[spec.message] = message
            fields.setdefault(spec.message, []).append((quantity, spec.signal, factor * spec.scale))
        self.db = db
        self.stats = DecodeStats(per_message={name: 0 for name in messages})
        self._routes: dict[int, _Route] = {
            frame_key(m.frame_id, m.is_extended_frame): _Route(
                name, m, m.length, tuple(fields.get(name, ())), e2e=name in protected
            )
            for name, m in messages.items()
        }
        self._throttle = Throttle()

    @classmethod
    def from_config(cls, config: Config, every_message: bool = False) -> CanDecoder:
        """Load ``can.dbc`` (honouring ``can.dbc_strict``) and resolve ``can.signals`` and ``can.e2e``."""
        db = load_dbc(config.dbc_path, config.can.dbc_strict)
        return cls(db, config.can.signals, config.can.e2e, config.source, every_message)

    def can_filters(self) -> list[dict[str, int | bool]]:
        """python-can filters passing exactly the ids in use (for kernel or hardware filtering)."""
        return [
            {
                "can_id": r.message.frame_id,
                "can_mask": 0x1FFFFFFF if r.message.is_extended_frame else 0x7FF,
                "extended": bool(r.message.is_extended_frame),
            }
            for r in self._routes.values()
        ]

    def message_names(self) -> dict[str, str]:
        """Quantity -> name of the message that carries it."""
        return {q: r.name for r in self._routes.values() for q, _, _ in r.fields}

    def decode(self, msg: can.Message) -> list[CanSample]:
        """SI samples of one frame at ``t = msg.timestamp``; [] for frames not in use, bad or stale."""
        checked = self._values(msg)
        if checked is None:
            return []
        route, values = checked
        t = msg.timestamp
        out = []
        for quantity, signal, factor in route.fields:
            raw = values.get(signal)
            if raw is None:  # a multiplexed signal absent from this frame
                continue
            value = float(raw) * factor
            if not math.isfinite(value):
                self.stats.decode_errors += 1
                self._warn("%s.%s: non-finite value %r", route.name, signal, raw)
                continue
            out.append(CanSample(t, quantity, value))
        if out:
            self.stats.decoded += 1
        return out

    def decode_signals(self, msg: can.Message) -> tuple[str, dict[str, float]] | None:
        """Every signal of one frame in use, in DBC units (value tables not applied): (message name, values).

        None for frames not in use, bad or stale.
        """
        checked = self._values(msg)
        if checked is None:
            return None
        route, values = checked
        self.stats.decoded += 1
        return route.name, {name: float(v) for name, v in values.items()}

    def _values(self, msg: can.Message) -> tuple[_Route, Mapping[str, Any]] | None:
        """Count the frame, drop it if not in use, short, failing its E2E check or undecodable, else decode it."""
        stats = self.stats
        stats.frames += 1
        if stats.frames == 1:
            stats.first_t = msg.timestamp
        stats.last_t = msg.timestamp
        if msg.is_error_frame:
            stats.error_frames += 1
            return None
        if msg.is_remote_frame:
            stats.remote_frames += 1
            return None
        key = frame_key(msg.arbitration_id, msg.is_extended_id)
        route = self._routes.get(key)
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
        data = bytes(msg.data)
        if len(data) < route.length:
            stats.decode_errors += 1
            self._warn("%s: short payload (%d of %d bytes)", route.name, len(data), route.length)
            return None
        if route.e2e and not self._check_e2e(route, data):
            return None
        try:
            return route, route.message.decode(data, decode_choices=False)
        except Exception as e:  # one bad frame must never stop the stream
            stats.decode_errors += 1
            self._warn("%s: cannot decode %s: %s", route.name, data.hex(), e)
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


def _message(db: Database, name: str, key: str) -> Message:
    try:
        return db.get_message_by_name(name)
    except KeyError as e:
        known = ", ".join(sorted(m.name for m in db.messages))
        raise ConfigError(f"{key}: no message {name!r} in the DBC (known: {known})") from e


@dataclass
class LogStats:
    """Counters of one log read: frames yielded, malformed lines skipped, and the error that ended it early."""

    frames: int = 0
    malformed: int = 0
    error: str = ""


_CANDUMP_LINE = re.compile(
    r"\(\d+(?:\.\d+)?\)\s+\S+\s+(?:[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#"
    r"(?:#[0-9A-Fa-f])?(?:(?:[0-9A-Fa-f]{2}){0,64}|[Rr]\d{0,2})(?:\s+[RrTt])?"
)
"""One ``candump -L`` line, as :class:`can.CanutilsLogReader` parses it (CAN FD ``##`` and remote ``#R`` too)."""


def read_log(path: str | PathLike[str], stats: LogStats | None = None) -> Iterator[can.Message]:
    """Frames of a CAN log in any format python-can reads (by suffix: candump -L ``.log``, ``.asc``, ``.blf``,
    ``.trc``, ``.csv``, each optionally ``.gz``).

    Raises SourceError at once for a missing, unreadable or unknown-format file. In candump logs a malformed line
    is counted in ``stats.malformed`` and skipped; in other formats a read error ends the file early (counted,
    logged, ``stats.error`` set), since their readers cannot resume.
    """
    p = Path(path)
    stats = stats if stats is not None else LogStats()
    if not p.is_file():
        raise SourceError(f"{p}: CAN log not found")
    name = p.name.lower()
    try:
        if name.endswith((".log", ".log.gz")):
            opener = gzip.open if name.endswith(".gz") else open
            # opened here so an unreadable file fails now; the line generator owns and closes it
            text: TextIO = opener(p, "rt", encoding="utf-8", errors="replace")
            reader: can.io.generic.MessageReader = can.CanutilsLogReader(_valid_candump_lines(text, p, stats))
        else:
            reader = can.LogReader(p)
    except ValueError as e:
        raise SourceError(f"{p}: unsupported CAN log format ({e})") from e
    except Exception as e:  # OSError, or a reader rejecting the file header (BLFParseError, ...)
        raise SourceError(f"{p}: cannot read CAN log: {e}") from e
    return _frames(reader, p, stats)


def _valid_candump_lines(text: TextIO, path: Path, stats: LogStats) -> Iterator[str]:
    throttle = Throttle()
    with text:
        for n, line in enumerate(text, 1):
            stripped = line.strip()
            if not stripped:
                continue
            if _CANDUMP_LINE.fullmatch(stripped):
                yield stripped
                continue
            stats.malformed += 1
            if throttle.ready():
                log.warning("%s:%d: skipping malformed candump line %.60r (%d so far)", path, n, line, stats.malformed)


def _frames(reader: can.io.generic.MessageReader, path: Path, stats: LogStats) -> Iterator[can.Message]:
    with reader:
        try:
            for msg in reader:
                stats.frames += 1
                yield msg
        except Exception as e:  # a corrupt file must end the read, never the program
            stats.malformed += 1
            stats.error = f"{type(e).__name__}: {e}"
            log.warning("%s: stopped reading after %d frames: %s", path, stats.frames, stats.error)
