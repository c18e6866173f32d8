"""Vehicle models of the state-uniform estimator: pure functions on numpy arrays and CasADi symbols."""

from sumhe.model.su import (
    SuModel,
    antenna_azimuth,
    antenna_distance_residual,
    integrate_odometry,
    output_noise,
    output_residuals,
    state_noise,
    state_residuals,
    su5_output,
    su5_step,
    su7_output,
    su7_step,
    su_model,
    wrap_angle,
)

__all__ = [
    "SuModel",
    "antenna_azimuth",
    "antenna_distance_residual",
    "integrate_odometry",
    "output_noise",
    "output_residuals",
    "state_noise",
    "state_residuals",
    "su5_output",
    "su5_step",
    "su7_output",
    "su7_step",
    "su_model",
    "wrap_angle",
]
