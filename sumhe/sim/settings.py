"""Settings of one simulated drive, and their round trip through ``scenario.toml``.

Everything a drive depends on is here: the same settings (seed included) give the same bytes. Settings left at
None (speed scale, yaw-rate bias, GPS error scale) are drawn from the seed or take the error model's default;
the values actually applied are recorded in the truth and in the ``[applied]`` table of ``scenario.toml``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sumhe.config import build_section

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

SCENARIO_NAMES = ("urban", "highway", "offroad")
GPS_ERROR_MODELS = ("uniform", "gaussian", "walk", "rtk")
OUTAGE_STYLES = ("silence", "nofix")
CAN_LAYOUTS = ("reference", "production")
"""``reference``: dbc/sumhe_ref.dbc as it is; ``production``: dbc/sumhe_prod.dbc with the drive's quanta."""
SPEED_SOURCES = ("broadcast", "obd")
"""Where the speed comes from: a cyclic chassis message, or OBD-II mode 01 PID 0x0D polled by a logger."""
OBD_ROUNDINGS = ("round", "floor")
TALKERS = ("GP", "GN")
DEFAULT_GPS_ERROR_M = {"uniform": 1.0, "gaussian": 1.0, "walk": 1.0, "rtk": 0.03}
"""Scale of each error model: the half-width of the uniform box (uniform, rtk) or the 1-sigma per axis."""
START_UNIX_S = 1780300800.0
"""2026-06-01T08:00:00Z."""


@dataclass(frozen=True, slots=True)
class SimSettings:
    """One simulated drive. Times in s (relative to the start unless named ``_unix_s``), distances in m.

    GPS: ``gps_error`` is the error model: ``uniform`` (bounded box of half-width ``gps_error_m`` per axis, the
    assumption of paper 000), ``gaussian`` (white, sigma ``gps_error_m`` per axis), ``walk`` (a first-order
    Gauss-Markov random walk with correlation time ``gps_walk_tau_s`` plus white noise, together sigma
    ``gps_error_m`` per axis: what real receivers do) or ``rtk`` (uniform, default +-3 cm, GGA quality 4).
    ``multipath_per_min`` jumps of ``multipath_min_m``-``multipath_max_m`` lasting 1-10 s are added on top.
    ``outages`` are (start_s, length_s) half-open intervals of fix time with no valid fix, either silent or
    sent as "no fix" sentences (GGA quality 0, RMC status V, GST and HDT empty). Two antennas sit on the
    lengthwise axis, antenna 2 ``antenna_distance_m`` behind antenna 1 (the reference point, the rear-axle centre).

    CAN: speed reported as truth * ``speed_scale`` + noise, yaw rate as truth + bias + noise, both taken
    ``can_sensor_delay_s`` before the frame goes out; host timestamps with USB-adapter jitter and bursts.

    Real-car errors (all off by default, which is the ``kind`` profile; :mod:`sumhe.sim.profiles` draws them for
    the ``realistic`` one; docs/simulator.md gives each one's range and evidence):

    - GNSS clock: a fix tagged t (UTC) lies where the car is at t + ``gps_time_offset_s`` on the CAN/host clock
      (the offset at mid-drive; it drifts by ``gps_clock_drift_ppm``); its NMEA arrives ``gps_latency_s`` +
      U(0, ``gps_latency_jitter_s``) after that instant. ``gps_drop_rate`` of the epochs are never sent.
    - GNSS errors: heavy-tailed outliers (``gps_outliers_per_min`` jumps of mean size ``gps_outlier_m``,
      0.1-1.5 s long) on top of the error model and multipath; with ``gps_velocity_sigma_mps`` > 0 the speed and
      course come from the antenna's velocity plus a Gauss-Markov error (``gps_velocity_tau_s``) instead of
      white speed noise. ``gps_nmea_hdop`` / ``gps_nmea_gst`` false: no HDOP field, no GST sentence.
    - Geometry: antenna 1 sits ``antenna_forward_m`` ahead of and ``antenna_left_m`` left of the rear-axle
      reference point (the truth); the body's heading is the direction of motion minus the sideslip
      ``thrust_angle_deg + sideslip_deg_per_mps2 * lateral acceleration`` (nose into the turn), so the yaw-rate
      sensor sees the path's yaw rate plus the sideslip's rate, and HDT the body's heading.
    - CAN: yaw rate = ``yaw_rate_scale`` * body yaw rate + bias + noise. ``can_layout = "production"`` speaks
      dbc/sumhe_prod.dbc with a ``yaw_rate_quantum_dps`` / ``speed_quantum_kmh`` resolution (the drive carries its
      own ``vehicle.dbc``); ``speed_source = "obd"`` replaces the broadcast speed by OBD-II PID 0x0D polled at
      ``obd_rate_hz`` (whole km/h, ``obd_rounding``, ``obd_delay_s`` old) and takes the yaw rate from an
      aftermarket IMU module on can1 (``imu_sign`` -1: mounted upside down). ``can_poll_max_s`` > 0: the host
      reads the USB adapter at random intervals up to that, so frames arrive in bursts; ``can_ecu_jitter_s`` is
      the senders' task jitter.
    """

    scenario: str = "urban"
    seed: int = 0
    duration_s: float = 240.0
    start_unix_s: float = START_UNIX_S
    datum_lat_deg: float = 50.0755
    datum_lon_deg: float = 14.4378
    datum_alt_m: float = 250.0
    truth_rate_hz: float = 100.0
    gps_rate_hz: float = 10.0
    gps_error: str = "walk"
    gps_error_m: float | None = None
    gps_walk_tau_s: float = 60.0
    multipath_per_min: float = 0.0
    multipath_min_m: float = 5.0
    multipath_max_m: float = 50.0
    outages: tuple[tuple[float, float], ...] = ()
    outage_style: str = "silence"
    gps_latency_s: float = 0.08
    gps_latency_jitter_s: float = 0.02
    antennas: int = 1
    antenna_distance_m: float = 1.0
    heading_sigma_deg: float = 0.2
    speed_scale: float | None = None
    yaw_rate_bias_dps: float | None = None
    yaw_rate_bias_drift_dps: float = 0.02
    speed_noise_mps: float = 0.02
    wheel_speed_noise_mps: float = 0.03
    yaw_rate_noise_dps: float = 0.1
    accel_noise_mps2: float = 0.05
    can_sensor_delay_s: float = 0.02
    can_jitter_s: float = 0.0005
    can_burst_per_min: float = 2.0
    can_burst_max_s: float = 0.05
    can_drop_rate: float = 0.0
    profile: str = "kind"
    gps_time_offset_s: float = 0.0
    gps_clock_drift_ppm: float = 0.0
    gps_drop_rate: float = 0.0
    gps_outliers_per_min: float = 0.0
    gps_outlier_m: float = 3.0
    gps_velocity_sigma_mps: float = 0.0
    gps_velocity_tau_s: float = 1.0
    gps_nmea_hdop: bool = True
    gps_nmea_gst: bool = True
    gps_talker: str = "GP"
    antenna_forward_m: float = 0.0
    antenna_left_m: float = 0.0
    thrust_angle_deg: float = 0.0
    sideslip_deg_per_mps2: float = 0.0
    yaw_rate_scale: float = 1.0
    can_layout: str = "reference"
    speed_source: str = "broadcast"
    yaw_rate_quantum_dps: float = 0.244
    speed_quantum_kmh: float = 0.01
    obd_rate_hz: float = 2.0
    obd_delay_s: float = 0.1
    obd_rounding: str = "round"
    imu_sign: int = 1
    can_poll_max_s: float = 0.0
    can_ecu_jitter_s: float = 0.0001

    def __post_init__(self) -> None:
        _choice(self, "scenario", SCENARIO_NAMES)
        _choice(self, "gps_error", GPS_ERROR_MODELS)
        _choice(self, "outage_style", OUTAGE_STYLES)
        _choice(self, "can_layout", CAN_LAYOUTS)
        _choice(self, "speed_source", SPEED_SOURCES)
        _choice(self, "obd_rounding", OBD_ROUNDINGS)
        _choice(self, "gps_talker", TALKERS)
        if not isinstance(self.profile, str) or not self.profile.isidentifier():
            raise ValueError(f"profile: must be a name, got {self.profile!r}")
        if self.imu_sign not in (1, -1) or isinstance(self.imu_sign, bool):
            raise ValueError(f"imu_sign: must be 1 or -1, got {self.imu_sign!r}")
        for name in ("gps_nmea_hdop", "gps_nmea_gst"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: must be true or false, got {getattr(self, name)!r}")
        if self.speed_source == "obd" and self.can_layout != "production":
            raise ValueError("speed_source: 'obd' needs can_layout = 'production' (the IMU module is in its DBC)")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: must be an integer >= 0, got {self.seed!r}")
        if isinstance(self.antennas, bool) or self.antennas not in (1, 2):
            raise ValueError(f"antennas: must be 1 or 2, got {self.antennas!r}")
        _within(self, "duration_s", 1.0, 3600.0)
        _within(self, "start_unix_s", 0.0, 4102444800.0)
        _within(self, "datum_lat_deg", -85.0, 85.0)
        _within(self, "datum_lon_deg", -180.0, 180.0)
        _within(self, "datum_alt_m", -500.0, 9000.0)
        _within(self, "truth_rate_hz", 10.0, 1000.0)
        _within(self, "gps_rate_hz", 1.0, 20.0)
        if abs(100.0 / self.gps_rate_hz - round(100.0 / self.gps_rate_hz)) > 1e-9:
            raise ValueError(
                f"gps_rate_hz: the period must be whole centiseconds (e.g. 1, 5, 10, 20 Hz), got {self.gps_rate_hz!r}"
            )
        _within(self, "gps_walk_tau_s", 1.0, 3600.0)
        _within(self, "multipath_per_min", 0.0, 60.0)
        _within(self, "multipath_min_m", 0.0, 1000.0)
        _within(self, "multipath_max_m", self.multipath_min_m, 1000.0)
        _within(self, "gps_latency_s", 0.0, 1.0)
        _within(self, "gps_latency_jitter_s", 0.0, 0.5)
        _within(self, "antenna_distance_m", 0.1, 10.0)
        _within(self, "heading_sigma_deg", 0.0, 10.0)
        _within(self, "yaw_rate_bias_drift_dps", 0.0, 1.0)
        for name in ("speed_noise_mps", "wheel_speed_noise_mps", "accel_noise_mps2"):
            _within(self, name, 0.0, 1.0)
        _within(self, "yaw_rate_noise_dps", 0.0, 5.0)
        _within(self, "can_sensor_delay_s", 0.0, 0.5)
        _within(self, "can_jitter_s", 0.0, 0.1)
        _within(self, "can_burst_per_min", 0.0, 600.0)
        _within(self, "can_burst_max_s", 0.0, 1.0)
        _within(self, "can_drop_rate", 0.0, 0.9)
        _within(self, "gps_time_offset_s", -1.0, 1.0)
        _within(self, "gps_clock_drift_ppm", -1000.0, 1000.0)
        _within(self, "gps_drop_rate", 0.0, 0.5)
        _within(self, "gps_outliers_per_min", 0.0, 60.0)
        _within(self, "gps_outlier_m", 0.0, 100.0)
        _within(self, "gps_velocity_sigma_mps", 0.0, 5.0)
        _within(self, "gps_velocity_tau_s", 0.01, 60.0)
        _within(self, "antenna_forward_m", -5.0, 5.0)
        _within(self, "antenna_left_m", -2.0, 2.0)
        _within(self, "thrust_angle_deg", -5.0, 5.0)
        _within(self, "sideslip_deg_per_mps2", -2.0, 2.0)
        _within(self, "yaw_rate_scale", 0.5, 1.5)
        _within(self, "yaw_rate_quantum_dps", 0.001, 1.0)
        _within(self, "speed_quantum_kmh", 0.001, 1.0)
        _within(self, "obd_rate_hz", 0.1, 20.0)
        _within(self, "obd_delay_s", 0.0, 2.0)
        _within(self, "can_poll_max_s", 0.0, 0.1)
        _within(self, "can_ecu_jitter_s", 0.0, 0.01)
        if self.gps_error_m is not None:
            _within(self, "gps_error_m", 0.001, 100.0)
        if self.speed_scale is not None:
            _within(self, "speed_scale", 0.8, 1.2)
        if self.yaw_rate_bias_dps is not None:
            _within(self, "yaw_rate_bias_dps", -5.0, 5.0)
        for outage in self.outages:
            if not isinstance(outage, tuple | list) or len(outage) != 2:
                raise ValueError(f"outages: each outage is (start_s, length_s), got {outage!r}")
            start, length = outage
            if not (_is_number(start) and _is_number(length) and 0.0 <= start < self.duration_s and length > 0):
                raise ValueError(f"outages: need 0 <= start_s < duration_s and length_s > 0, got {outage!r}")
        for name in _FLOAT_FIELDS:
            value = getattr(self, name)
            if isinstance(value, int):
                object.__setattr__(self, name, float(value))
        object.__setattr__(self, "outages", tuple((float(start), float(length)) for start, length in self.outages))

    @property
    def gps_error_scale_m(self) -> float:
        """``gps_error_m``, or the error model's default when it is None."""
        return DEFAULT_GPS_ERROR_M[self.gps_error] if self.gps_error_m is None else self.gps_error_m

    @property
    def speed_age_beyond_s(self) -> float:
        """How much older the CAN speed is than the yaw rate (s): an OBD-II reply's ``obd_delay_s`` beyond the chassis
        sensors' ``can_sensor_delay_s``, 0 for a broadcast speed (``sumhe calibrate``'s ``can_delay_s``, the
        config's ``sensors.can.speed_delay_s``)."""
        return self.obd_delay_s - self.can_sensor_delay_s if self.speed_source == "obd" else 0.0


_FLOAT_FIELDS = tuple(f.name for f in dataclasses.fields(SimSettings) if f.type in ("float", "float | None"))
"""Fields normalised from int to float, so equal settings always write the same scenario.toml."""
_NAMES = [f.name for f in dataclasses.fields(SimSettings)]
REAL_CAR_FIELDS = tuple(_NAMES[_NAMES.index("profile") :])
"""The real-car error fields: written to scenario.toml only where they differ from the default (off), so a
``kind`` drive's scenario.toml is what it was before they existed."""


def _is_number(value: Any) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float) and math.isfinite(value)


def _within(obj: SimSettings, name: str, low: float, high: float) -> None:
    value = getattr(obj, name)
    if not (_is_number(value) and low <= value <= high):
        raise ValueError(f"{name}: must be a number within [{low:g}, {high:g}], got {value!r}")


def _choice(obj: SimSettings, name: str, choices: tuple[str, ...]) -> None:
    value = getattr(obj, name)
    if value not in choices:
        raise ValueError(f"{name}: must be one of {', '.join(choices)}, got {value!r}")


def settings_from_mapping(table: Mapping[str, Any]) -> SimSettings:
    """Settings from a TOML-like table (lists become tuples); ValueError naming ``sim.<key>``."""
    return build_section(SimSettings, table, "sim")  # type: ignore[no-any-return]


def load_settings(path: str | Path) -> SimSettings:
    """Read the ``[sim]`` table of a ``scenario.toml``; ValueError naming the file and key when it is wrong."""
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise ValueError(f"{path}: cannot read scenario: {e}") from e
    table = data.get("sim")
    if not isinstance(table, Mapping):
        raise ValueError(f"{path}: no [sim] table")
    try:
        return settings_from_mapping(table)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e


def settings_to_toml(
    settings: SimSettings,
    applied: Mapping[str, float | str],
    calibration: Mapping[str, float] | None = None,
) -> str:
    """``scenario.toml``: the ``[sim]`` table (None fields and real-car fields at their default omitted), the
    drawn ``[applied]`` values and, when given, the ``[calibration]`` truth in ``sumhe calibrate``'s terms."""
    lines = ["# sumhe simulated drive: `sumhe simulate --settings scenario.toml --out DIR` regenerates it.", "[sim]"]
    default = SimSettings()
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if value is None or (f.name in REAL_CAR_FIELDS and value == getattr(default, f.name)):
            continue
        lines.append(f"{f.name} = {_toml_value(value)}")
    lines += ["", "[applied]"]
    lines += [f"{key} = {_toml_value(value)}" for key, value in applied.items()]
    if calibration:
        lines += ["", "[calibration]"]
        lines += [f"{key} = {_toml_value(value)}" for key, value in calibration.items()]
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"
