"""Keys of the flat ``[estimator]`` table of sumhe <= 0.1 and where they live now: :func:`sumhe.config.load_config`
refuses an old key with a message naming the new one (a silently ignored key would be a wrong setting)."""

from __future__ import annotations

_MHE = (
    "solver",
    "steps",
    "steps_before",
    "steps_after",
    "max_steps",
    "shrink_steps",
    "max_merge",
    "bucket_steps",
    "sqp_iterations",
    "qp_max_iter",
    "qp_tol",
    "trapezoid_q",
    "theta_drift",
    "gate_m",
    "gate_drift",
    "max_retries",
)
_BATCH = (
    "objective",
    "centre",
    "centre_margin",
    "derived_floors",
    "ipopt_max_iter",
    "ipopt_tol",
    "lp_regularisation",
    "max_widenings",
)
_VEHICLE = (
    "max_speed_mps",
    "max_reverse_speed_mps",
    "max_accel_mps2",
    "max_yaw_rate_rps",
    "max_yaw_accel_rps2",
    "antenna_distance_m",
    "antenna_tolerance_m2",
    "antenna_lever",
)
_GNSS = {
    "gps_sigma_rtk_m": "sigma_rtk_m",
    "gps_sigma_float_m": "sigma_float_m",
    "gps_uere_m": "uere_m",
    "gps_sigma_m": "sigma_m",
    "gps_resolution_m": "resolution_m",
    "gps_speed_sigma_mps": "speed_sigma_mps",
    "gps_speed": "use_speed",
    "gps_heading_sigma_rad": "heading_sigma_rad",
    "course_min_speed_mps": "course_min_speed_mps",
    "use_heading": "use_heading",
    "step_s": "period_s",
}
_CAN = {
    "can_speed_resolution_mps": "speed_resolution_mps",
    "can_yaw_rate_resolution_rps": "yaw_rate_resolution_rps",
    "can_speed_sigma_mps": "speed_sigma_mps",
    "can_yaw_rate_sigma_rps": "yaw_rate_sigma_rps",
    "can_max_gap_s": "max_gap_s",
    "can_delay_s": "delay_s",
    "speed_scale_max": "speed_scale_max",
    "yaw_rate_bias_max_rps": "yaw_rate_bias_max_rps",
}

MOVED: dict[str, str] = {
    **{f"estimator.mhe_{k}": f"estimator.mhe.{k}" for k in _MHE},
    **{f"estimator.{k}": f"estimator.batch.{k}" for k in _BATCH},
    "estimator.ipopt_max_iter": "estimator.batch.ipopt_max_iter (estimator.mhe.nlp_max_iter for the MHE)",
    "estimator.batch_window_s": "estimator.batch.window_s",
    "estimator.batch_overlap_s": "estimator.batch.overlap_s",
    **{f"estimator.{k}": f"vehicle.{k}" for k in _VEHICLE},
    **{f"estimator.{old}": f"sensors.gnss.{new}" for old, new in _GNSS.items()},
    **{f"estimator.{old}": f"sensors.can.{new}" for old, new in _CAN.items()},
}
"""Old dotted key -> where it lives now."""
