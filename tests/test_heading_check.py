"""A receiver's headings checked against the CAN yaw rate's turn: headings that jump weigh as far as they are off,
settled ones as configured."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from sumhe.bench.mhe import drive_stream
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.heading_check import FORGET_S, NOISE_SIGMAS, TIME_ERROR_S, HeadingCheck, HeadingFix, turn_excess_rad
from sumhe.frontend.stream import Epoch, FrontEnd
from sumhe.frontend.tally import Tally
from sumhe.messages import CanSample
from sumhe.settings import CanModel, EstimationSettings, GnssModel
from sumhe.sim import SimSettings, simulate

GNSS = GnssModel()
CAN = CanModel()
NOISE = NOISE_SIGMAS * math.sqrt(2.0) * GNSS.heading_sigma_rad
"""What the two headings' configured noise adds to a turn's allowance (rad)."""


def test_a_headings_turn_counts_beyond_the_yaw_rates_errors_and_the_headings_noise() -> None:
    bias = CAN.yaw_rate_bias_max_rps
    assert turn_excess_rad(0.1, -0.1, 0.0, 1.0, GNSS, CAN) == 0.0  # clockwise as the yaw rate turns anticlockwise
    assert turn_excess_rad(0.5, -0.5 * (1 + 0.9 * CAN.yaw_rate_gain_max), 0.0, 1.0, GNSS, CAN) == 0.0  # gain error
    jump = math.radians(10.0)  # on a straight road, 1 s
    assert turn_excess_rad(jump, 0.0, 0.0, 1.0, GNSS, CAN) == pytest.approx(jump - bias - NOISE)
    assert turn_excess_rad(-jump, 0.0, 0.0, 0.1, GNSS, CAN) == pytest.approx(jump - 0.1 * bias - NOISE)
    # where the yaw rate changes between the fixes their time error turns the heading too
    assert turn_excess_rad(jump, 0.0, 0.2, 1.0, GNSS, CAN) == pytest.approx(jump - bias - NOISE - TIME_ERROR_S * 0.2)
    # across north: 359 -> 1 deg is 2 deg
    two = math.radians(2.0)
    assert turn_excess_rad(two - math.tau, 0.0, 0.0, 0.1, GNSS, CAN) == pytest.approx(two - 0.1 * bias - NOISE)


def _north(check: HeadingCheck, t: float, heading_deg: float) -> None:
    """A fix at ``t`` (s) on a straight road (no yaw) with ``heading_deg``."""
    check.add(HeadingFix(t, math.radians(heading_deg), 0.0), 0.0 if check.before is not None else None)


def test_headings_that_jump_on_a_straight_road_weigh_as_they_jump_until_they_have_settled() -> None:
    check = HeadingCheck(GNSS, CAN)
    for t in range(20):
        _north(check, float(t), 0.2 * (-1) ** t)  # settled: 0.4 deg from one to the next
    assert check.sigma_rad(19.0) == 0.0
    rng = np.random.default_rng(1)
    for t in range(20, 60):  # unsettled, as the shared drive's first minute: 5 deg from one second to the next
        _north(check, float(t), rng.normal(0.0, 5.0))
    unsettled = math.degrees(check.sigma_rad(59.5))
    assert 2.0 < unsettled < 6.0
    for t in range(60, 180):
        _north(check, float(t), 0.2 * (-1) ** t)
        if t == 60 + FORGET_S:
            assert math.degrees(check.sigma_rad(t)) < 0.7 * unsettled
    assert check.sigma_rad(179.0) < GNSS.heading_sigma_rad  # the configured sigma again


def test_a_jump_is_the_error_of_that_heading_and_weighs_on_those_after_it() -> None:
    check = HeadingCheck(GNSS, CAN)
    for t in range(10):
        _north(check, float(t), 0.0)
    _north(check, 10.0, 8.0)
    error = (math.radians(8.0) - CAN.yaw_rate_bias_max_rps - NOISE) / math.sqrt(2.0)
    assert check.sigma_rad(10.0) == pytest.approx(error)
    _north(check, 11.0, 8.0)  # no jump: the time-averaged square of the one, forgotten since
    assert check.sigma_rad(11.0) == pytest.approx(
        error * math.sqrt((1 - math.exp(-1 / FORGET_S)) * math.exp(-1 / FORGET_S))
    )
    assert check.sigma_rad(51.0) == pytest.approx(check.sigma_rad(11.0) * math.exp(-1.0))


def test_no_turn_to_compare_across_a_gap_or_without_the_can_yaw_rate() -> None:
    check = HeadingCheck(GNSS, CAN)
    _north(check, 0.0, 0.0)
    _north(check, 10.0, 20.0)  # 10 s later: not a pair
    check.add(HeadingFix(11.0, math.radians(40.0), None), 0.0)  # no yaw rate there
    check.add(HeadingFix(12.0, math.radians(60.0), 0.0), None)  # no yaw rate in between
    assert check.sigma_rad(12.0) == 0.0


def _frontend() -> FrontEnd:
    return FrontEnd(EstimationSettings(), Tally("test", logging.getLogger("test")))


def test_the_front_end_weighs_a_heading_at_what_the_check_finds_and_counts_it() -> None:
    fe = _frontend()
    sigmas = []
    for k in range(500):  # 10 m/s north, CAN at 50 Hz, fixes at 1 Hz from 0.5 s on
        t = 0.02 * k
        fe.push(CanSample(t, "speed", 10.0))
        fe.push(CanSample(t + 0.001, "yaw_rate", 0.0))
        if k % 50 == 25:
            heading = math.radians(8.0 if k // 50 >= 5 else 0.0)  # from the sixth fix on 8 deg to the right
            fix = LocalFix(t + 0.002, True, 0.0, 10.0 * t, hdop=1.0, speed_mps=10.0, heading_rad=heading)
            sigmas += [e.fix.azimuth_sigma_rad for e in fe.push(fix) if isinstance(e, Epoch) and e.fix is not None]
    configured = GNSS.heading_sigma_rad
    assert sigmas[:5] == [configured] * 5
    assert sigmas[5] == pytest.approx((math.radians(8.0) - CAN.yaw_rate_bias_max_rps - NOISE) / math.sqrt(2.0))
    assert configured < sigmas[6] < sigmas[5]
    assert fe.tally.counts["headings_off"] == len(sigmas) - 5


@pytest.mark.parametrize("scenario", ["urban", "highway"])
def test_a_settled_two_antenna_heading_is_never_weighed_down(scenario: str) -> None:
    """The simulator's two-antenna receiver (HDT, 0.2 deg of white noise, the body's heading with its sideslip; a
    CAN yaw rate with a bias and a gain error): every heading passes, through the drive's turns and stops."""
    drive = simulate(
        SimSettings(
            scenario=scenario,
            seed=3,
            duration_s=120.0,
            antennas=2,
            yaw_rate_bias_dps=0.5,
            yaw_rate_scale=1.05,
            gps_error="walk",
        )
    )
    fe = _frontend()
    headings = 0
    for sample in drive_stream(drive):
        for event in fe.push(sample):
            headings += isinstance(event, Epoch) and event.fix is not None and event.fix.heading
    assert headings > 1000 and "headings_off" not in fe.tally.counts
