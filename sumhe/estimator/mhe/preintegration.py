"""The motion between two window steps by the CAN data itself, integrated finely: the transition's offset and its
CAN error bound (an IMU preintegration, for the planar SU model).

The SU model's transition (:func:`~sumhe.model.su.trapezoid`) moves a step with the speed and yaw rate of its two
ends only. At 10 Hz GNSS that is close to what the car did; at 1 Hz (a logger's receiver) a step spans a second of
turning in, braking or a lane change, and its azimuth and position are off by degrees and decimetres, which the
state-noise bounds of the vehicle's limits then have to cover (a loose bound is a small weight: the azimuth followed
every course measurement and the yaw-rate bias wandered, measured on a real drive). So each step's transition gets
an offset ``d``: where the CAN samples between the two steps, integrated sample by sample
(:func:`~sumhe.model.su.integrate_odometry`), take the car beyond one model step between the CAN values at its
ends, at the current CAN states (speed scale, yaw-rate bias and gain). The yaw rate's end values are the steps'
own CAN outputs, the values their states are fitted to: with a point interpolation there instead, the offsets and
the states disagreed by 0.001 rad/s on average over an outage of a realistic simulated highway drive (an azimuth
drift of 0.8 deg in 12 s). The speed's ends stay interpolated: with its outputs there too, a drive-off with a
multipath jump (``tests/test_mhe.py``) left the window infeasible and the vehicle lost. The model then only has to
explain the difference between the states and their CAN values at the ends, and the state noise of the positions
and the azimuth is what the CAN data's own errors leave over the step (:func:`can_step_bound`): half a quantum
and ``r_cap_sigmas`` sigmas of the samples' mean, integrated over the step.
"""

from __future__ import annotations

import bisect
import math
import operator
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from sumhe.floats import interp
from sumhe.frontend.can import CanBuffer
from sumhe.frontend.measurements import can_allowance
from sumhe.model.su import SuModel, can_motion, odometry_end
from sumhe.settings import EstimationSettings

FloatArray = NDArray[np.float64]
NUMPY_GRID = 8
"""A step's grid of at least this many times is interpolated by numpy at once, a shorter one point by point."""


def _samples(can: CanBuffer, quantity: str, t0: float, t1: float, max_gap: float) -> tuple[list[float], list[float]]:
    """The samples of ``quantity`` from the last one at or before ``t0`` to the first one at or after ``t1`` (within
    ``max_gap`` s of the interval)."""
    store = can[quantity]
    ts, vs = store.t, store.v
    i = max(bisect.bisect_right(ts, t0) - 1, 0)
    j = min(bisect.bisect_left(ts, t1) + 1, len(ts))
    # of those, the ones within max_gap: a slice, the times being ordered
    i = bisect.bisect_left(ts, t0 - max_gap, i, j)
    j = bisect.bisect_right(ts, t1 + max_gap, i, j)
    return ts[i:j], vs[i:j]


def _widest_gap(t0: float, times: list[float], t1: float) -> float:
    """The longest time (s) between consecutive ones of ``t0``, ``times``, ``t1``."""
    points = [t0, *times, t1]
    return max(map(operator.sub, points[1:], points))


def can_step_bound(
    model: SuModel, h: float, n_speed: int, n_yaw: int, speed_mps: float, settings: EstimationSettings
) -> FloatArray:
    """The bound on a step's state noise (dynamic states; NaN for those it does not bound) that the CAN data's
    errors leave when the step of ``h`` s is integrated from ``n_speed`` speed and ``n_yaw`` yaw-rate samples:
    for the azimuth, ``h`` times the yaw rate's allowance; for the positions, ``h`` times the speed's, plus the
    sideways drift of half that azimuth error at ``speed_mps``."""
    s, k_sig = settings.can, settings.estimator.r_cap_sigmas
    q_phi = h * can_allowance(s.yaw_rate_quantum_rps, s.yaw_rate_sigma_rps, k_sig, max(n_yaw, 1))
    q_pos = h * can_allowance(s.speed_quantum_mps, s.speed_sigma_mps, k_sig, max(n_speed, 1))
    q_pos += 0.5 * abs(speed_mps) * h * q_phi
    q = [math.nan] * model.n_dynamic  # filled as floats, one array at the end: np.full and three stores cost twice
    i_e, i_n = model.position
    q[i_e] = q[i_n] = q_pos
    q[model.i_phi] = q_phi
    return np.array(q)


def step_motion(
    model: SuModel,
    can: CanBuffer,
    t0: float,
    t1: float,
    x0: FloatArray,
    x1: FloatArray,
    settings: EstimationSettings,
    ends: FloatArray | Sequence[Sequence[float]] | None = None,
) -> tuple[FloatArray, FloatArray] | None:
    """The offset (m states) and the CAN noise bound (dynamic states) of the transition from the step at ``t0``
    (state ``x0``) to the step at ``t1`` (state ``x1``, s): module docstring. The ends' CAN speed and yaw rate are
    ``ends`` (rows: the two ends; columns: speed, yaw rate; NaN for one a step lacks), else the CAN samples
    interpolated there: pass the values the steps' states are fitted to (their CAN outputs), so that the offset
    adds to the states' own trapezoid exactly what the samples did beyond those values. None where the yaw rate has
    a gap longer than twice ``sensors.can.max_gap_s`` within the step, or no speed sample lies within
    ``max_gap_s`` of it (the step then keeps the model's transition and the vehicle's bounds). A speed polled more
    sparsely (OBD-II at 1 Hz: gaps a little over a second) is interpolated between its polls: before 30 Nov 2026
    its gaps, too, left such steps without the yaw rate's own turn, and a realistic simulated offroad drive (seed
    17) dead-reckoned a slalom of 45-58 deg/s turns 13 deg off in 6 s, where the CAN data integrated alone ends
    0.5 deg off."""
    gap = settings.can.max_gap_s
    tv, v = _samples(can, "speed", t0, t1, gap)
    tw, w = _samples(can, "yaw_rate", t0, t1, gap)
    if not tv or not tw or _widest_gap(t0, tw, t1) > 2.0 * gap:
        return None
    inner = tw[bisect.bisect_right(tw, t0) : bisect.bisect_left(tw, t1)]
    grid = [t0, *inner, t1]
    # the grid's CAN values: a long grid by numpy's interpolation, elementwise (the same bits as sumhe.floats.interp
    # point by point: 4x faster at the hundred points of a 1 Hz receiver's step), a short one point by point in plain
    # floats (numpy's set-up would cost more: a 10 Hz step often has no CAN sample within it)
    if len(grid) >= NUMPY_GRID:
        raw_speed, raw_yaw = np.interp(grid, tv, v), np.interp(grid, tw, w)
    else:
        raw_speed, raw_yaw = np.array([interp(g, tv, v) for g in grid]), np.array([interp(g, tw, w) for g in grid])
    if ends is not None:
        for k, end in ((0, ends[0]), (-1, ends[1])):
            raw_speed[k] = float(end[0]) if math.isfinite(end[0]) else raw_speed[k]
            raw_yaw[k] = float(end[1]) if math.isfinite(end[1]) else raw_yaw[k]
    x_start = x0.tolist()
    moving = can_motion(raw_speed, raw_yaw, x_start, model.i_bias, model.i_scale, model.i_gain)
    speed, yaw_rate = moving[0].tolist(), moving[1].tolist()
    i_e, i_n = model.position
    east, north, phi = odometry_end(grid, speed, yaw_rate, x_start[i_e], x_start[i_n], x_start[model.i_phi])
    start, end = list(x_start), x1.tolist()
    start[model.i_v], start[model.i_omega] = speed[0], yaw_rate[0]
    end[model.i_v], end[model.i_omega] = speed[-1], yaw_rate[-1]
    pred = model.transition(start, end, t1 - t0, math)
    offset = np.zeros(model.n_states)
    offset[i_e], offset[i_n] = east - pred[i_e], north - pred[i_n]
    offset[model.i_phi] = phi - pred[model.i_phi]
    n_speed = bisect.bisect_right(tv, t1) - bisect.bisect_right(tv, t0)
    mean_speed = float(np.abs(moving[0]).sum()) / len(speed)
    bound = can_step_bound(model, t1 - t0, n_speed, len(inner) + 1, mean_speed, settings)
    if not math.isfinite(float(offset[model.i_phi])):
        return None
    return offset, bound


def part_bound(
    model: SuModel, can: CanBuffer, t0: float, t1: float, speed_mps: float, settings: EstimationSettings
) -> FloatArray | None:
    """The CAN noise bound (dynamic states; NaN for those it does not bound) of the part of a step from the step at
    ``t0`` to ``t1`` (s) that a CAN-rate estimate is moved on by the CAN samples (:mod:`.propagate`), at
    ``speed_mps``: :func:`can_step_bound` of the samples in (``t0``, ``t1``]; None where the newest speed or
    yaw-rate sample at or before ``t1`` is more than ``sensors.can.max_gap_s`` old (the estimate then moves on
    without them)."""
    counts = []
    for quantity in ("speed", "yaw_rate"):
        ts = can[quantity].t
        k = bisect.bisect_right(ts, t1)
        if not k or t1 - ts[k - 1] > settings.can.max_gap_s:
            return None
        counts.append(k - bisect.bisect_right(ts, t0, 0, k))
    return can_step_bound(model, t1 - t0, counts[0], counts[1], speed_mps, settings)
