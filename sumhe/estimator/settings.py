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
    # the receiver's speed over ground (Doppler; RMC/VTG) as a measurement of the speed, above course_min_speed_mps
    gps_speed: bool = True
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
    # two antennas (su7): distance d and tolerance alpha of (23); antenna_lever: antenna 2 swings in turns
    antenna_distance_m: float = 1.0
    antenna_tolerance_m2: float = 0.05
    antenna_lever: bool = True
    # CAN sensor delay (s): a CAN sample measures the vehicle this long before its timestamp. (GNSS fixes come
    # stamped with their measurement time: the [gps] table's time, latency_s, max_clock_offset_s)
    can_delay_s: float = 0.0
    # grid and solvers
    step_s: float = 0.1
    ipopt_max_iter: int = 300
    ipopt_tol: float = 1e-8
    lp_regularisation: float = 1e-2
    # algorithm 3.3 of 001: widen the caps of q and r by this factor while a problem is infeasible
    widen_factor: float = 2.0
    max_widenings: int = 8
    # moving-horizon estimator (docs/mhe.md): solver, window policy (steps), QP, CAN states' drift, gate
    mhe_solver: str = "sqp"
    mhe_steps: int = 50
    mhe_steps_before: int = 20
    mhe_steps_after: int = 10
    mhe_max_steps: int = 300
    mhe_shrink_steps: int = 2
    mhe_max_merge: int = 4
    mhe_bucket_steps: int = 25
    mhe_sqp_iterations: int = 3
    mhe_qp_max_iter: int = 200
    mhe_qp_tol: float = 1e-5
    mhe_trapezoid_q: float = 0.1
    mhe_theta_drift: float = 0.05
    mhe_gate_m: float = 2.0
    mhe_gate_drift: float = 0.05
    mhe_max_retries: int = 2
    # su-batch: the batch estimator over a whole recorded drive, in overlapping windows
    batch_window_s: float = 30.0
    batch_overlap_s: float = 6.0

    def __post_init__(self) -> None:
        if not 0.0 < self.batch_overlap_s < self.batch_window_s:
            raise ValueError(f"batch_overlap_s: must be within (0, batch_window_s), got {self.batch_overlap_s!r}")
        _one_of(self, "model", MODELS)
        _one_of(self, "objective", OBJECTIVES)
        _one_of(self, "centre", CENTRES)
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
        for name in ("centre_margin", "course_min_speed_mps", "max_reverse_speed_mps", "can_delay_s"):
            value = getattr(self, name)
            if not 0 <= value < float("inf"):
                raise ValueError(f"{name}: must be >= 0 and finite, got {value!r}")
        if self.speed_scale_max >= 1:
            raise ValueError("speed_scale_max: must be below 1 (a relative error)")
        if not self.widen_factor > 1:
            raise ValueError(f"widen_factor: must be > 1, got {self.widen_factor!r}")
        if self.max_widenings < 0:
            raise ValueError(f"max_widenings: must be >= 0, got {self.max_widenings!r}")
        _check_mhe(self)


def _one_of(obj: object, name: str, allowed: tuple[str, ...]) -> None:
    value = getattr(obj, name)
    if value not in allowed:
        raise ValueError(f"{name}: must be one of {', '.join(allowed)}, got {value!r}")


MHE_SOLVERS = ("sqp", "ipopt", "fatrop")


def _check_mhe(s: EstimatorSettings) -> None:
    """Validate the ``mhe_*`` fields (ValueError naming the field)."""
    _one_of(s, "mhe_solver", MHE_SOLVERS)
    for name in ("mhe_max_steps", "mhe_max_merge", "mhe_bucket_steps", "mhe_sqp_iterations", "mhe_qp_max_iter"):
        if getattr(s, name) < 1:
            raise ValueError(f"{name}: must be >= 1, got {getattr(s, name)!r}")
    if s.mhe_steps < 2:
        raise ValueError(f"mhe_steps: need at least 2 steps, got {s.mhe_steps!r}")
    if s.mhe_max_steps < s.mhe_steps:
        raise ValueError(f"mhe_max_steps: must be >= mhe_steps ({s.mhe_steps}), got {s.mhe_max_steps!r}")
    for name in ("mhe_steps_before", "mhe_steps_after", "mhe_shrink_steps", "mhe_max_retries"):
        if getattr(s, name) < 0:
            raise ValueError(f"{name}: must be >= 0, got {getattr(s, name)!r}")
    if s.mhe_steps_before >= s.mhe_steps:
        raise ValueError(f"mhe_steps_before: must be below mhe_steps ({s.mhe_steps}), got {s.mhe_steps_before!r}")
    for name in ("mhe_qp_tol", "mhe_trapezoid_q", "mhe_theta_drift", "mhe_gate_m", "mhe_gate_drift"):
        value = getattr(s, name)
        if not 0 < value < float("inf"):
            raise ValueError(f"{name}: must be a positive finite number, got {value!r}")
