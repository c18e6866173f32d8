"""The MHE's parts of issue 12: each step's motion from the CAN data (preintegration), the CAN-rate estimate moved on
by the samples, and the output bounds learned from the residuals (the envelope)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sumhe.estimator.batch import model_for
from sumhe.estimator.mhe.envelope import BLOCK, OutputEnvelope
from sumhe.estimator.mhe.preintegration import step_motion
from sumhe.estimator.mhe.propagate import advance
from sumhe.estimator.mhe.window import Plan, Window
from sumhe.frontend.can import CanBuffer
from sumhe.settings import EstimationSettings, with_changes

SETTINGS = with_changes(EstimationSettings(), {"can.speed_resolution_mps": 0.01, "can.yaw_rate_resolution_rps": 0.0005})
MODEL = model_for(SETTINGS)


def _buffer(t0: float, t1: float, speed, yaw_rate, rate_hz: float = 100.0, speed_hz: float | None = None) -> CanBuffer:
    """Samples of ``speed`` (at ``speed_hz``, default ``rate_hz``) and ``yaw_rate`` (at ``rate_hz``) over [t0, t1]."""
    can = CanBuffer()
    for t in np.arange(t0, t1 + 1e-9, 1.0 / (speed_hz or rate_hz)):
        can["speed"].add(float(t), float(speed(t)))
    for t in np.arange(t0, t1 + 1e-9, 1.0 / rate_hz):
        can["yaw_rate"].add(float(t), float(yaw_rate(t)))
    return can


def _state(phi: float, v: float, w: float) -> np.ndarray:
    x = np.zeros(MODEL.n_states)
    x[MODEL.i_phi], x[MODEL.i_v], x[MODEL.i_omega] = phi, v, w
    x[MODEL.i_scale] = x[MODEL.i_gain] = 1.0
    return x


def test_a_turn_in_over_a_one_second_step_is_the_can_datas_own_motion() -> None:
    """Entering a bend (yaw rate 0 -> 0.4 rad/s within the step, 15 m/s): the trapezoid of the step's ends misses
    the azimuth by h^2/12 of the yaw acceleration's change (degrees at 1 Hz); the offset gives the motion of the
    samples themselves, to millimetres."""

    def yaw_rate(t):
        return 0.4 * np.clip(t - 10.0, 0.0, 1.0) ** 2

    can = _buffer(9.0, 12.0, lambda t: 15.0, yaw_rate)
    x0, x1 = _state(0.0, 15.0, 0.0), _state(0.0, 15.0, 0.4)
    offset, bound = step_motion(MODEL, can, 10.0, 11.0, x0, x1, SETTINGS)
    tf = np.linspace(10.0, 11.0, 20001)
    phi = -np.concatenate([[0.0], np.cumsum(0.5 * (yaw_rate(tf[1:]) + yaw_rate(tf[:-1])) * np.diff(tf))])
    east = np.sum(15.0 * np.sin(0.5 * (phi[1:] + phi[:-1])) * np.diff(tf))
    pred = MODEL.transition(x0, x1, 1.0)
    assert pred[MODEL.i_phi] + offset[MODEL.i_phi] == pytest.approx(phi[-1], abs=2e-4)
    assert pred[0] + offset[0] == pytest.approx(east, abs=0.003)
    assert abs(offset[MODEL.i_phi]) > math.radians(1.0)  # what one trapezoidal step would have missed
    assert offset[MODEL.i_v] == offset[MODEL.i_omega] == 0.0
    # the bound the samples' errors leave: a step's worth of half a quantum and 4 sigmas of 100 samples' mean
    assert bound[MODEL.i_phi] == pytest.approx(0.5 * 0.0005 + 4.0 * 0.002 / math.sqrt(100), rel=0.02)
    assert math.isnan(bound[MODEL.i_v])


def test_a_speed_polled_once_a_second_still_gives_the_step_the_yaw_rates_own_turn() -> None:
    """OBD-II speed polled at 0.98 Hz (gaps a little over a second, more than twice ``sensors.can.max_gap_s``)
    under a 100 Hz yaw rate: the step still turns by the samples' integral, the speed interpolated between its polls.
    Until 30 Nov 2026 such a step had no offset at all (its transition the trapezoid of its ends' yaw rates): on a
    realistic simulated offroad drive (seed 17) half the steps of a slalom of 45-58 deg/s turns, and the azimuth
    13 deg off 6 s into an outage (the CAN data integrated alone: 0.5 deg)."""

    def yaw_rate(t):
        return 0.4 * np.clip(t - 10.0, 0.0, 1.0) ** 2

    can = _buffer(8.0, 13.0, lambda t: 15.0, yaw_rate, speed_hz=0.98)
    assert max(np.diff(can["speed"].t)) > 2.0 * SETTINGS.can.max_gap_s
    x0, x1 = _state(0.0, 15.0, 0.0), _state(0.0, 15.0, 0.4)
    offset, _ = step_motion(MODEL, can, 10.0, 11.0, x0, x1, SETTINGS)
    tf = np.linspace(10.0, 11.0, 20001)
    phi = -np.sum(0.5 * (yaw_rate(tf[1:]) + yaw_rate(tf[:-1])) * np.diff(tf))
    assert MODEL.transition(x0, x1, 1.0)[MODEL.i_phi] + offset[MODEL.i_phi] == pytest.approx(phi, abs=2e-4)
    gap = CanBuffer()  # a gap of more than a second in the yaw rate itself still leaves the step to the model
    for t, v in zip(can["speed"].t, can["speed"].v, strict=True):
        gap["speed"].add(t, v)
    for t, v in zip(can["yaw_rate"].t, can["yaw_rate"].v, strict=True):
        if not 9.9 < t < 11.1:
            gap["yaw_rate"].add(t, v)
    assert step_motion(MODEL, gap, 10.0, 11.0, x0, x1, SETTINGS) is None


@pytest.mark.parametrize("speed_hz", [2.0, 50.0])
def test_the_can_rate_estimate_turns_with_the_yaw_rate_not_behind_it(speed_hz: float) -> None:
    """Turning in (the yaw rate 0 -> 0.4 rad/s over 2 s, 10 m/s) with the speed polled at 2 Hz (OBD-II) or sent at
    50 Hz and the yaw rate at 100 Hz: the estimate moved on by the samples turns by the yaw rate's integral within a
    few thousandths of a radian. The trapezoid of consecutive steps' means had turned it as the yaw rate was half a
    speed period before: 0.086 rad (4.9 deg) short at 2 Hz."""

    def yaw_rate(t):
        return 0.2 * np.clip(t - 10.0, 0.0, 2.0)

    can = _buffer(9.0, 13.0, lambda t: 10.0, yaw_rate, speed_hz=speed_hz)
    x = advance(MODEL, _state(0.0, 10.0, 0.0).tolist(), 10.0, 12.0, can, 0.6)
    assert x[MODEL.i_phi] == pytest.approx(-0.4, abs=0.004)
    assert x[MODEL.i_v] == 10.0


def test_the_can_states_correct_the_samples() -> None:
    """CAN reads 2 % fast and its yaw rate 5 % high plus a bias: the step is the corrected motion, a circle of 10 m/s
    at 0.1 rad/s (the offset also takes the trapezoid's own error on an arc, millimetres over a second)."""
    can = _buffer(0.0, 3.0, lambda t: 10.2, lambda t: 0.95 * 0.1 + 0.01)
    x0 = _state(0.0, 10.0, 0.1)
    x0[MODEL.i_scale], x0[MODEL.i_gain], x0[MODEL.i_bias] = 1.02, 0.95, 0.01
    offset, _ = step_motion(MODEL, can, 1.0, 2.0, x0, x0.copy(), SETTINGS)
    pred = np.array(MODEL.transition(x0, x0, 1.0)) + offset
    radius = 10.0 / 0.1  # a left turn from heading north: towards the west
    assert pred[MODEL.i_phi] == pytest.approx(-0.1, abs=1e-9)
    assert pred[0] == pytest.approx(-radius * (1 - math.cos(0.1)), abs=1e-4)
    assert pred[1] == pytest.approx(radius * math.sin(0.1), abs=1e-4)


def test_the_offset_is_taken_between_the_steps_own_can_outputs() -> None:
    """A yaw rate that is 0.01 rad/s at the steps' instants and 0 between them (a point interpolation reads the
    spikes): states fitted to the steps' CAN outputs (0, their means) plus the offset turn by what the samples
    turned, nothing; the offset between interpolated ends instead adds the spikes' trapezoid to every step."""

    def yaw_rate(t):
        return np.where(np.abs(t - np.round(t, 1)) < 1e-6, 0.01, 0.0)

    can = _buffer(0.0, 2.0, lambda t: 10.0, yaw_rate, rate_hz=200.0)
    x0, x1 = _state(0.0, 10.0, 0.0), _state(0.0, 10.0, 0.0)
    ends = np.array([[10.0, 0.0], [10.0, 0.0]])
    own, _ = step_motion(MODEL, can, 1.0, 1.1, x0, x1, SETTINGS, ends)
    fine = -np.trapezoid(yaw_rate(np.arange(1.0, 1.1 + 1e-9, 0.005))[1:-1], dx=0.005)  # the inner samples' turn
    assert MODEL.transition(x0, x1, 0.1)[MODEL.i_phi] + own[MODEL.i_phi] == pytest.approx(fine, abs=1e-9)
    pointwise, _ = step_motion(MODEL, can, 1.0, 1.1, x0, x1, SETTINGS)
    spike = 0.1 * 0.01 - 0.005 * 0.01  # the ends' trapezoid less the spikes' own half-samples in the fine integral
    assert pointwise[MODEL.i_phi] - own[MODEL.i_phi] == pytest.approx(spike, rel=1e-6)
    missing = np.array([[np.nan, np.nan], [10.0, 0.0]])  # a step without CAN outputs: its interpolated samples
    partial, _ = step_motion(MODEL, can, 1.0, 1.1, x0, x1, SETTINGS, missing)
    assert partial[MODEL.i_phi] - own[MODEL.i_phi] == pytest.approx(0.5 * spike, rel=1e-6)


def test_a_gap_in_the_can_data_leaves_the_model_step() -> None:
    can = _buffer(0.0, 1.0, lambda t: 10.0, lambda t: 0.0)
    assert step_motion(MODEL, can, 1.0, 3.0, _state(0.0, 10.0, 0.0), _state(0.0, 10.0, 0.0), SETTINGS) is None


def test_a_merged_step_sums_its_parts_bounds() -> None:
    win = Window(10, MODEL.n_states, MODEL.n_outputs)
    for k in range(4):
        win.append(
            float(k),
            np.zeros(MODEL.n_outputs),
            np.zeros(MODEL.n_outputs, bool),
            np.ones(MODEL.n_outputs),
            _state(0, 0, 0),
        )
        win.q_step[k] = 0.1 * (k + 1)
    win.apply(Plan(merge=(1,)))
    assert win.t.tolist() == [0.0, 2.0, 3.0]
    assert win.q_step[1, 0] == pytest.approx(0.2 + 0.3) and win.q_step[2, 0] == pytest.approx(0.4)


def test_the_envelope_learns_the_largest_ratio_with_a_margin() -> None:
    env = OutputEnvelope(3, history=4 * BLOCK, margin=1.1, max_factor=5.0)
    env.observe(np.array([[0.5, np.nan, 0.2]]))
    assert env.factor.tolist() == [1.0, 1.0, 1.0]  # within the sensors' claims: the claims stand
    env.observe(np.array([[2.0, np.nan, 10.0]]))
    assert env.factor == pytest.approx([2.2, 1.0, 5.0])  # the largest ratio x the margin, at most the cap
    for _ in range(5 * BLOCK):
        env.observe(np.array([[0.5, 0.5, 0.5]]))
    assert env.factor == pytest.approx([1.0, 1.0, 1.0])  # an excess older than the history is forgotten
