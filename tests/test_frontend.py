"""The measurement front-end: one fix-weighting policy, one course sigma, GNSS timing, the CAN buffer, the events
every streaming estimator reads."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator

import numpy as np
import pytest

from sumhe.baseline.ekf import Ekf
from sumhe.config import DatumSettings
from sumhe.estimator.grid import _fix_sigmas
from sumhe.estimator.mhe import MovingHorizonEstimator
from sumhe.estimator.mhe.outputs import correlation_factor
from sumhe.frontend.alignment import UNLEARNED_TIME_OFFSET_SD_S
from sumhe.frontend.can import CanBuffer
from sumhe.frontend.epochs import EpochClock, nominal_period
from sumhe.frontend.fixes import FixConverter, LocalFix
from sumhe.frontend.measurements import azimuth_measurement, chord_azimuth, course_sigma, fix_sigmas, gps_speed
from sumhe.frontend.stream import MAX_DATA_GAP_S, CanTick, Epoch, FrontEnd
from sumhe.frontend.tally import Tally
from sumhe.messages import CanSample, GnssFix
from sumhe.settings import EstimationSettings, GnssModel, with_changes

GNSS = GnssModel(uere_m=2.5)


# ---- one fix-weighting policy ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("quality", "hdop", "gst", "expected"),
    [
        (4, 0.8, (0.3, 0.5), (0.3, 0.5)),  # GST first, per axis
        (4, 0.8, None, (0.02, 0.02)),  # RTK fixed without GST: its sigma, not HDOP x UERE
        (5, 0.8, None, (0.3, 0.3)),  # RTK float
        (1, 0.8, None, (2.0, 2.0)),  # HDOP x the configured UERE (2.5 m)
        (1, None, None, (3.0, 3.0)),  # nothing said: the default
        (1, None, (0.0001, 0.0001), (0.001, 0.001)),  # at least the resolution
    ],
)
def test_one_fix_weighting_policy(quality: int, hdop: float | None, gst: tuple | None, expected: tuple) -> None:
    gst_e, gst_n = gst if gst is not None else (None, None)
    assert fix_sigmas(quality, hdop, gst_e, gst_n, GNSS) == pytest.approx(expected)
    fix = LocalFix(1.0, True, 0.0, 0.0, quality=quality, hdop=hdop, gst_sigma_east_m=gst_e, gst_sigma_north_m=gst_n)
    assert fix.sigmas(GNSS) == pytest.approx(expected)


def test_the_grid_and_the_stream_weigh_the_same_fix_alike() -> None:
    rng = np.random.default_rng(2)
    fixes = [
        GnssFix(
            t=float(k),
            time_utc=None,
            lat_deg=50.0 + 1e-5 * k,
            lon_deg=14.0,
            alt_m=None,
            quality=int(rng.choice([1, 2, 4, 5])),
            valid=True,
            hdop=float(rng.uniform(0.5, 3.0)) if k % 3 else None,
            sigma_lat_m=float(rng.uniform(0.1, 2.0)) if k % 4 == 0 else None,
            sigma_lon_m=float(rng.uniform(0.1, 2.0)) if k % 4 == 0 else None,
        )
        for k in range(40)
    ]
    settings = EstimationSettings(gnss=GNSS)
    grid_e, grid_n = _fix_sigmas(fixes, settings)
    converter = FixConverter(DatumSettings("fixed", 50.0, 14.0))
    stream = np.array([converter.convert(f).sigmas(GNSS) for f in fixes])
    assert np.allclose(stream[:, 0], grid_e) and np.allclose(stream[:, 1], grid_n)
    assert len(set(np.round(grid_e, 6))) > 10  # the cases above all occur


def test_unusable_sigmas_make_a_valid_fix_no_fix() -> None:
    for gst in (-1.0, 0.0, 2000.0):
        fix = LocalFix(t=1.0, valid=True, east_m=0.0, north_m=0.0, gst_sigma_east_m=gst, gst_sigma_north_m=gst)
        assert not fix.usable(fix.sigmas(GNSS))
    good = LocalFix(t=1.0, valid=True, east_m=0.0, north_m=0.0, hdop=1.0)
    assert good.usable(good.sigmas(GNSS))
    nowhere = LocalFix(t=1.0, valid=True, east_m=math.nan, north_m=0.0)
    assert not nowhere.usable(nowhere.sigmas(GNSS))


# ---- azimuth and speed over ground -------------------------------------------------------------------------------


def test_one_course_and_heading_sigma() -> None:
    gnss = GnssModel(speed_sigma_mps=0.05, course_sigma_rad=0.01, course_min_speed_mps=2.0)
    assert course_sigma(10.0, gnss) == pytest.approx(math.hypot(0.01, 0.005))
    assert azimuth_measurement(0.3, 1.2, 10.0, gnss) == (1.2, gnss.heading_sigma_rad, True)  # heading first
    angle, sigma, heading = azimuth_measurement(0.3, None, 10.0, gnss)  # type: ignore[misc]
    assert (angle, heading) == (0.3, False) and sigma == pytest.approx(course_sigma(10.0, gnss))
    assert azimuth_measurement(0.3, None, 1.0, gnss) is None  # below the minimum speed
    assert azimuth_measurement(0.3, None, None, gnss) is None
    configured = (1.2, gnss.heading_sigma_rad, True)  # a receiver's rating below the configured sigma: the configured
    assert azimuth_measurement(0.3, 1.2, 10.0, gnss, 0.5 * gnss.heading_sigma_rad) == configured
    assert azimuth_measurement(0.3, 1.2, 10.0, gnss, 0.1) == (1.2, 0.1, True)  # rated worse: its rating
    assert azimuth_measurement(0.3, None, 10.0, gnss, 0.1)[2] is False  # type: ignore[index]  # no heading: course
    no_heading = GnssModel(use_heading=False)
    assert azimuth_measurement(0.3, 1.2, 10.0, no_heading)[0] == 0.3  # type: ignore[index]
    speeds = np.array([10.0, 1.0, np.nan])
    assert np.allclose(gps_speed(speeds, np.array([-5.0, 5.0, 5.0]), gnss), [-10.0, np.nan, np.nan], equal_nan=True)


# ---- GNSS timing ----------------------------------------------------------------------------------------------


def test_the_period_is_the_mean_of_the_regular_intervals() -> None:
    assert nominal_period([0.1], 0.2) == 0.2  # one interval says nothing
    assert nominal_period([0.09, 0.11, 0.1, 3.0, 0.1], 0.2) == pytest.approx(0.1)  # the outage gap left out
    assert nominal_period([1.0, 1.0, 1.02, 0.98], 0.1) == pytest.approx(1.0)  # a 1 Hz receiver
    assert nominal_period([0.01, 0.09], 0.5) == pytest.approx(0.05)  # nothing regular: the median


def test_the_clock_counts_missed_epochs_on_the_fix_clock() -> None:
    clock = EpochClock(0.1)
    for k in range(5):
        clock.observe(10.0 + 0.1 * k, newest_can=10.05 + 0.1 * k)
    assert clock.period_s == pytest.approx(0.1) and clock.delay_s == pytest.approx(0.05)
    clock.last_epoch = 10.4
    assert clock.missed(10.54) == []
    assert clock.missed(10.8) == pytest.approx([10.5, 10.6, 10.7])
    assert clock.last_epoch == pytest.approx(10.7)


def test_the_can_buffer() -> None:
    buf = CanBuffer()
    for k in range(10):
        buf["speed"].add(float(k), 10.0 + k)
    assert buf["speed"].mean(2.0, 5.0) == (pytest.approx(14.0), 3)
    assert buf["speed"].at(4.5, 1.0) == 14.0 and buf["speed"].at(20.0, 1.0) is None
    assert buf.newest == 9.0
    buf.trim(100.0)
    assert buf["speed"].newest == -math.inf


# ---- the streaming front-end's events ---------------------------------------------------------------------------


def _frontend(**changes: object) -> FrontEnd:
    settings = with_changes(EstimationSettings(), {"can.delay_s": 0.02, **changes})
    return FrontEnd(settings, Tally("test", __import__("logging").getLogger("test")))


def _fix(t: float, **kw: object) -> LocalFix:
    return LocalFix(t=t, valid=True, east_m=1.0, north_m=2.0, hdop=1.0, speed_mps=10.0, course_rad=0.5, **kw)  # type: ignore[arg-type]


def test_events_start_at_the_first_usable_fix_and_missed_epochs_come_first() -> None:
    fe = _frontend()
    assert fe.push(CanSample(10.0, "speed", 10.0)) == []  # nothing before the first fix
    assert fe.push(LocalFix(t=10.01, valid=False)) == []
    (start,) = fe.push(_fix(10.05))
    assert isinstance(start, Epoch) and start.start and start.fix is not None
    assert start.fix.speed_mps == 10.0 and start.fix.azimuth_rad == 0.5
    assert start.fix.sigma_east_m == pytest.approx(1.5)  # HDOP x UERE
    (tick,) = fe.push(CanSample(10.10, "speed", 10.0))
    assert tick == CanTick(pytest.approx(10.08), 10.10, "speed", 10.0, output=True)  # measured delay_s before its stamp
    fe.push(_fix(10.15))
    fe.push(_fix(10.25))
    # GNSS falls silent: each CAN sample reveals the epochs missed before it
    events = fe.push(CanSample(10.52, "yaw_rate", 0.1))
    assert [type(e) for e in events] == [Epoch, Epoch, CanTick] and not events[2].output  # type: ignore[union-attr]
    assert [e.t for e in events[:2]] == pytest.approx([10.35, 10.45]) and all(e.missed for e in events[:2])  # type: ignore[union-attr]
    assert fe.tally.counts["missed_epochs"] == 2


def test_bad_input_is_counted_not_raised() -> None:
    fe = _frontend()
    fe.push(CanSample(10.0, "speed", 10.0))
    fe.push(_fix(10.05))
    for bad in (
        CanSample(math.nan, "speed", 1.0),
        CanSample(10.1, "yaw_rate", 1e9),
        CanSample(9.0, "speed", 1.0),
        LocalFix(t=10.0, valid=True, east_m=0.0, north_m=0.0),
        _fix(10.2, gst_sigma_east_m=-1.0, gst_sigma_north_m=-1.0),
        "not a sample",
    ):
        assert not [e for e in fe.push(bad) if isinstance(e, Epoch) and e.fix is not None]  # type: ignore[arg-type]
    counts = fe.tally.counts
    assert counts["bad_samples"] == 3 and counts["dropped_backwards"] == 2 and counts["bad_fixes"] == 1
    # fixes more than a second behind the CAN data are dropped
    late = _frontend()
    for k in range(5):
        late.push(CanSample(20.0 + 0.1 * k, "speed", 10.0))
        events = late.push(_fix(18.5 + 0.1 * k))
        assert len(events) == (k == 0)
    assert late.tally.counts["late_fixes"] == 4


def test_a_long_gap_restarts_at_the_next_usable_fix() -> None:
    fe = _frontend()
    fe.push(_fix(10.0))
    t = 10.0 + MAX_DATA_GAP_S + 5.0
    assert fe.push(CanSample(t, "speed", 3.0)) == []
    (epoch,) = fe.push(_fix(t + 0.1))
    assert epoch.start and fe.tally.counts["restarts"] == 1  # type: ignore[union-attr]


def test_every_family_reads_the_same_fix_sigma() -> None:
    """An RTK fix without GST: 2 cm for the MHE and for the Kalman filters (the EKF took 1.5 x HDOP before)."""
    settings = EstimationSettings()
    rtk = LocalFix(t=10.0, valid=True, east_m=0.0, north_m=0.0, quality=4, hdop=0.9, speed_mps=0.0)
    mhe, ekf = MovingHorizonEstimator(settings), Ekf(settings)
    for est in (mhe, ekf):
        est.push(CanSample(9.99, "speed", 0.0))
        est.push(rtk)
    # the MHE's allowance: r_cap_sigmas of it, grown as a fix at the configured GNSS period (0.1 s until the stream
    # shows its own) weighs as its share of one a second (estimator.mhe.fix_correlation_s)
    k = settings.estimator.r_cap_sigmas * correlation_factor(mhe.period_s, settings.estimator.mhe.fix_correlation_s)
    assert mhe.window.allow[0, mhe.model.j_position[0]] == pytest.approx(k * 0.02)
    assert ekf.P[0, 0] == pytest.approx((ekf.noise.gps_scale * 0.02) ** 2)


# ---- the GNSS time offset -----------------------------------------------------------------------------------------


def test_a_configured_time_offset_moves_every_fix_onto_the_can_clock() -> None:
    fe = _frontend(**{"gnss.time_offset_s": -0.3, "gnss.learn_time_offset": False})
    fe.push(CanSample(10.0, "speed", 10.0))
    (start,) = fe.push(_fix(10.5))
    assert start.t == pytest.approx(10.2) and start.fix.t == pytest.approx(10.2)  # type: ignore[union-attr]
    assert fe.time_offset_s == -0.3


def _lagging_receiver(fe: FrontEnd, speed_age_s: float = 0.0) -> Iterator[list[Epoch | CanTick]]:
    """Feed ``fe`` 300 s of a 1 Hz receiver whose fixes are true 0.3 s before their stamp (speed over ground behind
    the CAN speed, 5 Hz, ``speed_age_s`` old at its stamp) and yield the events of each fix."""

    def speed(t: float) -> float:
        return 12.0 + 5.0 * math.sin(t / 6.0)

    for k in range(1, 3000):
        t = 0.1 * k
        if k % 2 == 0:
            fe.push(CanSample(t, "speed", speed(t - speed_age_s)))
        if k % 10 == 0:
            yield fe.push(LocalFix(t=t, valid=True, east_m=1.0, north_m=2.0, hdop=1.0, speed_mps=speed(t - 0.3)))


def test_the_learned_time_offset_is_applied_gradually_and_keeps_epochs_in_order() -> None:
    """A receiver whose fixes are true 0.3 s before their stamp (speed over ground behind the CAN speed): the
    front-end learns it from the speeds and moves the fixes, by at most a fifth of a period per fix."""
    fe = _frontend(**{"can.delay_s": 0.0})
    times = [e.t for events in _lagging_receiver(fe) for e in events if isinstance(e, Epoch)]
    assert fe.time_offset_s == pytest.approx(-0.3, abs=0.02)
    assert all(np.diff(times) > 0.5)  # 1 Hz epochs, each moved by at most 0.2 s more than the one before
    assert times[-1] == pytest.approx(299.0 + fe.time_offset_s)


def test_an_older_speed_is_kept_at_its_own_time_and_the_fixes_line_up_with_the_yaw_rate() -> None:
    """An OBD-II speed 0.2 s older than the yaw rate: told so (``speed_delay_s``), the front-end keeps each speed
    sample at its own measurement time and answers it at the common one (the ticks stay in order), and the time
    offset learned from it is the fixes' own (-0.3 s); untold, the fixes come out 0.2 s late."""
    told = _frontend(**{"can.delay_s": 0.02, "can.speed_delay_s": 0.2})
    told.push(CanSample(10.0, "yaw_rate", 0.1))
    assert told.push(_fix(10.05))  # the start
    (tick,) = told.push(CanSample(10.10, "speed", 10.0))
    assert tick.t == pytest.approx(10.08) and told.can["speed"].newest == pytest.approx(9.88)
    (tick,) = told.push(CanSample(10.12, "yaw_rate", 0.1))
    assert tick.t == pytest.approx(10.10) and told.can["yaw_rate"].newest == pytest.approx(10.10)
    for speed_delay, offset in ((0.2, -0.3), (0.0, -0.1)):
        fe = _frontend(**{"can.delay_s": 0.0, "can.speed_delay_s": speed_delay})
        for _ in _lagging_receiver(fe, speed_age_s=0.2):
            pass
        assert fe.time_offset_s == pytest.approx(offset, abs=0.02)


@pytest.mark.parametrize("learn", [True, False])
def test_fixes_without_a_speed_over_ground_are_counted_where_the_time_offset_is_learned(
    learn: bool, caplog: pytest.LogCaptureFixture
) -> None:
    """A receiver that sends no speed over ground gives the learner nothing: each valid fix is counted and the
    first logged (the offset stays at the config's); with the offset configured (not learned) nothing is said."""
    fe = _frontend(**{"can.delay_s": 0.0, "gnss.learn_time_offset": learn})
    with caplog.at_level(logging.WARNING, logger="test"):
        for k in range(1, 120):
            fe.push(CanSample(0.5 * k, "speed", 12.0 + math.sin(k / 6.0)))
            if k % 2 == 0:
                fe.push(LocalFix(t=0.5 * k, valid=True, east_m=1.0, north_m=2.0, hdop=1.0))
    assert fe.tally.counts["fixes_without_speed"] == (59 if learn else 0)
    assert fe.time_offset_s == 0.0 and fe.time_offset_sigma_s == (UNLEARNED_TIME_OFFSET_SD_S if learn else 0.0)
    assert ("not learned" in caplog.text) == learn


def test_the_applied_time_offsets_error_is_the_prior_then_the_fit_and_what_the_slew_has_not_applied() -> None:
    """The same receiver (fixes true 0.3 s before their stamp): until the learner's first fit the applied offset's
    error is the prior it starts from; then the fit's standard error and the part the slew has not applied yet
    (root sum of squares); once applied, the fit's alone. A configured offset is a calibration: none."""
    fe = _frontend(**{"can.delay_s": 0.0})
    assert fe.time_offset_sigma_s == UNLEARNED_TIME_OFFSET_SD_S and fe.aligner is not None
    learner = fe.aligner
    seen = [
        (fe.time_offset_sigma_s, learner.sigma_s, learner.offset_s - fe.time_offset_s) for _ in _lagging_receiver(fe)
    ]
    first = next(i for i, (_, fit, _) in enumerate(seen) if fit < UNLEARNED_TIME_OFFSET_SD_S)
    assert first > 0 and all(sigma == UNLEARNED_TIME_OFFSET_SD_S for sigma, _, _ in seen[:first])
    sigma, fit, unapplied = seen[first]
    assert abs(unapplied) > 0.05 and sigma == pytest.approx(math.hypot(fit, unapplied))
    sigma, fit, unapplied = seen[-1]
    assert abs(unapplied) < 1e-9 and sigma == pytest.approx(fit) and fit < 0.03
    configured = _frontend(**{"gnss.time_offset_s": -0.3, "gnss.learn_time_offset": False})
    assert configured.time_offset_sigma_s == 0.0


def test_missed_epochs_wait_for_the_period() -> None:
    """A 1 Hz receiver whose fixes come 0.4 s behind the CAN data: before two intervals have shown the period, the
    default 0.1 s must not turn the silence between its first fixes into missed epochs (its second fix would be
    dropped as back in time, and the period never measured)."""
    fe = _frontend(**{"gnss.time_offset_s": -0.4, "gnss.learn_time_offset": False})
    epochs = []
    for k in range(1, 60):
        t = 0.1 * k
        fe.push(CanSample(t, "speed", 10.0))
        if k % 10 == 5:
            epochs += [e for e in fe.push(_fix(t)) if isinstance(e, Epoch)]
    assert [e.missed for e in epochs] == [False] * 6
    assert fe.period_s == pytest.approx(1.0) and fe.tally.counts["dropped_backwards"] == 0


def test_the_can_buffer_interpolates_between_samples() -> None:
    buf = CanBuffer()
    buf["speed"].add(1.0, 10.0)
    buf["speed"].add(1.5, 11.0)
    assert buf["speed"].interpolate(1.2, 0.5) == pytest.approx(10.4)
    assert buf["speed"].interpolate(1.6, 0.5) is None  # nothing after
    assert buf["speed"].interpolate(1.2, 0.1) is None  # the samples too far


@pytest.mark.parametrize("fills", [True, False])
@pytest.mark.parametrize("learn_offset", [False, True])
def test_fixes_that_start_coming_later_are_taken_again_after_at_most_a_few(learn_offset: bool, fills: bool) -> None:
    """A 10 Hz receiver whose fixes come 0.05 s behind the CAN data, then 0.35 s behind (a stalled reader, a busier
    receiver): the first late fixes find their epochs already declared missed; each fills its missed epoch
    (``Epoch(fills=True)``, once), or, for an estimator that cannot put a fix in the past (``fills_missed`` False),
    is dropped and counted. Either way what they show of the new delay is learned, so the fixes after them are
    taken as they come (they were all dropped: GNSS lost for good)."""
    fe = _frontend(**{"gnss.learn_time_offset": learn_offset})
    fe.fills_missed = fills
    lag, taken, filled, pending = 0.05, [], [], []
    for k in range(1, 1000):
        t = 0.02 * k
        if k == 250:
            lag = 0.35
        for fix_t in [f for f in pending if f + lag <= t]:
            pending.remove(fix_t)
            for e in fe.push(_fix(fix_t)):
                if isinstance(e, Epoch) and e.fix is not None:
                    (filled if e.fills else taken).append(fix_t)
        fe.push(CanSample(t, "speed", 10.0))
        if k % 5 == 0:
            pending.append(t)
    after = [x for x in taken if x > 5.0]
    assert fe.tally.counts["dropped_backwards"] == 0
    assert 1 <= len(filled) + fe.tally.counts["fixes_after_missed"] <= 5
    assert fe.tally.counts["fixes_after_missed"] == 0 if fills else not filled
    assert all(5.0 <= x < 5.6 for x in filled) and not set(filled) & set(taken)
    assert len(after) >= 140 and max(taken) > 19.0
    if filled:  # the same fix again: its epoch is filled once
        assert fe.push(_fix(filled[-1])) == [] and fe.tally.counts["dropped_backwards"] == 1


@pytest.mark.parametrize("yaw_rate", [0.0, 0.3, -0.2])
def test_the_chord_between_fixes_gives_the_azimuth_at_the_later_one_on_a_circle(yaw_rate: float) -> None:
    """On a circle at a constant yaw rate (anticlockwise; the azimuth turns clockwise from north) the chord points
    half the turn behind the later fix's azimuth; its sigma is the error across it over its length."""
    phi0, speed, dt, h = 2.0, 10.0, 1.0, 1e-4
    e = n = 0.0
    for k in range(round(dt / h)):
        phi = phi0 - yaw_rate * (k + 0.5) * h
        e, n = e + speed * h * math.sin(phi), n + speed * h * math.cos(phi)
    got = chord_azimuth(e, n, 1.5, dt, yaw_rate)
    assert got is not None
    assert got[0] == pytest.approx((phi0 - yaw_rate * dt) % (2 * math.pi), abs=1e-6)
    assert got[1] == pytest.approx(1.5 / math.hypot(e, n))
    assert chord_azimuth(0.0, 0.0, 1.5, dt, yaw_rate) is None
