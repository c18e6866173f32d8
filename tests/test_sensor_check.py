"""The on-line check of the CAN yaw rate's and speed's mapping against the receiver: a flipped sign, a yaw rate that
does not follow the azimuth, a speed in the wrong unit, each said once at ERROR naming the key, and counted; nothing
said of a correct mapping."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable

import pytest

from sumhe.baseline.ekf import Ekf
from sumhe.bench.mhe import StreamItem, drive_stream
from sumhe.frontend.alignment import LagFit
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.sensor_check import CHECK_SIGMAS, speed_scale_outside, yaw_verdict
from sumhe.frontend.stream import FrontEnd, Tally
from sumhe.messages import CanSample
from sumhe.settings import EstimationSettings
from sumhe.sim import SimSettings, simulate

CHECKS = ("yaw_rate_sign_flipped", "yaw_rate_not_following", "speed_scale_outside")


@pytest.fixture(scope="module")
def urban() -> list[StreamItem]:
    """A simulated town drive (10 Hz fixes with course and speed over ground), mapped correctly: it has turned
    about 200 deg by 60 s."""
    return drive_stream(simulate(SimSettings(scenario="urban", seed=3, duration_s=80.0)))


def _scaled(quantity: str, factor: float) -> Callable[[StreamItem], StreamItem]:
    def change(s: StreamItem) -> StreamItem:
        if isinstance(s, CanSample) and s.quantity == quantity:
            return dataclasses.replace(s, value=factor * s.value)
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
    assert fe.check.yaw_done and "follows the receiver's azimuth" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.parametrize(
    ("change", "key", "says"),
    [
        (_scaled("yaw_rate", -1.0), "yaw_rate_sign_flipped", "set scale = -1 (times the scale it has) in can.signals"),
        (lambda s: _without_azimuth(_scaled("yaw_rate", -1.0)(s)), "yaw_rate_sign_flipped", "can.signals.yaw_rate"),
        (_scaled("yaw_rate", math.pi / 180.0), "yaw_rate_not_following", "check can.signals.yaw_rate"),
        (_scaled("speed", 1.609), "speed_scale_outside", "check can.signals.speed"),
        (_scaled("speed", 1.0 / 1.609), "speed_scale_outside", "sensors.can.speed_scale_max = 0.05"),
    ],
    ids=["yaw-flipped", "yaw-flipped-no-course", "yaw-deg-as-rad", "speed-km/h-as-mph", "speed-mph-as-km/h"],
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


def test_the_estimators_stats_carry_the_counter(urban):
    ekf = Ekf(EstimationSettings())
    for s in urban:
        ekf.push(_scaled("yaw_rate", -1.0)(s))
    assert ekf.stats()["yaw_rate_sign_flipped"] == 1


@pytest.mark.parametrize(
    ("scale", "std", "verdict"),
    [
        (0.97, 0.05, "ok"),
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


def test_a_speed_scale_is_judged_against_the_configs_bounds_less_a_truncated_quantum():
    """gnss = scale x CAN: the CAN speed's scale is its inverse. OBD-II's whole km/h truncated read up to half a
    step low, 2 % at 7 m/s: inside the bounds with it, outside without."""
    fit = LagFit(0.0, 0.01, 1.0 / 1.07, 0.0, 0.1, 300, scale_std=0.001, level=7.0)
    assert speed_scale_outside(fit, 0.05, 0.01) == pytest.approx(1.07)
    assert speed_scale_outside(fit, 0.05, 1.0 / 3.6) is None
    assert speed_scale_outside(dataclasses.replace(fit, scale_std=0.01), 0.05, 0.01) is None
    assert speed_scale_outside(dataclasses.replace(fit, scale=1.0), 0.05, 0.01) is None
