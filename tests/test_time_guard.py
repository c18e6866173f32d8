import math

import pytest
from test_udp import _estimate

from sumhe.messages import CanSample, GnssFix
from sumhe.service.app import Inbox
from sumhe.service.pipeline import MonotonicOutput, TimeGuard, TimeRules

T0 = 1780300800.0


def can(t: float, value: float = 1.0) -> CanSample:
    return CanSample(t, "speed", value)


def fix(t: float) -> GnssFix:
    return GnssFix(t=t, time_utc=None, lat_deg=48.1, lon_deg=11.5, alt_m=0.0, quality=1, valid=True)


def test_in_order_samples_are_accepted():
    g = TimeGuard(TimeRules())
    assert [g.check(can(T0 + i * 0.01)) for i in range(5)] == ["ok"] * 5
    assert g.stats.accepted == 5


@pytest.mark.parametrize("t", [0.0, -5.0, math.nan, math.inf])
def test_zero_and_non_finite_times_are_dropped(t):
    g = TimeGuard(TimeRules())
    assert g.check(can(t)) == "drop"
    assert g.stats.zero_time == 1 and g.stats.accepted == 0


def test_future_and_stale_are_judged_against_the_wall_clock():
    g = TimeGuard(TimeRules(future_s=2.0, stale_s=10.0), wall_clock=lambda: T0)
    assert g.check(can(T0 + 5.0)) == "drop"
    assert g.check(can(T0 - 60.0)) == "drop"
    assert g.check(can(T0 - 0.5)) == "ok"
    assert (g.stats.future, g.stats.stale) == (1, 1)


def test_late_and_duplicate_samples_are_dropped():
    g = TimeGuard(TimeRules())
    assert g.check(can(T0 + 1.0)) == "ok"
    assert g.check(can(T0 + 0.5)) == "drop"
    assert g.check(can(T0 + 1.0)) == "drop"  # the same sample again
    assert g.check(can(T0 + 1.0, value=2.0)) == "ok"  # same time, other value: a real sample
    assert (g.stats.late, g.stats.duplicate) == (1, 1)


@pytest.mark.parametrize("jump", [+120.0, -120.0])
def test_a_clock_jump_either_way_asks_for_a_reset(jump):
    g = TimeGuard(TimeRules(jump_s=30.0))
    g.check(can(T0))
    assert g.check(can(T0 + jump)) == "reset"
    assert g.check(can(T0 + jump + 0.01)) == "ok"
    assert g.stats.clock_resets == 1


def test_gnss_clock_skew_against_can_is_counted_but_the_fix_is_used():
    g = TimeGuard(TimeRules(skew_s=1.0))
    g.check(can(T0 + 5.0))
    assert g.check(fix(T0 + 7.0)) == "ok"
    assert g.stats.skew == 1 and g.stats.last_skew_s == pytest.approx(2.0)


def test_time_order_is_judged_per_stream_not_across_them():
    """No reorder hold: a fix stamped before CAN samples already taken is in order on its own stream."""
    g = TimeGuard(TimeRules())
    assert g.check(can(T0 + 1.0)) == "ok"
    assert g.check(CanSample(T0 + 0.99, "yaw_rate", 0.1)) == "ok"  # another quantity: its own stream
    assert g.check(fix(T0 + 0.8)) == "ok"  # the receiver's latency behind the CAN data
    assert g.check(fix(T0 + 0.7)) == "drop"  # back in time on the GNSS stream
    assert g.check(fix(T0 + 0.8)) == "drop"  # the same fix again
    assert g.check(CanSample(T0 + 0.98, "yaw_rate", 0.1)) == "drop"
    assert (g.stats.late, g.stats.duplicate, g.stats.accepted) == (2, 1, 3)


def test_a_clock_jump_is_judged_against_the_newest_of_any_stream():
    g = TimeGuard(TimeRules(jump_s=30.0))
    g.check(can(T0 + 100.0))
    assert g.check(fix(T0)) == "reset"
    assert g.check(can(T0 + 0.1)) == "ok"  # after the reset the CAN stream starts over too


def test_the_inbox_hands_out_the_earliest_stamped_first_and_drops_them_when_full():
    inbox = Inbox(max_len=4)
    for k, s in enumerate([can(T0 + 0.3), fix(T0 + 0.1), can(T0 + 0.2), can(T0 + 0.4), can(T0 + 0.5)]):
        inbox.put(s, arrived=100.0 + k)
    assert inbox.dropped == 1 and len(inbox) == 4  # the earliest-stamped (the fix at T0 + 0.1) went
    assert inbox.earliest_t() == T0 + 0.2
    chunk, arrived = inbox.take(3)
    assert [s.t for s in chunk] == [T0 + 0.2, T0 + 0.3, T0 + 0.4]
    assert arrived == 101.0  # the oldest arrival still waiting when taken
    assert inbox.last_arrivals == [102.0, 100.0, 103.0]  # each one's own, in the order taken
    assert [s.t for s in inbox.take(10)[0]] == [T0 + 0.5]
    assert not inbox and inbox.earliest_t() == math.inf


def test_the_output_edge_drops_estimates_stamped_before_the_last_sent():
    out = MonotonicOutput()
    times = [1.0, 1.1, 1.05, 1.1, 1.2, 0.9, 1.3]
    sent = [e.t for t in times for e in out.release([_estimate(t=t)], now=t)]
    assert sent == [1.0, 1.1, 1.1, 1.2, 1.3]
    assert out.out_of_order == 2
    assert out.reset() == []
    assert [e.t for e in out.release([_estimate(t=0.5)], now=0.5)] == [0.5]


def test_the_output_edge_holds_an_estimate_stamped_ahead_of_the_input_until_its_time():
    # an epoch estimate 0.3 s ahead of the CAN data (a positive GNSS time offset), then CAN-rate estimates: none of
    # them is dropped, the epoch's goes out in its place
    out = MonotonicOutput()
    sent = [e.t for e in out.release([_estimate(t=1.0), _estimate(t=1.3)], now=1.0)]
    for t in (1.1, 1.2, 1.3, 1.4):
        sent += [e.t for e in out.release([_estimate(t=t)], now=t)]
    assert sent == [1.0, 1.1, 1.2, 1.3, 1.3, 1.4] and out.out_of_order == 0 and out.held == 1
    # held at the end: let out by flush (or before the next estimates after a clock jump back)
    assert out.release([_estimate(t=2.0)], now=1.5) == [] and [e.t for e in out.flush()] == [2.0]
    out.release([_estimate(t=3.0)], now=2.5)
    assert [e.t for e in out.reset()] == [3.0]
    assert [e.t for e in out.release([_estimate(t=0.1)], now=0.1)] == [0.1]
