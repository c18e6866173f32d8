"""The vehicle (``[vehicle]``) and the sensor models (``[sensors.gnss]``, ``[sensors.can]``) every estimator reads.

Units are in the names: ``_m``, ``_mps`` (m/s), ``_mps2``, ``_rad``, ``_rps`` (rad/s), ``_rps2``, ``_s``. These
describe the car and its sensors, not an estimator: the measurement front-end (:mod:`sumhe.frontend`) turns them
into each measurement's error model once, for every estimator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sumhe.settings.checks import non_negative, one_of, positive

FALLBACK_SPEED_RESOLUTION_MPS = 0.01
"""The CAN speed's quantum (m/s) when neither ``sensors.can.speed_resolution_mps`` nor a DBC says it."""
FALLBACK_YAW_RATE_RESOLUTION_RPS = 0.0005
"""The CAN yaw rate's quantum (rad/s) when neither ``sensors.can.yaw_rate_resolution_rps`` nor a DBC says it."""
COARSE_QUANTUM_MPS = 0.1
"""From this CAN speed quantum on (0.36 km/h) a truncated speed is told from a rounded one (half a quantum low on
the mean): a finer quantum's offset is below what a drive's spread of speeds tells apart from the scale."""
SPEED_ROUNDINGS = ("round", "truncate")
"""How a CAN speed is made whole quanta (``sensors.can.speed_rounding``): to the nearest, or towards 0."""


@dataclass(frozen=True, slots=True)
class VehicleSettings:
    """What the vehicle can do (the state bounds and the state-noise caps come from these) and its antennas.

    The estimate is the position of the reference point the CAN speed and yaw rate describe (on most cars the
    middle of the rear axle); the GNSS antenna sits ``antenna_forward_m`` ahead of it and ``antenna_left_m`` to its
    left (m, measured on the car). With ``estimator.antenna_offset`` the estimators refine the forward offset on
    line within ``antenna_forward_range_m`` of the value given (a roof antenna's position is rarely known to a
    decimetre). Two antennas (``su7``): distance ``antenna_distance_m`` and tolerance ``antenna_tolerance_m2`` of
    000 (23); ``antenna_lever``: antenna 2 swings about antenna 1 in turns.
    """

    max_speed_mps: float = 70.0
    max_reverse_speed_mps: float = 10.0
    max_accel_mps2: float = 10.0
    max_yaw_rate_rps: float = 1.5
    max_yaw_accel_rps2: float = 3.0
    antenna_forward_m: float = 0.0
    antenna_left_m: float = 0.0
    antenna_forward_range_m: float = 2.0
    antenna_distance_m: float = 1.0
    antenna_tolerance_m2: float = 0.05
    antenna_lever: bool = True

    def __post_init__(self) -> None:
        for name in ("antenna_forward_m", "antenna_left_m"):
            value = getattr(self, name)
            if not -10.0 <= value <= 10.0:
                raise ValueError(f"{name}: must be within [-10, 10] m, got {value!r}")
        positive(
            self,
            "antenna_forward_range_m",
            "max_speed_mps",
            "max_accel_mps2",
            "max_yaw_rate_rps",
            "max_yaw_accel_rps2",
            "antenna_distance_m",
            "antenna_tolerance_m2",
        )
        non_negative(self, "max_reverse_speed_mps")


@dataclass(frozen=True, slots=True)
class GnssModel:
    """The GNSS receiver's error model.

    A fix's 1-sigma position error per axis: the receiver's GST sigmas, else by GGA quality (``sigma_rtk_m`` for
    RTK fixed, ``sigma_float_m`` for float), else HDOP x ``uere_m``, else ``sigma_m``; at least ``resolution_m``
    (:func:`sumhe.frontend.measurements.fix_sigmas`). Course over ground (above ``course_min_speed_mps``):
    ``hypot(course_sigma_rad, speed_sigma_mps / speed)``; heading (HDT/THS, with ``use_heading``):
    ``heading_sigma_rad``. Speed over ground (Doppler, with ``use_speed``): ``speed_sigma_mps``. ``period_s``:
    the receiver's nominal period until the stream has shown its own. ``azimuth_offset_max_rad`` bounds the
    receiver's azimuth offset (sideslip, mounting) where the estimator has it as a state.

    Time: a fix's position is true ``time_offset_s`` after the time it was stamped with (``[gps] time``), on the
    CAN clock (a receiver's solution latency, a host clock off UTC, a logger stamping GNSS frames on arrival: -0.4
    to +0.2 s measured). With ``learn_time_offset`` the front-end learns it on line from the receiver's speed over
    ground against the CAN speed (:mod:`sumhe.frontend.alignment`), starting from ``time_offset_s``.
    """

    sigma_rtk_m: float = 0.02
    sigma_float_m: float = 0.3
    uere_m: float = 1.5
    sigma_m: float = 3.0
    resolution_m: float = 0.001
    speed_sigma_mps: float = 0.05
    course_sigma_rad: float = 0.0
    heading_sigma_rad: float = 0.005
    course_min_speed_mps: float = 2.0
    use_speed: bool = True
    use_heading: bool = True
    period_s: float = 0.1
    azimuth_offset_max_rad: float = 0.03
    time_offset_s: float = 0.0
    learn_time_offset: bool = True

    def __post_init__(self) -> None:
        if not -2.0 <= self.time_offset_s <= 2.0:
            raise ValueError(f"time_offset_s: must be within [-2, 2] s, got {self.time_offset_s!r}")
        positive(
            self,
            "sigma_rtk_m",
            "sigma_float_m",
            "uere_m",
            "sigma_m",
            "resolution_m",
            "speed_sigma_mps",
            "heading_sigma_rad",
            "period_s",
            "azimuth_offset_max_rad",
        )
        non_negative(self, "course_sigma_rad", "course_min_speed_mps")


@dataclass(frozen=True, slots=True)
class CanModel:
    """The CAN speed and yaw-rate sensors' error model.

    ``speed_resolution_mps`` / ``yaw_rate_resolution_rps``: the signals' quanta; unset, the DBC signal's scale (in
    SI, times the mapping's ``scale``) when the estimator is built from a config with a DBC mapping, else
    :data:`FALLBACK_SPEED_RESOLUTION_MPS` / :data:`FALLBACK_YAW_RATE_RESOLUTION_RPS`. ``*_sigma_*``: white noise per
    sample. ``max_gap_s``: a sample older than this is no longer used. ``delay_s``: a sample measures the vehicle
    this long before its timestamp (a calibration); ``speed_delay_s``: how much older than that the speed is (an
    OBD-II reply's speed, polled, beside a broadcast yaw rate; negative where it is the younger: what ``sumhe
    calibrate`` measures as ``can_delay_s``). GNSS and CAN observe only how the ages differ: the learned GNSS time
    offset is relative to the CAN speed, so a speed older than the yaw rate by ``d`` puts every fix ``d`` late
    against the yaw rate (``v d`` along the road) unless ``speed_delay_s`` says so. ``speed_scale_max``,
    ``yaw_rate_bias_max_rps`` and ``yaw_rate_gain_max`` bound the CAN speed's scale error and the yaw rate's bias
    and gain error (CAN speed = k v, CAN yaw rate = g omega + b). ``speed_rounding``: how the CAN speed is made
    whole quanta, ``"round"`` (to the nearest) or ``"truncate"`` (towards 0: an OBD-II speed in whole km/h on many
    cars, up to a quantum low, half a quantum on the mean; each such speed other than 0 is taken at the middle of
    its quantum, :func:`sumhe.frontend.can.centred_speed`). The on-line sensor check says when the speed reads the
    other way (:mod:`sumhe.frontend.sensor_check`); ``sumhe calibrate`` measures it.
    """

    speed_resolution_mps: float | None = None
    yaw_rate_resolution_rps: float | None = None
    speed_sigma_mps: float = 0.02
    yaw_rate_sigma_rps: float = 0.002
    max_gap_s: float = 0.5
    delay_s: float = 0.0
    speed_delay_s: float = 0.0
    speed_scale_max: float = 0.05
    yaw_rate_bias_max_rps: float = 0.02
    yaw_rate_gain_max: float = 0.15
    speed_rounding: str = "round"

    def __post_init__(self) -> None:
        one_of(self, "speed_rounding", SPEED_ROUNDINGS)
        for name in ("speed_resolution_mps", "yaw_rate_resolution_rps"):
            if getattr(self, name) is not None:
                positive(self, name)
        positive(
            self,
            "speed_sigma_mps",
            "yaw_rate_sigma_rps",
            "max_gap_s",
            "speed_scale_max",
            "yaw_rate_bias_max_rps",
            "yaw_rate_gain_max",
        )
        non_negative(self, "delay_s")
        if not -1.0 <= self.speed_delay_s <= 1.0:
            raise ValueError(f"speed_delay_s: must be within [-1, 1] s, got {self.speed_delay_s!r}")
        for name in ("speed_scale_max", "yaw_rate_gain_max"):
            if getattr(self, name) >= 1:
                raise ValueError(f"{name}: must be below 1 (a relative error)")

    def delay_of(self, quantity: str) -> float:
        """How long before its timestamp a sample of ``quantity`` measures the vehicle (s): ``delay_s``, plus
        ``speed_delay_s`` for the speed."""
        return self.delay_s + self.speed_delay_s if quantity == "speed" else self.delay_s

    @property
    def speed_quantum_mps(self) -> float:
        """The CAN speed's resolution (m/s): the setting, else the fallback."""
        return self.speed_resolution_mps or FALLBACK_SPEED_RESOLUTION_MPS

    @property
    def yaw_rate_quantum_rps(self) -> float:
        """The CAN yaw rate's resolution (rad/s): the setting, else the fallback."""
        return self.yaw_rate_resolution_rps or FALLBACK_YAW_RATE_RESOLUTION_RPS


@dataclass(frozen=True, slots=True)
class SensorSettings:
    """``[sensors]``: the GNSS receiver's and the CAN sensors' error models."""

    gnss: GnssModel = field(default_factory=GnssModel)
    can: CanModel = field(default_factory=CanModel)
