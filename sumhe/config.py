"""Configuration: one TOML file loaded once into frozen, validated settings.

This is the only module that reads configuration files or the environment. Precedence:
overrides (CLI) > environment (``SUMHE_<SECTION>__<KEY>``, e.g. ``SUMHE_CAN__CHANNEL=vcan1``; a nested table's
key with one ``__`` per level, ``SUMHE_ESTIMATOR__MHE__STEPS=80``) > file > defaults. Every error is a
:class:`~sumhe.errors.ConfigError` naming the key and where it was set: the file, the environment variable
(``SUMHE_CAN__CHANEL`` for a typo there), or the command line.
"""

from __future__ import annotations

import dataclasses
import difflib
import ipaddress
import logging
import os
import re
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

from sumhe.errors import ConfigError, printable
from sumhe.messages import CAN_QUANTITIES, GNSS_QUANTITIES
from sumhe.settings import EstimationSettings, EstimatorSettings, SensorSettings, VehicleSettings
from sumhe.settings.moved import MOVED

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

log = logging.getLogger(__name__)

PACKAGE_DATA = Path(__file__).parent / "data"
DEFAULT_DBC = "dbc/sumhe_ref.dbc"


def default_can_interface() -> str:
    """``socketcan`` on Linux (the field default), python-can's in-process ``virtual`` bus elsewhere."""
    return "socketcan" if sys.platform.startswith("linux") else "virtual"


@dataclass(frozen=True, slots=True)
class SignalSpec:
    """Where one quantity lives in the DBC: ``MESSAGE.SIGNAL``; unit from the DBC unless overridden.

    ``scale`` multiplies the SI value (use -1 to flip a sign convention). ``channel`` restricts the quantity to
    frames of that bus channel (as the log or interface names it: ``1``, ``"can0"``; compared as text), for logs
    of several buses whose ids repeat; None takes the frames of every channel. ``valid`` names a signal of the
    same message that flags the value: the value is used only when that signal is non-zero.

    A yaw rate may instead come from a 3-axis IMU mounted any way: ``rates`` names its three angular-rate signals
    and ``accelerations`` its three accelerometer signals, all of ``message`` (``signal`` is then empty); the yaw
    rate is the angular rate about the up direction the accelerometer finds (:class:`sumhe.io.imu.VerticalRate`).
    """

    message: str
    signal: str
    scale: float = 1.0
    unit: str | None = None
    channel: str | None = None
    valid: str | None = None
    rates: tuple[str, ...] = ()
    accelerations: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return f"{self.message}.{'/'.join(self.rates) if self.rates else self.signal}"


BUS_OWN_KEYS = {
    "interface": "set can.interface",
    "channel": "set can.channel",
    "bitrate": "set can.bitrate",
    "can_filters": "from the DBC's messages",
    "fd": "on for socketcan",
}
"""``Bus`` arguments that ``can.bus`` may not set, and where they come from."""


@dataclass(frozen=True, slots=True)
class CanSettings:
    """The CAN bus and its decoding. ``dbc`` is one database file or a list of them (e.g. the car's OBD-II
    replies and a logger's own sensors); a message name is looked up in all of them."""

    interface: str = field(default_factory=default_can_interface)
    channel: str = "vcan0"
    bitrate: int | None = None
    dbc: str | tuple[str, ...] = DEFAULT_DBC
    dbc_strict: bool = True
    dbc_max_mb: float = 32.0
    """Largest database file read (MB): a wrong file (a log, a binary) named as the DBC is refused before parsing."""
    receive_timeout_s: float = 1.0
    queue_size: int = 2000
    reconnect_max_s: float = 5.0
    signals: Mapping[str, SignalSpec] = field(default_factory=dict)
    e2e: tuple[str, ...] = ()
    """Messages protected by CRC-8 in byte 0 and a 4-bit rolling counter (see :mod:`sumhe.io.can`)."""
    bus: Mapping[str, str | int | float | bool] = field(default_factory=dict)
    """More keyword arguments of python-can's ``Bus`` for the interface (e.g. ``port`` of ``udp_multicast``), passed
    as they are by everything that opens the bus (the service, ``sumhe play``)."""

    def __post_init__(self) -> None:
        _positive(self, "receive_timeout_s", "queue_size", "reconnect_max_s", "dbc_max_mb")
        for key in self.bus:
            if key in BUS_OWN_KEYS:
                raise ValueError(f"bus.{key}: set by sumhe ({BUS_OWN_KEYS[key]})")
        if self.bitrate is not None and self.bitrate <= 0:
            raise ValueError("bitrate: must be positive")
        if not self.dbc_files or not all(self.dbc_files):
            raise ValueError("dbc: name at least one database file")

    @property
    def dbc_files(self) -> tuple[str, ...]:
        """``dbc`` as a tuple of file names."""
        return (self.dbc,) if isinstance(self.dbc, str) else self.dbc


@dataclass(frozen=True, slots=True)
class GpsSettings:
    """The GNSS receiver. ``source = "nmea"``: NMEA on a serial ``port`` (a device, or a pyserial URL such as
    ``socket://host:port``), or an NMEA log in a replay. ``source = "can"``: fixes decoded from CAN frames by the
    ``signals`` mapping (quantities :data:`~sumhe.messages.GNSS_QUANTITIES`; ``lat`` and ``lon`` needed), one fix
    per epoch (:mod:`sumhe.io.can_gnss`): the frames of one epoch arrive within ``epoch_span_s`` of its first.

    ``time`` says which time a fix's position refers to on the service clock: ``"utc"``, the fix's own UTC time
    of fix when it lies within ``max_clock_offset_s`` of its receive time (a service clock on UTC: NTP live,
    recorded logs), else ``receive time - latency_s``; ``"receive"``, always ``receive time - latency_s``. The
    receive time of a fix from CAN is the timestamp of the frame carrying its position.
    """

    source: str = "nmea"
    port: str | None = "/dev/ttyUSB0"
    baudrate: int = 115200
    time: str = "utc"
    latency_s: float = 0.0
    max_clock_offset_s: float = 1.0
    receive_timeout_s: float = 2.0
    queue_size: int = 200
    reconnect_max_s: float = 5.0
    signals: Mapping[str, SignalSpec] = field(default_factory=dict)
    epoch_span_s: float = 0.1

    def __post_init__(self) -> None:
        _positive(
            self, "baudrate", "receive_timeout_s", "queue_size", "reconnect_max_s", "max_clock_offset_s", "epoch_span_s"
        )
        if self.time not in ("utc", "receive"):
            raise ValueError("time: must be 'utc' or 'receive'")
        if not 0.0 <= self.latency_s <= 5.0:
            raise ValueError("latency_s: must be within [0, 5] s")
        if self.source not in ("nmea", "can"):
            raise ValueError("source: must be 'nmea' or 'can'")
        if self.source == "can" and not {"lat", "lon"} <= set(self.signals):
            raise ValueError("signals: gps.source = 'can' needs lat and lon (e.g. lat = 'MESSAGE.SIGNAL')")
        if self.source == "nmea" and self.signals:
            raise ValueError("signals: read only with gps.source = 'can'")


@dataclass(frozen=True, slots=True)
class DatumSettings:
    """Origin of the local east/north/up frame: the first valid fix, or a fixed point."""

    mode: str = "first_fix"
    lat: float | None = None
    lon: float | None = None
    alt: float = 0.0

    def __post_init__(self) -> None:
        if self.mode not in ("first_fix", "fixed"):
            raise ValueError("mode: must be 'first_fix' or 'fixed'")
        if self.mode == "fixed":
            if self.lat is None or self.lon is None:
                raise ValueError("lat: 'fixed' datum needs lat and lon")
            if not -90.0 <= self.lat <= 90.0:
                raise ValueError("lat: must be within [-90, 90]")
            if not -180.0 <= self.lon <= 180.0:
                raise ValueError("lon: must be within [-180, 180]")


DEFAULT_JSON = ("127.0.0.1:5005",)


@dataclass(frozen=True, slots=True)
class OutputSettings:
    """Sinks: one list of UDP destinations ``host:port`` per format (``json``, ``nmea``), and the status line.

    A destination is an IP address or a host name (resolved at start). Without ``allow_remote`` every destination
    must be this host (loopback, an address of its own, an interface-local IPv6 multicast group); broadcast,
    multicast beyond the host and other hosts need ``allow_remote = true`` (:mod:`sumhe.io.udp`)."""

    json: tuple[str, ...] = DEFAULT_JSON
    nmea: tuple[str, ...] = ()
    status_udp: str | None = None
    status_interval_s: float = 5.0
    allow_remote: bool = False

    def __post_init__(self) -> None:
        for name in ("json", "nmea"):
            for dest in getattr(self, name):
                _destination(name, dest)
        if self.status_udp is not None:
            _destination("status_udp", self.status_udp)
        _positive(self, "status_interval_s")

    @property
    def formats(self) -> dict[str, tuple[str, ...]]:
        """Format -> destinations, for the formats that have any."""
        return {name: dests for name in ("json", "nmea") if (dests := getattr(self, name))}


LEGACY_OUTPUT_KEYS = ("udp", "formats")
"""Keys of ``[output]`` before one destination list per format; still read (every listed format to every
destination, as before), with a warning naming the keys that replace them."""


@dataclass(frozen=True, slots=True)
class Config:
    """All settings of one sumhe process.

    ``source`` is the config file (or ``"<defaults>"``); ``origins`` says where a key given elsewhere came from
    (``"environment variable SUMHE_CAN__CHANNEL"``, ``"command line"``), so errors blame the right place.
    """

    can: CanSettings = field(default_factory=CanSettings)
    gps: GpsSettings = field(default_factory=GpsSettings)
    datum: DatumSettings = field(default_factory=DatumSettings)
    output: OutputSettings = field(default_factory=OutputSettings)
    vehicle: VehicleSettings = field(default_factory=VehicleSettings)
    sensors: SensorSettings = field(default_factory=SensorSettings)
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    source: str = "<defaults>"
    base_dir: Path = field(default_factory=Path.cwd)
    log_dirs: tuple[Path, ...] = ()
    """The folders of the logs being replayed: files named in the config are looked for there too."""
    origins: Mapping[str, str] = field(default_factory=dict)

    def blame(self, key: str) -> str:
        """Where ``key`` (dotted, e.g. ``can.signals.speed``) was set: an environment variable, the command line,
        or the config file (also for keys left at their defaults)."""
        return _origin_of(key, self.origins, self.source)

    def error(self, key: str, text: str) -> ConfigError:
        """A ConfigError ``"<where key was set>: <key>: <text>"``."""
        return ConfigError(f"{self.blame(key)}: {key}: {text}")

    def resolve_path(self, value: str, key: str) -> Path:
        """Find a file named in the config: absolute, next to the config file, in the working directory, beside
        the logs being replayed (:attr:`log_dirs`), or bundled with the package (``dbc/...`` and ``data/...``)."""
        p = Path(value).expanduser()
        dirs = [self.base_dir, Path.cwd(), *self.log_dirs]
        candidates = [p] if p.is_absolute() else [*(d / p for d in dirs), PACKAGE_DATA / p.name]
        for c in candidates:
            if c.is_file():
                return c
        where = (
            ""
            if p.is_absolute()
            else f" (looked in {', '.join(str(d) for d in dict.fromkeys(dirs))} and the bundled files)"
        )
        raise self.error(key, f"file not found: {value}{where}")

    @property
    def dbc_paths(self) -> tuple[Path, ...]:
        """The files of ``can.dbc``, found by :meth:`resolve_path`."""
        return tuple(self.resolve_path(name, "can.dbc") for name in self.can.dbc_files)

    @classmethod
    def of(cls, estimation: EstimationSettings, **sections: Any) -> Config:
        """A config with the estimator, vehicle and sensors of ``estimation`` (and other ``sections`` given)."""
        sensors = SensorSettings(estimation.gnss, estimation.can)
        return cls(estimator=estimation.estimator, vehicle=estimation.vehicle, sensors=sensors, **sections)

    @property
    def estimation(self) -> EstimationSettings:
        """What an estimator reads: ``[estimator]``, ``[vehicle]`` and ``[sensors]``."""
        return EstimationSettings.of(self.estimator, self.vehicle, self.sensors)


_SIGNAL_QUANTITIES: dict[type, tuple[str, ...]] = {CanSettings: CAN_QUANTITIES, GpsSettings: GNSS_QUANTITIES}
"""Settings classes with a ``signals`` table -> the quantities it may map."""

REQUIRED_SIGNALS: tuple[str, ...] = ("speed", "yaw_rate")
"""The CAN quantities every estimator needs: ``sumhe run`` and ``sumhe replay`` refuse to start without them."""


def require_signals(config: Config) -> None:
    """ConfigError naming ``can.signals.<quantity>`` (and where the mapping came from) for a required quantity
    that is not mapped."""
    for quantity in REQUIRED_SIGNALS:
        if quantity not in config.can.signals:
            raise config.error(
                f"can.signals.{quantity}",
                "not mapped; sumhe needs the vehicle's speed and yaw rate "
                f'(add {quantity} = "MESSAGE.SIGNAL" under [can.signals]; README: "A real car")',
            )


_SECTIONS: dict[str, type] = {
    "can": CanSettings,
    "gps": GpsSettings,
    "datum": DatumSettings,
    "output": OutputSettings,
    "vehicle": VehicleSettings,
    "sensors": SensorSettings,
    "estimator": EstimatorSettings,
}


def parse_host_port(text: str) -> tuple[str, int]:
    """``"127.0.0.1:5005"`` or ``"[::1]:5005"`` -> (host, port); ValueError naming the text."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{text!r} is not a host:port destination (e.g. '127.0.0.1:5005' or '[::1]:5005')")
    return host, int(port)


_HOST_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def is_host(text: str) -> bool:
    """Whether ``text`` is an IP address (IPv6 with an optional ``%zone``) or a host name (RFC 1123 labels)."""
    try:
        ipaddress.ip_address(text.partition("%")[0])
    except ValueError:
        labels = text.removesuffix(".").split(".")
        return len(text) <= 253 and all(_HOST_LABEL.fullmatch(x) for x in labels) and not labels[-1].isdigit()
    return True


def _destination(key: str, text: str) -> None:
    try:
        host, _ = parse_host_port(text)
    except ValueError as e:
        raise ValueError(f"{key}: {e}") from e
    if not is_host(host):
        raise ValueError(
            f"{key}: '{printable(text, 80)}': '{printable(host, 80)}' is neither an IP address nor a host name"
        )


def _positive(obj: object, *names: str) -> None:
    for n in names:
        if getattr(obj, n) <= 0:
            raise ValueError(f"{n}: must be positive")


_SIGNAL_KEYS = ("signal", "scale", "unit", "channel", "valid")
_IMU_KEYS = ("message", "rates", "accelerations")
IMU_QUANTITY = "yaw_rate"
"""The one quantity a 3-axis IMU's signals may give (``rates`` and ``accelerations``: :class:`SignalSpec`)."""


def _parse_signal(value: Any, key: str, imu: bool) -> SignalSpec:
    """One quantity's spec; ``imu``: whether the quantity may come from a 3-axis IMU's signals."""
    if isinstance(value, str):
        value = {"signal": value}
    if not isinstance(value, Mapping):
        raise ValueError(f"{key}: expected 'MESSAGE.SIGNAL' or a table with 'signal'")
    known = _SIGNAL_KEYS + _IMU_KEYS if imu else _SIGNAL_KEYS
    unknown = set(value) - set(known)
    if unknown:
        raise ValueError(f"{key}.{sorted(unknown)[0]}: unknown key ({', '.join(known)})")
    rates: tuple[str, ...] = ()
    accelerations: tuple[str, ...] = ()
    if set(_IMU_KEYS) & set(value):
        if "signal" in value:
            raise ValueError(f"{key}: either signal or message, rates and accelerations (a 3-axis IMU), not both")
        message = _signal_name(value.get("message"), f"{key}.message", "the IMU's message")
        rates, accelerations = (_imu_signals(value.get(k), f"{key}.{k}") for k in _IMU_KEYS[1:])
        signal = ""
    else:
        name = value.get("signal")
        if not isinstance(name, str) or name.count(".") != 1 or "" in name.split("."):
            raise ValueError(f"{key}: expected 'MESSAGE.SIGNAL', got {name!r}")
        message, signal = name.split(".")
    scale = value.get("scale", 1.0)
    if isinstance(scale, bool) or not isinstance(scale, int | float) or scale == 0:
        raise ValueError(f"{key}.scale: must be a non-zero number")
    unit = value.get("unit")
    if unit is not None and not isinstance(unit, str):
        raise ValueError(f"{key}.unit: must be a string")
    valid = value.get("valid")
    if valid is not None and (not isinstance(valid, str) or not valid or "." in valid):
        raise ValueError(f"{key}.valid: expected the name of a signal of {message}, got {valid!r}")
    channel = _parse_channel(value.get("channel"), key)
    return SignalSpec(message, signal, float(scale), unit, channel, valid, rates, accelerations)


def _signal_name(name: Any, key: str, what: str) -> str:
    if not isinstance(name, str) or not name or "." in name:
        raise ValueError(f"{key}: expected the name of {what}, got {name!r}")
    return name


def _imu_signals(names: Any, key: str) -> tuple[str, ...]:
    """Three signal names of the IMU's message: its three axes, in the order the other list names them."""
    if not isinstance(names, list | tuple) or len(names) != 3:
        raise ValueError(f"{key}: expected a list of the three axes' signals of the message, got {names!r}")
    out = tuple(_signal_name(n, key, "a signal of the message") for n in names)
    if len(set(out)) != 3:
        raise ValueError(f"{key}: three different signals needed, got {list(out)}")
    return out


def _parse_channel(channel: Any, key: str) -> str | None:
    """A bus channel as text: a non-negative integer (MF4 ``BusChannel``, ``1``) or a name (``"can0"``)."""
    if channel is None:
        return None
    if isinstance(channel, int) and not isinstance(channel, bool) and channel >= 0:
        return str(channel)
    if isinstance(channel, str) and channel.strip():
        return channel.strip()
    raise ValueError(f"{key}.channel: expected a channel number (e.g. 1) or name (e.g. 'can0'), got {channel!r}")


def _coerce(value: Any, hint: Any, key: str) -> Any:
    """Check a TOML value against a field's type hint, converting lists to tuples and ints to floats."""
    origin = typing.get_origin(hint)
    if origin in (Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, key)
            except ValueError as e:
                errors.append(str(e))
        raise ValueError(errors[0] if errors else f"{key}: bad value {value!r}")
    if origin is Mapping:
        (_key, item) = typing.get_args(hint)
        if not isinstance(value, Mapping):
            raise ValueError(f"{key}: expected a table, got {value!r}")
        return {str(k): _coerce(v, item, f"{key}.{k}") for k, v in value.items()}
    if origin is tuple:
        (item, _ellipsis) = typing.get_args(hint)
        if isinstance(value, str) or not isinstance(value, list | tuple):
            raise ValueError(f"{key}: expected a list, got {value!r}")
        return tuple(_coerce(v, item, key) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{key}: expected true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{key}: expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ValueError(f"{key}: expected a string, got {value!r}")
        return value
    raise ValueError(f"{key}: unsupported setting type {hint!r}")


def build_section(cls: type, table: Mapping[str, Any], section: str, base: Any = None) -> Any:
    """Build one frozen settings dataclass from a TOML table; ValueError messages name ``section.key``.

    A nested settings table (e.g. ``[estimator.mhe]``) changes the keys it names in its field's default; a key
    that moved elsewhere is refused naming its new place (:data:`sumhe.settings.moved.MOVED`)."""
    hints = typing.get_type_hints(cls)
    defaults = {f.name: f for f in dataclasses.fields(cls) if f.init}
    kwargs: dict[str, Any] = {}
    for key, value in table.items():
        full = f"{section}.{key}"
        if full in MOVED:
            raise ValueError(f"{full}: moved: set {MOVED[full]}")
        if key not in defaults:
            close = difflib.get_close_matches(key, defaults, n=1)
            guess = f"did you mean {section}.{close[0]}? " if close else ""
            raise ValueError(f"{full}: unknown key ({guess}known: {', '.join(sorted(defaults))})")
        if key == "signals" and cls in _SIGNAL_QUANTITIES:
            quantities = _SIGNAL_QUANTITIES[cls]
            if not isinstance(value, Mapping):
                raise ValueError(f"{full}: expected a table of quantity = 'MESSAGE.SIGNAL'")
            for q in value:
                if q not in quantities:
                    raise ValueError(f"{full}.{q}: unknown quantity (known: {', '.join(quantities)})")
            imu = cls is CanSettings
            kwargs[key] = {q: _parse_signal(v, f"{full}.{q}", imu and q == IMU_QUANTITY) for q, v in value.items()}
        elif dataclasses.is_dataclass(hints[key]):
            if not isinstance(value, Mapping):
                raise ValueError(f"{full}: expected a table")
            f = defaults[key]
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            kwargs[key] = build_section(hints[key], value, full, default)
        else:
            kwargs[key] = _coerce(value, hints[key], full)
    try:
        return dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if msg.startswith(section + ".") else f"{section}.{msg}") from e


ENV_PREFIX = "SUMHE_"

MAX_DEPTH = 16
"""Deepest nesting of tables and arrays a config value may have (sumhe's own go 3 deep)."""


def _too_deep(value: Any, key: str) -> str | None:
    """The dotted key of the first place in ``value`` (at ``key``) nested more than :data:`MAX_DEPTH` deep, or None
    (walked without recursion)."""
    stack = [(value, key, 0)]
    while stack:
        node, where, depth = stack.pop()
        if depth > MAX_DEPTH:
            return where
        if isinstance(node, Mapping):
            stack.extend((v, f"{where}.{k}" if where else str(k), depth + 1) for k, v in node.items())
        elif isinstance(node, list):
            stack.extend((v, where, depth + 1) for v in node)
    return None


def _check_depth(data: Any, origin: str, key: str = "") -> None:
    where = _too_deep(data, key)
    if where is not None:
        raise ConfigError(f"{origin}: {printable(where, 80)}: nested more than {MAX_DEPTH} tables or arrays deep")


def _loads(text: str, origin: str, key: str | None = None) -> dict[str, Any]:
    """``tomllib.loads`` with nesting too deep for its recursive parser turned into a ConfigError naming ``key`` (or
    the line and its key)."""
    try:
        return tomllib.loads(text)
    except RecursionError:
        if key is not None:
            raise ConfigError(f"{origin}: {key}: nested more than {MAX_DEPTH} tables or arrays deep") from None
        n, line = next(
            ((n, line) for n, line in enumerate(text.splitlines(), 1) if _opens(line) > MAX_DEPTH), (0, text)
        )
        key = line.partition("=")[0].strip() if "=" in line else "?"
        where = f"line {n}: " if n else ""
        raise ConfigError(
            f"{origin}: {where}{printable(key, 80)}: nested more than {MAX_DEPTH} tables or arrays deep"
        ) from None


def _opens(line: str) -> int:
    """The most ``[`` / ``{`` a line opens without closing one (a rough nesting depth, strings not skipped)."""
    depth = most = 0
    for c in line:
        if c in "[{":
            depth += 1
            most = max(most, depth)
        elif c in "]}":
            depth -= 1
    return most


def _env_overrides(env: Mapping[str, str]) -> dict[str, tuple[Any, str]]:
    """``SUMHE_<SECTION>__<KEY>[__<SUBKEY>]`` variables as dotted key -> (value, origin). A value is read as a
    TOML value where it parses as one (``500000``, ``true``, ``["a", "b"]``), else as a plain string. A variable
    that names a section but misses the double underscore is an error (it would be ignored otherwise)."""
    out: dict[str, tuple[Any, str]] = {}
    for name, raw in env.items():
        if not name.startswith(ENV_PREFIX):
            continue
        rest = name[len(ENV_PREFIX) :].lower()
        origin = f"environment variable {name}"
        if "__" not in rest:
            section = rest.partition("_")[0]
            if section in _SECTIONS:
                hint = f"{ENV_PREFIX}{section.upper()}__{rest[len(section) + 1 :].upper()}"
                raise ConfigError(f"{origin}: not a setting: write {ENV_PREFIX}<SECTION>__<KEY> (e.g. {hint})")
            continue
        key = rest.replace("__", ".")
        try:
            value: Any = _loads(f"v = {raw}", origin, key)["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        _check_depth(value, origin, key)
        out[key] = (value, origin)
    return out


def _apply(data: dict[str, Any], dotted: Mapping[str, tuple[Any, str]], origins: dict[str, str]) -> None:
    for key, (value, origin) in dotted.items():
        section, _, rest = key.partition(".")
        if section not in _SECTIONS or not rest:
            raise ConfigError(f"{origin}: {key}: unknown setting (sections: {', '.join(_SECTIONS)})")
        node = data.setdefault(section, {})
        *parents, leaf = rest.split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{origin}: {key}: {p} is not a table")
        node[leaf] = value
        origins[key] = origin


def _origin_of(key: str, origins: Mapping[str, str], default: str) -> str:
    """The origin of ``key`` or of the nearest enclosing table that was given as a whole."""
    parts = key.split(".")
    for n in range(len(parts), 0, -1):
        origin = origins.get(".".join(parts[:n]))
        if origin is not None:
            return origin
    return default


def _legacy_output(table: Mapping[str, Any], origins: Mapping[str, str], source: str) -> dict[str, Any]:
    """``[output] udp`` + ``formats`` (every format to every destination) as ``json`` / ``nmea`` lists."""
    given = [k for k in LEGACY_OUTPUT_KEYS if k in table]
    if not given:
        return dict(table)
    where = _origin_of(f"output.{given[0]}", origins, source)
    mixed = [k for k in ("json", "nmea") if k in table]
    if mixed:
        raise ConfigError(
            f"{where}: output.{given[0]}: replaced by output.json and output.nmea; remove it (output.{mixed[0]} is set)"
        )
    out = {k: v for k, v in table.items() if k not in LEGACY_OUTPUT_KEYS}
    formats = table.get("formats", ["json"])
    udp = table.get("udp", list(DEFAULT_JSON))
    if isinstance(formats, str) or not isinstance(formats, list):
        raise ConfigError(f"{where}: output.formats: expected a list, got {formats!r}")
    try:
        for dest in _coerce(udp, tuple[str, ...], "output.udp"):
            _destination("output.udp", dest)
    except ValueError as e:
        raise ConfigError(f"{where}: {e}") from e
    for f in formats:
        if f not in ("json", "nmea"):
            raise ConfigError(f"{where}: output.formats: unknown format {f!r} (json, nmea)")
    for f in ("json", "nmea"):
        out[f] = udp if f in formats else []
    new = " and ".join(f"{f} = {udp!r}".replace("'", '"') for f in formats)
    log.warning(
        "%s: output.%s: replaced by one destination list per format; write %s under [output]",
        where,
        " and output.".join(given),
        new,
    )
    return out


def _read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    source = str(path)
    try:
        data = _loads(Path(path).read_text(encoding="utf-8"), source)
    except FileNotFoundError as e:
        raise ConfigError(f"{source}: file not found") from e
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{source}: cannot read: {printable(str(e))}") from e
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{source}: not valid TOML: {printable(str(e))}") from e
    _check_depth(data, source)
    return data


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> None:
    """Merge the TOML tables of ``over`` into ``base``, key by key (a value replaces, a table merges)."""
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = value


def load_config(
    path: str | os.PathLike[str] | None = None,
    env: Mapping[str, str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    layers: Sequence[str | os.PathLike[str]] = (),
) -> Config:
    """Load, merge and validate the configuration; ConfigError naming the key and where it was set (the file,
    the environment variable, or the command line). ``layers`` are TOML files merged over ``path`` in order, key
    by key (e.g. one recorded drive's ``config.toml`` over a fleet's config); the environment and ``overrides``
    still come last."""
    source = " + ".join(str(p) for p in (*([path] if path is not None else []), *layers)) or "<defaults>"
    data: dict[str, Any] = _read_toml(path) if path is not None else {}
    for layer in layers:
        _merge(data, _read_toml(layer))
    origins: dict[str, str] = {}
    for name, table in data.items():
        if section_error := _section_error(name, table):
            raise ConfigError(f"{source}: {section_error}")
    _apply(data, _env_overrides(os.environ if env is None else env), origins)
    _apply(data, {k: (v, "command line") for k, v in (overrides or {}).items()}, origins)
    kwargs: dict[str, Any] = {}
    for section, table in data.items():
        if section == "output":
            table = _legacy_output(table, origins, source)
        try:
            kwargs[section] = build_section(_SECTIONS[section], table, section)
        except ValueError as e:
            msg = str(e)
            raise ConfigError(f"{_origin_of(msg.partition(':')[0], origins, source)}: {msg}") from e
    first = path if path is not None else next(iter(layers), None)
    base = Path(first).resolve().parent if first is not None else Path.cwd()
    return Config(**kwargs, source=source, base_dir=base, origins=origins)


def _section_error(section: str, table: Any) -> str | None:
    if section not in _SECTIONS:
        return f"{section}: unknown section (known: {', '.join(_SECTIONS)})"
    if not isinstance(table, Mapping):
        return f"{section}: expected a table"
    return None


def describe(config: Config) -> dict[str, Any]:
    """The resolved config as plain data, for the start-up log line."""
    out = {s: dataclasses.asdict(getattr(config, s)) for s in _SECTIONS}
    out["source"] = config.source
    return out
