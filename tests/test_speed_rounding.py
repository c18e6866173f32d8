"""A CAN speed in whole quanta, rounded or truncated (``sensors.can.speed_rounding``): a truncated one taken at the
middle of its quantum by the front-end, for every estimator; the on-line check saying, once and naming the key,
when the data read the other way than configured; the fit it judges by."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from sumhe.bench.mhe import StreamItem, drive_stream
from sumhe.estimator.su_batch import SuBatch
from sumhe.frontend.alignment import speed_lag
from sumhe.frontend.sensor_check import CHECK_SIGMAS, rounding_wrong
from sumhe.frontend.stream import FrontEnd
from sumhe.frontend.tally import Tally
from sumhe.messages import CanSample
from sumhe.settings import EstimationSettings
from sumhe.sim import SimSettings, simulate

KMH = 1.0 / 3.6
HALF = 0.5 * KMH
LOGGER = "test.speed_rounding"


def settings(rounding: str, quantum: float | None = KMH) -> EstimationSettings:
    s = EstimationSettings()
    return dataclasses.replace(s, can=dataclasses.replace(s.can, speed_resolution_mps=quantum, speed_rounding=rounding))


def front_end(rounding: str, quantum: float | None = KMH) -> FrontEnd:
    return FrontEnd(settings(rounding, quantum), Tally("test", logging.getLogger(LOGGER)))


@pytest.fixture(scope="module", params=["floor", "round"])
def obd_drive(request) -> tuple[str, list[StreamItem]]:
    """A 600 s town drive whose only speed is OBD-II's whole km/h (4 Hz), truncated or rounded."""
    sim = SimSettings(
        scenario="urban",
        seed=1,
        duration_s=600.0,
        can_layout="production",
        speed_source="obd",
        obd_rounding=request.param,
        obd_rate_hz=4.0,
    )
    return request.param, drive_stream(simulate(sim))


def run(stream: list[StreamItem], fe: FrontEnd) -> FrontEnd:
    for s in stream:
        fe.push(s)
    return fe


def test_a_truncated_speed_is_taken_at_the_middle_of_its_quantum_and_0_stays_0():
    fe = front_end("truncate")
    for t, v in ((1.0, 0.0), (2.0, 10 * KMH), (3.0, -3 * KMH)):
        fe.push(CanSample(t, "speed", v))
    speed = fe.can["speed"]
    assert speed.at(1.0, 0.1) == 0.0
    assert speed.at(2.0, 0.1) == pytest.approx(10.5 * KMH)
    assert speed.at(3.0, 0.1) == pytest.approx(-3.5 * KMH)
    rounded = front_end("round")
    rounded.push(CanSample(2.0, "speed", 10 * KMH))
    assert rounded.can["speed"].at(2.0, 0.1) == pytest.approx(10 * KMH)


def test_the_batch_su_estimator_takes_a_truncated_speed_at_the_middle_of_its_quantum_too():
    batch = SuBatch(settings("truncate"))
    for s in (CanSample(1.0, "speed", 10 * KMH), CanSample(1.0, "yaw_rate", 0.1), CanSample(2.0, "speed", 0.0)):
        batch.push(s)
    assert [(s.quantity, s.value) for s in batch._samples] == [
        ("speed", pytest.approx(10.5 * KMH)),
        ("yaw_rate", 0.1),
        ("speed", 0.0),
    ]


@pytest.mark.parametrize("rounding", ["floor", "round"])
def test_the_fit_says_how_much_a_speed_reads_low(rounding):
    rng = np.random.default_rng(4)
    t_fix = np.arange(0.0, 300.0, 1.0)
    t_can = np.arange(0.0, 300.0, 0.5)

    def truth(t):
        return 11.0 + 7.0 * np.sin(2 * np.pi * t / 97.0) + 2.0 * np.sin(2 * np.pi * t / 23.0)

    sog = truth(t_fix) + 0.05 * rng.standard_normal(len(t_fix))
    kmh = truth(t_can) / KMH
    can = (np.floor(kmh) if rounding == "floor" else np.round(kmh)) * KMH
    fit = speed_lag(t_fix, sog, t_can, can)
    assert fit is not None
    expected = HALF if rounding == "floor" else 0.0
    assert fit.reads_low == pytest.approx(expected, abs=max(3 * fit.reads_low_std, 0.02))
    assert 0.0 < fit.reads_low_std < HALF / CHECK_SIGMAS


@pytest.mark.parametrize(
    ("low", "std", "wrong", "verdict"),
    [
        (0.13, 0.01, HALF, True),  # taken as rounded, reads half a quantum low: truncated
        (0.01, 0.01, HALF, False),  # as configured
        (0.10, 0.05, HALF, None),  # not told apart yet
        (0.60, 0.01, HALF, None),  # neither: some other offset
        (-0.14, 0.01, -HALF, True),  # taken as truncated, reads half a quantum high: rounded
        (0.0, 0.0, HALF, None),  # no standard error: no fit
    ],
)
def test_the_rounding_is_judged_by_how_far_apart_the_fit_tells_the_two(low, std, wrong, verdict):
    assert rounding_wrong(low, std, wrong) is verdict


@pytest.mark.parametrize("configured", ["round", "truncate"])
def test_a_rounding_other_than_configured_is_said_once_naming_the_key(obd_drive, configured, caplog):
    rounding, stream = obd_drive
    with caplog.at_level(logging.INFO, logger=LOGGER):
        fe = run(stream, front_end(configured))
    wrong = (rounding == "floor") != (configured == "truncate")
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and "rounding" in r.getMessage()]
    assert fe.tally.counts["speed_rounding_wrong"] == int(wrong)
    assert fe.check.rounding_done
    if wrong:
        other = "round" if configured == "truncate" else "truncate"
        assert len(warnings) == 1 and f"sensors.can.speed_rounding = '{other}'" in warnings[0]
    else:
        assert not warnings
        assert any("as sensors.can.speed_rounding" in r.getMessage() for r in caplog.records)


def test_a_speed_scale_undone_on_line_leaves_the_rounding_judged_in_the_speeds_units(obd_drive, caplog):
    """The drive's speed read as 1.609 of it (km/h as mph), its quantum so too (the DBC's times the mapping's
    scale): the scale is undone on line at its verdict, and the rounding judged after it in the undone speed's
    quantum (in the config's, a truncated speed, half a quantum low, had read as rounded)."""
    rounding, stream = obd_drive
    factor = 1.609
    scaled = [
        dataclasses.replace(s, value=factor * s.value) if isinstance(s, CanSample) and s.quantity == "speed" else s
        for s in stream
    ]
    with caplog.at_level(logging.INFO, logger=LOGGER):
        fe = run(scaled, front_end("round", quantum=factor * KMH))
    assert fe.tally.counts["speed_scale_outside"] == 1
    assert fe.check.factor["speed"] * factor == pytest.approx(1.0, abs=0.02)
    assert fe.check.rounding_done and fe.tally.counts["speed_rounding_wrong"] == int(rounding == "floor")


def test_a_fine_quantum_is_not_judged(obd_drive):
    _, stream = obd_drive
    fe = front_end("round", quantum=None)  # the fallback quantum, 0.01 m/s
    assert fe.check.rounding_done
    run(stream[: len(stream) // 4], fe)
    assert fe.tally.counts["speed_rounding_wrong"] == 0
