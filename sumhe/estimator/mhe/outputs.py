"""A window step's outputs, availability and error allowances, from the front-end's measurements.

As the batch grid (:mod:`sumhe.estimator.grid`) does for a whole window: the allowance of an output is
``estimator.r_cap_sigmas`` sigmas of its measurement (:mod:`sumhe.frontend.measurements`), the azimuth's plus half
a step of turning (the model's azimuth is the chord direction of the step), and the CAN speed and yaw rate are
their values at the step's time: the mean of the samples within ``CAN_HALF_S`` of it, else the two samples around
it interpolated, else the nearest (their allowance from the sigma of that mean). The motion between two steps is
the CAN data's own, integrated finely (:mod:`.preintegration`): a step's CAN outputs only say what the speed and
yaw rate were at its instant, as the fix says where the car was, so a longer average (over a step of 1 s at 1 Hz
GNSS) would measure the states of another time when the car accelerates or turns in.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from sumhe.frontend.can import CanBuffer
from sumhe.frontend.measurements import can_allowance, unmodelled_can_errors
from sumhe.frontend.stream import FixMeasurement
from sumhe.model.su import SuModel
from sumhe.settings import EstimationSettings

MIN_HALF_S = 0.005
"""A step's CAN outputs are the samples around it interpolated while the samples reach less than this past it (s)."""
CAN_HALF_S = 0.05
"""Half-width (s) of the interval a step's CAN value is averaged over: a few samples of a 100 Hz signal, short
enough that the speed and yaw rate change by less than their quanta within it."""

Outputs = tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]
"""A step's outputs (n), availability (n) and allowances (n)."""


def empty_outputs(model: SuModel) -> Outputs:
    return np.zeros(model.n_outputs), np.zeros(model.n_outputs, dtype=bool), np.ones(model.n_outputs)


def heading_as_course(model: SuModel, heading_rad: float, x: NDArray[np.float64]) -> float:
    """A heading (the car's azimuth, rad: two antennas, or a receiver's own GNSS + IMU solution) as the azimuth
    output of ``model``, which is the course of the antenna's motion (it differs from the heading by the lever arm
    in turns): the heading moved by the model's course-minus-heading at the state ``x``."""
    course = model.output(x)[model.j_azimuth]
    heading = x[model.i_phi] + (x[model.i_azimuth_offset] if model.i_azimuth_offset is not None else 0.0)
    return float(heading_rad + course - heading)


def fix_outputs(
    model: SuModel,
    fix: FixMeasurement,
    period_s: float,
    settings: EstimationSettings,
    out: Outputs,
    x: NDArray[np.float64],
) -> None:
    """Fill in place the GNSS outputs of a step from its fix: position, azimuth (with half a step of turning at
    the step's CAN yaw rate, already in ``out``; a heading as the course it implies at the step's state ``x``) and
    speed over ground, each allowed ``r_cap_sigmas`` of its sigma times :func:`correlation_factor` (a fix at a GNSS
    period shorter than ``estimator.mhe.fix_correlation_s`` weighs as its share of one independent fix)."""
    y, avail, allow = out
    k_sig = settings.estimator.r_cap_sigmas * correlation_factor(period_s, settings.estimator.mhe.fix_correlation_s)
    for j, value, sigma in zip(
        model.j_position, (fix.east_m, fix.north_m), (fix.sigma_east_m, fix.sigma_north_m), strict=True
    ):
        y[j], avail[j], allow[j] = value, True, k_sig * sigma
    if fix.azimuth_rad is not None:
        j = model.j_azimuth
        turn = 0.5 * period_s * abs(y[model.j_can_yaw_rate])
        azimuth = heading_as_course(model, fix.azimuth_rad, x) if fix.heading else fix.azimuth_rad
        y[j], avail[j], allow[j] = azimuth, True, k_sig * fix.azimuth_sigma_rad + turn
    j_speed = model.j_gps_speed
    if j_speed is not None and fix.speed_mps is not None:
        y[j_speed], avail[j_speed], allow[j_speed] = fix.speed_mps, True, k_sig * fix.speed_sigma_mps


def correlation_factor(period_s: float, correlation_s: float) -> float:
    """How much a fix's allowances grow at a GNSS period of ``period_s`` when fixes within ``correlation_s`` of each
    other are one measurement: the square root of how many fixes that is (``correlation_s / period_s`` to the
    nearest whole fix, at least one: a 1 Hz receiver's period measured as 0.9993 s is one fix a second).

    A receiver at 5 or 10 Hz does not measure anew each time: its solutions come out of its own filter, and its
    position errors wander over tens of seconds (multipath, atmosphere). Taken as independent, ten fixes a second
    taught the window's CAN and installation states from that wander: on a realistic simulated highway drive at
    10 Hz (seed 14) the positions' slow error curved their track in the seconds after driving off, and the window
    took the yaw-rate bias from the stop's 0.225 deg/s (true 0.226) to 0.03 deg/s; the 30 s outage 22 s in was
    34.8 m off on the mean (the EKF, whose bias kept the stop's, 2.6 m), 16.8 m with the fixes weighed so."""
    if period_s <= 0.0:
        return 1.0
    return math.sqrt(max(1, round(correlation_s / period_s)))


def can_outputs(
    model: SuModel, can: CanBuffer, t: float, t0: float, t1: float, settings: EstimationSettings, out: Outputs
) -> None:
    """Fill in place the CAN outputs of the step at ``t`` whose half-intervals span (t0, t1]: the mean of the
    samples within ``CAN_HALF_S`` (and the half-intervals) of ``t``, else the samples around it interpolated, else
    the nearest within ``sensors.can.max_gap_s``; and their allowances
    (:func:`~sumhe.frontend.measurements.can_allowance`), plus the unmodelled scale error or bias when the model
    lacks those states. While the samples reach only part of the interval after ``t``, the interval is shrunk
    symmetrically around it (a mean over the samples before alone would lag)."""
    y, avail, allow = out
    s, k_sig = settings.can, settings.estimator.r_cap_sigmas
    for quantity, j, res, sigma in (
        ("speed", model.j_can_speed, s.speed_quantum_mps, s.speed_sigma_mps),
        ("yaw_rate", model.j_can_yaw_rate, s.yaw_rate_quantum_rps, s.yaw_rate_sigma_rps),
    ):
        store = can[quantity]
        reach = min(t - t0, t1 - t, store.newest - t, CAN_HALF_S)
        mean = store.mean(t - reach, t + reach) if reach > MIN_HALF_S else None
        if mean is None:
            between = store.interpolate(t, s.max_gap_s)
            mean = (between, 1) if between is not None else None
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
    x: NDArray[np.float64],
) -> Outputs:
    """Outputs, availability and allowances of the step at ``t`` (the previous step ``h_prev`` s before) whose
    state is (predicted as) ``x``."""
    out = empty_outputs(model)
    can_outputs(model, can, t, t - 0.5 * h_prev, t + 0.5 * period_s, settings, out)
    if fix is not None:
        fix_outputs(model, fix, period_s, settings, out, x)
    return out
