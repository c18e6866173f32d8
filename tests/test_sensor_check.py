"""The on-line check of the CAN yaw rate's and speed's mapping against the receiver: a flipped sign, a yaw rate that
does not follow the azimuth, a yaw-rate gain or bias out of bounds, a speed in the wrong unit, each said once at
ERROR naming the key, and counted; nothing said of a correct mapping. A flipped sign is turned round and a gain, bias
or speed scale out of bounds undone from the verdict on, the estimator starting over afresh."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import numpy as np
import pytest

from sumhe.baseline.ekf import Ekf
from sumhe.bench.mhe import StreamItem, drive_stream
from sumhe.estimator.mhe import MovingHorizonEstimator
from sumhe.frontend.alignment import LagFit
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.sensor_check import CHECK_SIGMAS, speed_scale_outside, within, yaw_verdict
from sumhe.frontend.stream import CanTick, Epoch, FrontEnd
from sumhe.frontend.tally import Tally
from sumhe.messages import CanSample
from sumhe.settings import EstimationSettings
from sumhe.sim import SimSettings, simulate

CHECKS = (
    "yaw_rate_sign_flipped",
    "yaw_rate_not_following",
    "yaw_rate_gain_outside",
    "yaw_rate_bias_outside",
    "speed_scale_outside",
)


@pytest.fixture(scope="module")
def urban() -> list[StreamItem]:
    """A simulated town drive (10 Hz fixes with course and speed over ground), mapped correctly: it has turned
    about 200 deg by 60 s."""
    return drive_stream(simulate(SimSettings(scenario="urban", seed=3, duration_s=80.0)))


def _scaled(quantity: str, factor: float, shift: float = 0.0) -> Callable[[StreamItem], StreamItem]:
    """The quantity's samples read as ``factor`` times the drive's plus ``shift``."""

    def change(s: StreamItem) -> StreamItem:
        if isinstance(s, CanSample) and s.quantity == quantity:
            return dataclasses.replace(s, value=factor * s.value + shift)
        return s

    return change


def _without_azimuth(s: StreamItem) -> StreamItem:
    return dataclasses.replace(s, course_rad=None, heading_rad=None) if isinstance(s, LocalFix) else s


def _run(stream: list[StreamItem], change: Callable[[StreamItem], StreamItem], fe: FrontEnd | None = None) -> FrontEnd:
    fe = fe or FrontEnd(EstimationSettings(), Tally("test", logging.getLogger("test.sensor_check")))
    for s in stream:
        fe.push(change(s))
    return fe


def test_a_correct_mapping_is_confirmed_without_a_word(urban, caplog):
    with caplog.at_level(logging.INFO, logger="test.sensor_check"):
        fe = _run(urban, lambda s: s)
    assert not any(fe.tally.counts[k] for k in CHECKS)
    assert fe.check.yaw_done and fe.check.gain_ok and fe.check.bias_ok
    assert "follows the receiver's azimuth" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.parametrize(
    ("change", "key", "says"),
    [
        (_scaled("yaw_rate", -1.0), "yaw_rate_sign_flipped", "set scale = -1 (times the scale it has) in can.signals"),
        (lambda s: _without_azimuth(_scaled("yaw_rate", -1.0)(s)), "yaw_rate_sign_flipped", "can.signals.yaw_rate"),
        (_scaled("yaw_rate", math.pi / 180.0), "yaw_rate_not_following", "check can.signals.yaw_rate"),
        (_scaled("yaw_rate", 0.7), "yaw_rate_gain_outside", "sensors.can.yaw_rate_gain_max = 0.15"),
        (_scaled("yaw_rate", 1.35), "yaw_rate_gain_outside", "check can.signals.yaw_rate (its scale?"),
        (_scaled("yaw_rate", 1.0, 0.04), "yaw_rate_bias_outside", "set sensors.can.yaw_rate_bias_max_rps to cover"),
        (_scaled("speed", 1.609), "speed_scale_outside", "check can.signals.speed"),
        (_scaled("speed", 1.0 / 1.609), "speed_scale_outside", "sensors.can.speed_scale_max = 0.05"),
    ],
    ids=[
        "yaw-flipped",
        "yaw-flipped-no-course",
        "yaw-deg-as-rad",
        "yaw-gain-0.7",
        "yaw-gain-1.35",
        "yaw-bias-2.3-deg/s",
        "speed-km/h-as-mph",
        "speed-mph-as-km/h",
    ],
)
def test_a_wrong_mapping_is_said_once_at_error_naming_the_key(urban, caplog, change, key, says):
    """The fitted value and its standard error come with it; the same drive again (after a clock jump's reset)
    says nothing more: the verdict is the config's."""
    with caplog.at_level(logging.INFO, logger="test.sensor_check"):
        fe = _run(urban, change)
        fe.reset()
        _run(urban, change, fe)
    assert {k: fe.tally.counts[k] for k in CHECKS} == {k: int(k == key) for k in CHECKS}
    (error,) = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert error.levelno == logging.ERROR and says in error.getMessage() and " +- " in error.getMessage()


WRONG = [
    ("yaw_rate", -1.0, 0.0, "yaw_rate_sign_flipped"),
    ("yaw_rate", 0.7, 0.0, "yaw_rate_gain_outside"),
    ("yaw_rate", 1.0, 0.04, "yaw_rate_bias_outside"),
    ("speed", 1.609, 0.0, "speed_scale_outside"),
]
"""A CAN quantity read as the drive's times a factor plus a shift, and what the check finds."""


@pytest.mark.parametrize(("quantity", "factor", "shift", "key"), WRONG)
def test_a_wrong_mapping_is_undone_from_the_verdict_on_and_the_estimator_starts_afresh(
    urban, quantity, factor, shift, key
):
    """Until the verdict the quantity's ticks are as mapped; from it on less the check's offset, times its factor
    (the samples kept too, and the time-offset learner's CAN speeds): -1 for a flipped sign, the fitted scale for a
    yaw-rate gain or a speed scale out of bounds (within 5 % of the inverse of the drive's), the fitted bias for a
    yaw-rate bias out of bounds (within 0.005 rad/s of the shift); the fix of the verdict starts the estimator over
    with ``fresh`` (its CAN states learned from the wrong mapping dropped). The drive starts from 5 s at rest: the
    bias is told when it drives off, the speed's scale from 100 moving fixes on (20 s), the rest once the azimuth
    has turned 180 deg (59 s)."""
    fe = FrontEnd(EstimationSettings(), Tally("test", logging.getLogger("test.sensor_check")))
    raw, ticked, starts = [], [], []
    for s in map(_scaled(quantity, factor, shift), urban):
        for e in fe.push(s):
            if isinstance(e, CanTick) and e.quantity == quantity:
                raw.append(s.value)  # type: ignore[union-attr]
                ticked.append(e.value)
            elif isinstance(e, Epoch) and e.start:
                starts.append((e.t, e.fresh, len(ticked)))
    undo, less = fe.check.factor[quantity], fe.check.offset[quantity]
    assert fe.tally.counts["restarts"] == 1 and fe.tally.counts[key] == 1
    assert undo == -1.0 if factor < 0 else undo * factor == pytest.approx(1.0, abs=0.05)
    assert less == pytest.approx(shift, abs=0.005)
    assert fe.check.factor == {"speed": 1.0, "yaw_rate": 1.0} | {quantity: undo}
    assert fe.check.offset == {"speed": 0.0, "yaw_rate": 0.0} | {quantity: less}
    (_, first, _), (t, fresh, k) = starts
    when = {"yaw_rate_bias_outside": (4.0, 6.0), "speed_scale_outside": (15.0, 25.0)}.get(key, (40.0, 75.0))
    assert fresh and not first and when[0] < t - urban[0].t < when[1]
    assert ticked[:k] == raw[:k] and ticked[k:] == [undo * (v - less) for v in raw[k:]]
    kept = fe.can[quantity].v
    assert kept == pytest.approx([undo * (v - less) for v in raw[-len(kept) :]], rel=1e-12, abs=1e-15)
    if quantity == "speed":
        _, learned = fe.learner._can.columns()
        assert learned.tolist() == pytest.approx([undo * v for v in raw[-len(learned) :]], rel=1e-15)


def test_a_stop_whose_yaw_rates_wander_tells_no_bias(urban):
    """The drive's first 5 s at rest, its yaw rates 0.04 rad/s more and swinging by 0.05 (a car creeping through a
    turn below the speed's quantum, or a gyro shaken): no bias is told from that stop, nor later (the fits see the
    drive's own)."""
    t0 = urban[0].t

    def creeping(s: StreamItem) -> StreamItem:
        if isinstance(s, CanSample) and s.quantity == "yaw_rate" and s.t < t0 + 5.0:
            return dataclasses.replace(s, value=s.value + 0.04 + 0.05 * math.sin(2.0 * math.pi * (s.t - t0)))
        return s

    fe = _run(urban, creeping)
    assert fe.tally.counts["yaw_rate_bias_outside"] == 0 and fe.tally.counts["restarts"] == 0
    assert fe.check.bias_ok and fe.check.offset["yaw_rate"] == 0.0


@pytest.mark.slow
@pytest.mark.parametrize(("quantity", "factor", "shift", "key"), WRONG)
@pytest.mark.parametrize("estimator", [Ekf, MovingHorizonEstimator])
def test_through_an_outage_after_the_verdict_a_wrong_mapping_does_as_well_as_the_right_one(
    estimator, quantity, factor, shift, key
):
    """A town drive whose yaw rate reads clockwise-positive or 0.7 of the car's (the verdict at 59 s), 0.04 rad/s
    (2.3 deg/s) more (5 s: its first drive-off), or whose speed reads 1.609 of it (20 s), with a 20 s outage from 70
    s: the error through it is that of the drive mapped right (MHE 1.41, 1.41, 1.90 and 1.95 against 1.93 m, EKF
    1.63, 1.63, 1.47 and 1.48 against 1.41 m); the MHE's was 6.1 m when it kept the CAN states learned from the
    wrong sign over the restart, and 51, 14 and 68 m with the gain, the bias and the speed left as they read."""
    drive = simulate(SimSettings(scenario="urban", seed=3, duration_s=100.0))
    t0 = drive.settings.start_unix_s
    out = (t0 + 70.0, t0 + 90.0)
    right = [s for s in drive_stream(drive) if not (isinstance(s, LocalFix) and out[0] <= s.t < out[1])]
    errors = []
    for stream in (right, [_scaled(quantity, factor, shift)(s) for s in right]):
        est = estimator(EstimationSettings())
        estimates = [e for s in stream for e in est.push(s) if out[0] <= e.t < out[1]]
        truth = drive.truth.at(np.array([e.t for e in estimates]))
        east, north = np.array([[e.east_m, e.north_m] for e in estimates]).T
        errors.append(float(np.mean(np.hypot(east - truth.east, north - truth.north))))
    assert est.stats()[key] == 1
    assert errors[1] < 1.3 * errors[0] + 0.5, errors


@pytest.mark.parametrize(
    ("scale", "std", "verdict"),
    [
        (0.97, 0.05, "follows"),
        (1.0 / 0.7, 0.02, "follows"),  # its gain is judged apart (within)
        (-0.95, 0.055, "sign_flipped"),
        (0.02, 0.05, "not_following"),
        (57.0, 2.0, "not_following"),
        (-0.9, 0.2, None),  # 5 standard errors reach past 0.5: not yet told
        (0.6, 0.05, None),
        (math.nan, 0.1, None),
        (1.0, math.inf, None),
    ],
)
def test_a_yaw_rate_scale_is_judged_by_its_standard_error(scale, std, verdict):
    assert CHECK_SIGMAS == 5.0
    assert yaw_verdict(scale, std) == verdict


@pytest.mark.parametrize(
    ("off", "std", "bound", "inside"),
    [
        (1.0 / 0.97 - 1.0, 0.005, 0.15, True),  # a gain of 1.03
        (1.0 / 0.97 - 1.0, 0.05, 0.15, None),  # not yet told
        (0.7 - 1.0, 0.01, 0.15, False),
        (1.3 - 1.0, 0.005, 0.15, False),
        (1.2 - 1.0, 0.02, 0.15, None),  # 5 standard errors reach back inside
        (0.0066, 0.002, 0.02, True),  # the shared drive's bias, rad/s
        (-0.04, 0.002, 0.02, False),
        (math.nan, 0.1, 0.15, None),
        (0.0, math.inf, 0.15, None),
    ],
)
def test_a_gain_or_bias_is_judged_against_its_bounds_by_its_standard_error(off, std, bound, inside):
    assert within(off, std, bound) is inside


def test_a_speed_scale_is_judged_against_the_configs_bounds_less_a_truncated_quantum():
    """gnss = scale x CAN: the CAN speed's scale is its inverse. OBD-II's whole km/h truncated read up to half a
    step low, 2 % at 7 m/s: inside the bounds with it, outside without."""
    fit = LagFit(0.0, 0.01, 1.0 / 1.07, 0.0, 0.1, 300, scale_std=0.001, level=7.0)
    assert speed_scale_outside(fit, 0.05, 0.01) == pytest.approx(1.07)
    assert speed_scale_outside(fit, 0.05, 1.0 / 3.6) is None
    assert speed_scale_outside(dataclasses.replace(fit, scale_std=0.01), 0.05, 0.01) is None
    assert speed_scale_outside(dataclasses.replace(fit, scale=1.0), 0.05, 0.01) is None
