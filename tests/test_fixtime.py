"""A fix's measurement time on the service clock (:mod:`sumhe.io.fixtime`): UTC where the service clock is on UTC,
else UTC moved by the clock offset learned from the receive times (:class:`FixClock`); through a real
pseudo-terminal and the live service too."""

from __future__ import annotations

import asyncio
import datetime as dt
import itertools
import statistics
import time

import pytest
from test_serial_source import Pty, epoch_at, settings, until

from sumhe.config import GpsSettings, load_config
from sumhe.estimator.registry import make_estimator
from sumhe.io.fixtime import OFFSET_FIXES, FixClock, stamp_fix
from sumhe.io.serial import SerialNmeaSource
from sumhe.messages import Estimate, GnssFix

UTC0 = dt.datetime(2024, 5, 17, 12, 0, tzinfo=dt.timezone.utc)
LATENCY_S = 0.09


def fix(utc_s: float, receive_s: float) -> GnssFix:
    """A fix of UTC time ``utc_s`` received at ``receive_s`` (both s after ``UTC0``)."""
    return GnssFix(
        t=UTC0.timestamp() + receive_s,
        time_utc=UTC0 + dt.timedelta(seconds=utc_s),
        lat_deg=48.1,
        lon_deg=11.5,
        alt_m=500.0,
        quality=1,
        valid=True,
    )


def test_a_clock_off_utc_stamps_utc_plus_the_median_receive_offset():
    """Receive times that jitter (the receiver's output, the host's reads) 300 s off UTC: each fix is stamped at its
    UTC time plus the median of the offsets so far minus the latency, so the jitter stays out of the stamps."""
    gps = GpsSettings(latency_s=LATENCY_S)
    clock = FixClock(gps)
    delays = [0.08, 0.1, 0.085, 0.14, 0.09, 0.095, 0.3, 0.088, 0.092, 0.081] * 3
    utc0 = UTC0.timestamp()
    stamped = []
    for k, delay in enumerate(delays):
        out = clock.stamp(fix(0.1 * k, 300.0 + 0.1 * k + delay))
        expected = utc0 + 0.1 * k + 300.0 + statistics.median(delays[: k + 1]) - LATENCY_S
        assert out.t == pytest.approx(expected, abs=1e-6)
        stamped.append(out.t - (utc0 + 0.1 * k))
    assert clock.offset_s == pytest.approx(300.0 + statistics.median(delays), abs=1e-6)
    received = [300.0 + d - LATENCY_S for d in delays]
    assert max(stamped[10:]) - min(stamped[10:]) < 0.1 * (max(received) - min(received))


def test_the_median_spans_the_last_fixes_and_starts_over_after_a_clock_step():
    clock = FixClock(GpsSettings(latency_s=LATENCY_S))
    utc0 = UTC0.timestamp()
    for k in range(OFFSET_FIXES + 10):
        clock.stamp(fix(0.1 * k, 300.0 + 0.1 * k + (0.5 if k < 10 else 0.1)))
    assert clock.offset_s == pytest.approx(300.1)  # the first ten (0.5 s) have left the median's span
    out = clock.stamp(fix(100.0, 100.0 + 50.0 + 0.1))  # the host clock stepped by -250 s
    assert out.t == pytest.approx(utc0 + 100.0 + 50.1 - LATENCY_S)
    assert clock.offset_s == pytest.approx(50.1)


@pytest.mark.parametrize(
    ("gps", "utc_s", "receive_s", "expected"),
    [
        (GpsSettings(latency_s=LATENCY_S), 10.0, 10.3, 10.0),  # a clock on UTC: the UTC time as it is
        (GpsSettings(latency_s=LATENCY_S, time="receive"), 10.0, 300.3, 300.3 - LATENCY_S),
        (GpsSettings(latency_s=LATENCY_S, time="receive"), 10.0, 10.3, 10.3 - LATENCY_S),
    ],
    ids=["on-utc", "receive-off-utc", "receive-on-utc"],
)
def test_a_clock_on_utc_and_gps_time_receive_stamp_as_stamp_fix(gps, utc_s, receive_s, expected):
    utc0 = UTC0.timestamp()
    f = fix(utc_s, receive_s)
    out = FixClock(gps).stamp(f)
    assert out.t == pytest.approx(utc0 + expected, abs=1e-6)
    assert out.t == stamp_fix(f, gps).t
    no_utc = GnssFix(**{**{k: getattr(f, k) for k in f.__dataclass_fields__}, "time_utc": None})
    assert FixClock(gps).stamp(no_utc).t == pytest.approx(f.t - LATENCY_S)


def test_the_service_stamps_fixes_read_from_a_pty_at_their_utc_time_on_its_clock():
    """The live service reads a receiver (a real pseudo-terminal) whose UTC is years off the service clock and
    whose epochs come with uneven delays: each epoch's estimate is at the fix's UTC time plus the median receive
    offset of the fixes so far (what a :class:`FixClock` gives for the receive times the source stamped). On a
    loaded machine the writer's epochs may come late in a bunch: an epoch whose fix came after the estimator's
    deadline is estimated as an outage, and the stamps of bunched fixes come closer than the epochs: every estimate
    on a fix is still at that fix's stamped time."""
    from sumhe.service.app import Service

    def stamped(fixes: list[GnssFix]) -> list[float]:
        check = FixClock(GpsSettings(latency_s=LATENCY_S))
        return [check.stamp(f).t for f in fixes]

    pty = Pty()
    raw: list[GnssFix] = []
    got: list[Estimate] = []
    delays = [0.0, 0.0, 0.04, 0.0, 0.07, 0.0, 0.0, 0.02, 0.0, 0.0, 0.05, 0.0]

    async def main() -> None:
        gps = settings(pty.path, latency_s=LATENCY_S)
        source = SerialNmeaSource(gps)

        async def recorded():  # what the source yields, before the service stamps it
            async for f in source:
                raw.append(f)
                yield f

        config = load_config(overrides={"gps.latency_s": LATENCY_S, "output.json": []})
        service = Service(config, make_estimator("ekf", config), {"gps": recorded()}, sink=got.append)
        stop = asyncio.Event()
        task = asyncio.create_task(service.run(stop))
        await source.start()
        await until(lambda: source.stats.connected)
        start = time.monotonic()
        for k, delay in enumerate(delays):
            await asyncio.sleep(max(0.0, start + 0.1 * k + delay - time.monotonic()))
            pty.write(epoch_at(k))
        # the last epoch ends on the serial idle gap; its estimate is the last
        await until(lambda: len(raw) == len(delays) and bool(got) and got[-1].t >= stamped(raw)[-1] - 1e-6)
        stop.set()
        await task
        await source.close()

    try:
        asyncio.run(asyncio.wait_for(main(), 30.0))
    finally:
        pty.close()
    expected = stamped(raw)
    assert len(raw) == len(delays)
    late = [e for e in got if e.gps == "outage"]
    assert [e.gps for e in got if e not in late] == ["ok"] * (len(got) - len(late))
    if not late:
        assert [e.t for e in got] == pytest.approx(expected, abs=1e-6)
    assert all(min(abs(e.t - x) for x in expected) < 1e-6 for e in got if e not in late)
    assert all(b > a for a, b in itertools.pairwise(e.t for e in got))
    assert abs(got[0].t - raw[0].time_utc.timestamp()) > 86400.0  # the service clock is not UTC's
