"""Dead reckoning's error growth model (:mod:`sumhe.baseline.dead_reckoning`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sumhe.baseline import kinematics as kin
from sumhe.baseline.dead_reckoning import DeadReckoning, raw_input_errors
from sumhe.frontend.fixes import LocalFix
from sumhe.messages import CanSample
from sumhe.settings import EstimationSettings, NoiseSettings

SPEED_MPS = 10.0
OUTAGE_FROM_S = 20.0


def north_then_outage(seconds: float) -> list[LocalFix | CanSample]:
    """Straight north at 10 m/s: CAN speed at 50 Hz, yaw rate (0) at 100 Hz, fixes with a course at 10 Hz until
    ``OUTAGE_FROM_S``."""
    t0, h = 50.0, 0.01
    samples: list[LocalFix | CanSample] = []
    for k in range(int(seconds / h)):
        t = k * h
        if k % 2 == 0:
            samples.append(CanSample(t0 + t, "speed", SPEED_MPS))
        samples.append(CanSample(t0 + t + 0.001, "yaw_rate", 0.0))
        if k % 10 == 5 and t < OUTAGE_FROM_S:
            samples.append(
                LocalFix(
                    t=t0 + t + 0.002,
                    valid=True,
                    east_m=0.0,
                    north_m=SPEED_MPS * t,
                    gst_sigma_east_m=0.3,
                    gst_sigma_north_m=0.3,
                    speed_mps=SPEED_MPS,
                    course_rad=0.0,
                )
            )
    return samples


def test_the_uncorrected_bias_and_scale_grow_the_error_as_constants_do() -> None:
    """Dead reckoning corrects neither the CAN yaw-rate bias nor the speed scale, and they stay what they were all
    through an outage: with their priors (half the configured maxima, one sigma) the azimuth's variance grows by
    ``(sigma_b t)^2`` (rad^2) and the position's along the track by ``(sigma_k v t)^2`` (m^2), t s into the outage,
    and across it by ``(sigma_b v t^2 / 2)^2`` (within 5 %: the fix's azimuth error and the noise add a little).
    Drawn afresh at every CAN sample, they grew as t and t^3: at 50 Hz, after 10 s, a 500th of that."""
    settings = EstimationSettings()
    sigma_b = 0.5 * settings.can.yaw_rate_bias_max_rps
    sigma_k = 0.5 * settings.can.speed_scale_max
    dr = DeadReckoning(settings)
    at: dict[float, np.ndarray] = {}
    for sample in north_then_outage(OUTAGE_FROM_S + 31.0):
        dr.push(sample)
        if isinstance(sample, CanSample) and sample.quantity == "speed":
            at[round(sample.t - 50.0 - OUTAGE_FROM_S, 2)] = dr._covariance().copy()
    P0 = at[0.0]
    for t in (10.0, 30.0):
        grown = at[t] - P0
        assert grown[kin.PHI, kin.PHI] == pytest.approx((sigma_b * t) ** 2, rel=0.05)
        assert grown[kin.N, kin.N] == pytest.approx((sigma_k * SPEED_MPS * t) ** 2, rel=0.05)
        assert grown[kin.E, kin.E] == pytest.approx((sigma_b * SPEED_MPS * t * t / 2.0) ** 2, rel=0.05)


def test_the_fixes_white_error_is_read_from_its_predictions() -> None:
    """Dead reckoning takes each fix as it is, so its residual at every fix is nil and says nothing of the fixes'
    white error; its prediction of the next fix, 0.1 s on, is off by the difference of two fixes' errors, and the
    consistency scales read the white part (trace, m^2) from that: fixes jittered independently by 0.3 m per axis
    (a white trace of 0.18 m^2) read 0.18 within 20 %, not 0."""
    rng = np.random.default_rng(7)
    dr = DeadReckoning(EstimationSettings())
    for sample in north_then_outage(OUTAGE_FROM_S):
        if isinstance(sample, LocalFix):
            sample = dataclasses.replace(
                sample,
                east_m=sample.east_m + rng.normal(0.0, 0.3),
                north_m=sample.north_m + rng.normal(0.0, 0.3),
                gst_sigma_east_m=0.5,
                gst_sigma_north_m=0.5,
            )
        dr.push(sample)
    assert dr.consistency.white_m2(0.5) == pytest.approx(2.0 * 0.3**2, rel=0.2)


@pytest.mark.parametrize("turning", [True, False])
def test_the_raw_yaw_rate_is_off_by_the_bias_and_the_gain_times_itself(turning: bool) -> None:
    """At 0.5 rad/s the CAN yaw rate's error is the bias's plus 0.5 times the gain's (CAN yaw rate = g omega + b),
    plus the noise; at 12 m/s the speed's 12 times the scale's; both correlated with those rows, which they leave
    as they were. At standstill no turning is integrated: the bias's and the gain's parts are nil."""
    layout, noise = kin.Layout(), NoiseSettings()
    b, k, g = layout.b, layout.k, layout.g
    assert b is not None and k is not None and g is not None
    P = np.eye(layout.n)
    P[b, b], P[k, k], P[g, g] = 1e-4, 6.25e-4, 5.6e-3
    x = np.zeros(layout.n)
    x[kin.V], x[kin.OMEGA] = 12.0, 0.5 if turning else 0.0
    out = raw_input_errors(P, x, turning, layout, noise)
    expected = 1e-4 + 0.25 * 5.6e-3 if turning else 0.0
    assert out[kin.OMEGA, kin.OMEGA] == pytest.approx(expected + noise.can_yaw_rate_rps**2)
    assert out[kin.OMEGA, b] == pytest.approx(-1e-4 if turning else 0.0)
    assert out[kin.OMEGA, g] == pytest.approx(-0.5 * 5.6e-3 if turning else 0.0)
    assert out[kin.V, kin.V] == pytest.approx(144.0 * 6.25e-4 + noise.can_speed_mps**2)
    assert out[kin.V, k] == pytest.approx(-12.0 * 6.25e-4)
    assert out[kin.V, kin.OMEGA] == 0.0
    rows = [kin.E, kin.N, kin.PHI, b, k, g]
    np.testing.assert_array_equal(out[np.ix_(rows, rows)], P[np.ix_(rows, rows)])
