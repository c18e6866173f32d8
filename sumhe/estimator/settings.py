"""Settings of the estimators (the ``[estimator]`` table of the config).

Every field is a plain str/int/float/bool so that :func:`sumhe.config.build_section` can build it from TOML.
The formulation choices (``objective``, ``centre``, ``derived_floors``, ``r_cap_sigmas``) are explained in
``docs/formulation.md`` and in :mod:`sumhe.estimator.batch`.
"""

from __future__ import annotations

from dataclasses import dataclass

OBJECTIVES = ("linear", "log", "caps")
CENTRES = ("lsq", "none")
MODELS = ("su5", "su7")
GPS_TIMES = ("utc", "receive")
DISCRETISATIONS = ("trapezoid", "euler")


@dataclass(frozen=True, slots=True)
class EstimatorSettings:
    """Which estimator runs, with which vehicle model, and the physical limits its noise bounds come from.

    Units are in the names: ``_m``, ``_mps`` (m/s), ``_mps2``, ``_rad``, ``_rps`` (rad/s), ``_rps2``, ``_s``.
    """

    name: str = "mhe"
    model: str = "su5"
    # optional states beyond the paper: CAN yaw-rate bias and CAN speed scale factor
    yaw_rate_bias: bool = True
    speed_scale: bool = True
    discretisation: str = "trapezoid"
    # formulation: stage-1 objective over (q, r), which point of the feasible set is reported
    objective: str = "linear"
    centre: str = "lsq"
    centre_margin: float = 0.1
    derived_floors: bool = True
    r_cap_sigmas: float = 4.0
    # GNSS receiver
    gps_sigma_rtk_m: float = 0.02
    gps_sigma_float_m: float = 0.3
    gps_uere_m: float = 1.5
    gps_sigma_m: float = 3.0
    gps_resolution_m: float = 0.001
    gps_speed_sigma_mps: float = 0.05
    gps_heading_sigma_rad: float = 0.005
    course_min_speed_mps: float = 2.0
    use_heading: bool = True
    # CAN sensors
    can_speed_resolution_mps: float = 0.01
    can_yaw_rate_resolution_rps: float = 0.0005
    can_speed_sigma_mps: float = 0.02
    can_yaw_rate_sigma_rps: float = 0.002
    can_max_gap_s: float = 0.5
    speed_scale_max: float = 0.05
    yaw_rate_bias_max_rps: float = 0.02
    # vehicle limits
    max_speed_mps: float = 70.0
    max_reverse_speed_mps: float = 10.0
    max_accel_mps2: float = 10.0
    max_yaw_rate_rps: float = 1.5
    max_yaw_accel_rps2: float = 3.0
    # two antennas (su7): distance d and tolerance alpha of (23)
    antenna_distance_m: float = 1.0
    antenna_tolerance_m2: float = 0.05
    # time base: GNSS epochs at the fix's UTC time ("utc") or at receive time minus latency ("receive")
    gps_time: str = "utc"
    gps_latency_s: float = 0.0
    can_delay_s: float = 0.0
    # grid and solvers
    step_s: float = 0.1
    ipopt_max_iter: int = 300
    ipopt_tol: float = 1e-8
    lp_regularisation: float = 1e-3
    lp_widen_factor: float = 2.0
    lp_max_retries: int = 8

    def __post_init__(self) -> None:
        _one_of(self, "model", MODELS)
        _one_of(self, "objective", OBJECTIVES)
        _one_of(self, "centre", CENTRES)
        _one_of(self, "gps_time", GPS_TIMES)
        _one_of(self, "discretisation", DISCRETISATIONS)
        for name in (
            "r_cap_sigmas",
            "gps_sigma_rtk_m",
            "gps_sigma_float_m",
            "gps_uere_m",
            "gps_sigma_m",
            "gps_resolution_m",
            "gps_speed_sigma_mps",
            "gps_heading_sigma_rad",
            "can_speed_resolution_mps",
            "can_yaw_rate_resolution_rps",
            "can_speed_sigma_mps",
            "can_yaw_rate_sigma_rps",
            "can_max_gap_s",
            "speed_scale_max",
            "yaw_rate_bias_max_rps",
            "max_speed_mps",
            "max_accel_mps2",
            "max_yaw_rate_rps",
            "max_yaw_accel_rps2",
            "antenna_distance_m",
            "antenna_tolerance_m2",
            "step_s",
            "ipopt_max_iter",
            "ipopt_tol",
            "lp_regularisation",
        ):
            value = getattr(self, name)
            if not value > 0 or value == float("inf"):
                raise ValueError(f"{name}: must be a positive finite number, got {value!r}")
        for name in ("centre_margin", "course_min_speed_mps", "max_reverse_speed_mps", "gps_latency_s", "can_delay_s"):
            value = getattr(self, name)
            if not 0 <= value < float("inf"):
                raise ValueError(f"{name}: must be >= 0 and finite, got {value!r}")
        if self.speed_scale_max >= 1:
            raise ValueError("speed_scale_max: must be below 1 (a relative error)")
        if not self.lp_widen_factor > 1:
            raise ValueError(f"lp_widen_factor: must be > 1, got {self.lp_widen_factor!r}")
        if self.lp_max_retries < 0:
            raise ValueError(f"lp_max_retries: must be >= 0, got {self.lp_max_retries!r}")


def _one_of(obj: object, name: str, allowed: tuple[str, ...]) -> None:
    value = getattr(obj, name)
    if value not in allowed:
        raise ValueError(f"{name}: must be one of {', '.join(allowed)}, got {value!r}")
