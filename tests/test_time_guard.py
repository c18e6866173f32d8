import math

import pytest

from sumhe.messages import CanSample, GnssFix
from sumhe.service.app import Reorder, newest_epoch_only
from sumhe.service.pipeline import TimeGuard, TimeRules

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


def test_reorder_releases_in_time_order_hold_after_each_timestamp():
    r = Reorder(hold_s=0.1)
    r.put(can(T0 + 0.20), now=T0 + 0.20)
    r.put(fix(T0 + 0.10), now=T0 + 0.25)  # stamped earlier than it arrived (receiver latency)
    r.put(can(T0 + 0.26), now=T0 + 0.26)
    assert r.next_due() == pytest.approx(T0 + 0.20)  # the fix, due 0.1 s after its own time
    released, lag = r.release(now=T0 + 0.31)
    assert [s.t for s in released] == [T0 + 0.10, T0 + 0.20]  # time order; the later CAN sample still held
    assert lag == pytest.approx(0.11, abs=1e-6)
    assert [s.t for s in r.release(now=T0 + 0.36)[0]] == [T0 + 0.26]


def test_reorder_never_holds_a_future_dated_sample_longer_than_the_hold():
    r = Reorder(hold_s=0.1)
    r.put(can(T0 + 100.0), now=T0)
    assert r.next_due() == pytest.approx(T0 + 0.1)
    assert len(r.release(now=T0 + 0.1)[0]) == 1


def test_newest_epoch_only_skips_older_epochs_but_keeps_can():
    batch = [fix(T0), can(T0 + 0.01), fix(T0 + 0.1), can(T0 + 0.11), fix(T0 + 0.2)]
    kept, skipped = newest_epoch_only(batch)
    assert skipped == 2
    assert [type(s).__name__ for s in kept] == ["CanSample", "CanSample", "GnssFix"]
    assert kept[-1].t == T0 + 0.2
