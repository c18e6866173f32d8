"""A window step's outputs, availability and error allowances, from the front-end's measurements.

As the batch grid (:mod:`sumhe.estimator.grid`) does for a whole window: the allowance of an output is
``estimator.r_cap_sigmas`` sigmas of its measurement (:mod:`sumhe.frontend.measurements`), the azimuth's plus half
a step of turning (the model's azimuth is the chord direction of the step), and the CAN speed and yaw rate are the
means of the samples of the step's half-intervals (their allowance from the sigma of that mean).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from sumhe.frontend.can import CanBuffer
from sumhe.frontend.measurements import can_allowance, unmodelled_can_errors
from sumhe.frontend.stream import FixMeasurement
from sumhe.model.su import SuModel
from sumhe.settings import EstimationSettings

MIN_HALF_S = 0.005
"""A step's CAN outputs are the sample nearest to it while the samples reach less than this past it (s)."""

Outputs = tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]
"""A step's outputs (n), availability (n) and allowances (n)."""


def empty_outputs(model: SuModel) -> Outputs:
    return np.zeros(model.n_outputs), np.zeros(model.n_outputs, dtype=bool), np.ones(model.n_outputs)


def fix_outputs(
    model: SuModel, fix: FixMeasurement, period_s: float, settings: EstimationSettings, out: Outputs
) -> None:
    """Fill in place the GNSS outputs of a step from its fix: position, azimuth (with half a step of turning at
    the step's CAN yaw rate, already in ``out``) and speed over ground."""
    y, avail, allow = out
    k_sig = settings.estimator.r_cap_sigmas
    for j, value, sigma in zip(
        model.j_position, (fix.east_m, fix.north_m), (fix.sigma_east_m, fix.sigma_north_m), strict=True
    ):
        y[j], avail[j], allow[j] = value, True, k_sig * sigma
    if fix.azimuth_rad is not None:
        j = model.j_azimuth
        turn = 0.5 * period_s * abs(y[model.j_can_yaw_rate])
        y[j], avail[j], allow[j] = fix.azimuth_rad, True, k_sig * fix.azimuth_sigma_rad + turn
    j_speed = model.j_gps_speed
    if j_speed is not None and fix.speed_mps is not None:
        y[j_speed], avail[j_speed], allow[j_speed] = fix.speed_mps, True, k_sig * fix.speed_sigma_mps


def can_outputs(
    model: SuModel, can: CanBuffer, t: float, t0: float, t1: float, settings: EstimationSettings, out: Outputs
) -> None:
    """Fill in place the CAN outputs of the step at ``t`` whose half-intervals span (t0, t1]: the mean of the
    samples there, else the nearest within ``sensors.can.max_gap_s``; and their allowances
    (:func:`~sumhe.frontend.measurements.can_allowance`), plus the unmodelled scale error or bias when the model
    lacks those states. While the samples reach only part of the second half-interval, the interval is shrunk
    symmetrically around ``t`` (a mean over the first half alone would lag by a quarter step)."""
    y, avail, allow = out
    s, k_sig = settings.can, settings.estimator.r_cap_sigmas
    for quantity, j, res, sigma in (
        ("speed", model.j_can_speed, s.speed_quantum_mps, s.speed_sigma_mps),
        ("yaw_rate", model.j_can_yaw_rate, s.yaw_rate_quantum_rps, s.yaw_rate_sigma_rps),
    ):
        store = can[quantity]
        reach = min(t - t0, t1 - t, store.newest - t)
        mean = store.mean(t - reach, t + reach) if reach > MIN_HALF_S else None
        value, count = mean if mean is not None else (store.at(t, s.max_gap_s), 1)
        y[j], avail[j] = (value, True) if value is not None else (0.0, False)
        allow[j] = can_allowance(res, sigma, k_sig, count)
    extra = unmodelled_can_errors(y[model.j_can_speed], s, model.i_scale is not None, model.i_bias is not None)
    allow[model.j_can_speed] += extra[0]
    allow[model.j_can_yaw_rate] += extra[1]


def step_outputs(
    model: SuModel,
    can: CanBuffer,
    t: float,
    h_prev: float,
    period_s: float,
    fix: FixMeasurement | None,
    settings: EstimationSettings,
) -> Outputs:
    """Outputs, availability and allowances of the step at ``t`` (the previous step ``h_prev`` s before)."""
    out = empty_outputs(model)
    can_outputs(model, can, t, t - 0.5 * h_prev, t + 0.5 * period_s, settings, out)
    if fix is not None:
        fix_outputs(model, fix, period_s, settings, out)
    return out
