"""The live service's inputs recorded (:mod:`sumhe.service.inputs`, ``sumhe run --record-inputs``): the file
replays to the estimates the service sent, one for one; its lines read back bit for bit."""

from __future__ import annotations

import asyncio
import dataclasses
import datetime as dt
import gc
import itertools
import math
import time

import can
import pytest
from test_serial_source import Pty, epoch_at, until

from sumhe.config import load_config
from sumhe.estimator.registry import make_estimator
from sumhe.io.can_source import CanBusSource
from sumhe.io.serial import SerialNmeaSource
from sumhe.messages import CanSample, Estimate, GnssFix
from sumhe.service.app import Service
from sumhe.service.inputs import InputRecorder, decode, read_inputs, read_records
from sumhe.service.inputs import encode as encode_sample
from sumhe.service.pipeline import Pipeline

from canframes import encode, ref_db

_channels = itertools.count()


def test_samples_read_back_bit_for_bit(tmp_path):
    samples = [
        CanSample(1_700_000_000.123456789, "speed", 0.1 + 0.2),
        CanSample(1_700_000_000.2, "yaw_rate", -1e-17),
        GnssFix(
            t=1_700_000_000.3,
            time_utc=dt.datetime(2024, 5, 17, 12, 0, 0, 300000, tzinfo=dt.timezone.utc),
            lat_deg=48.1173,
            lon_deg=11.516666666666667,
            alt_m=None,
            quality=1,
            valid=True,
            hdop=math.nan,
            course_rad=1.4730578,
            talker="GP",
        ),
        GnssFix(t=1_700_000_000.4, time_utc=None, lat_deg=None, lon_deg=None, alt_m=None, quality=0, valid=False),
    ]
    path = tmp_path / "inputs.jsonl"
    recorder = InputRecorder(path)
    for k, s in enumerate(samples):
        recorder(s, 100.0 + k, 100.5 + k)
    recorder.close()
    recorder.close()
    back = list(read_inputs(path))
    assert [(r.arrived, r.pushed) for r in read_records(path)] == [(100.0 + k, 100.5 + k) for k in range(4)]
    assert [encode_sample(s) for s in back] == [encode_sample(s) for s in samples]
    assert back[:2] == samples[:2] and back[3] == samples[3]
    assert back[2].time_utc == samples[2].time_utc and math.isnan(back[2].hdop)
    with pytest.raises(ValueError, match="not a recorded input"):
        decode('{"gga": 1}')


def test_the_recorded_inputs_of_a_live_service_replay_to_the_estimates_it_sent(tmp_path):
    """A live service on a python-can virtual bus (CAN speed 50 Hz, yaw rate 100 Hz) and a pseudo-terminal (NMEA
    10 Hz, its UTC years off the service clock) records its inputs; a replay of them gives every estimate it sent."""
    channel = f"sumhe-inputs-{next(_channels)}"
    pty = Pty()
    config = load_config(
        env={},
        overrides={
            "can.interface": "virtual",
            "can.channel": channel,
            "can.signals.speed": "ESP_VEHICLE_SPEED.VEHICLE_SPEED",
            "can.signals.yaw_rate": "ESP_YAW_RATE.YAW_RATE",
            "gps.port": pty.path,
            "gps.latency_s": 0.05,
            "output.json": [],
        },
    )
    path = tmp_path / "inputs.jsonl"
    sent: list[Estimate] = []

    async def main() -> Service:
        sources = {"can": CanBusSource.from_config(config), "gps": SerialNmeaSource(config.gps)}
        recorder = InputRecorder(path)
        service = Service(config, make_estimator("ekf", config), sources, sink=sent.append, record=recorder)
        stop = asyncio.Event()
        task = asyncio.create_task(service.run(stop))
        await until(lambda: all(s.stats.connected for s in sources.values()))
        db = ref_db()
        with can.Bus(interface="virtual", channel=channel) as bus:
            start = time.monotonic()
            for k in range(200):  # 2 s
                await asyncio.sleep(max(0.0, start + 0.01 * k - time.monotonic()))
                bus.send(encode(db, "ESP_YAW_RATE", time.time(), YAW_RATE=2.0))
                if k % 2 == 0:
                    bus.send(encode(db, "ESP_VEHICLE_SPEED", time.time(), VEHICLE_SPEED=18.52))
                if k % 10 == 0:
                    pty.write(epoch_at(k // 10))
            await asyncio.sleep(0.3)
        frozen.append(service.status()["gc"]["frozen"])  # the collector policy (sumhe.service.collector)
        stop.set()
        await task
        recorder.close()
        return service

    frozen: list[int] = []

    try:
        service = asyncio.run(asyncio.wait_for(main(), 30.0))
    finally:
        pty.close()
    inputs = list(read_inputs(path))
    records = list(read_records(path))
    assert all(r.arrived <= r.pushed for r in records)
    assert all(a.pushed <= b.pushed for a, b in itertools.pairwise(records))
    assert sum(isinstance(s, GnssFix) for s in inputs) == service.pipeline.stats.fixes >= 15
    assert sum(isinstance(s, CanSample) for s in inputs) == service.pipeline.stats.can_samples >= 250
    pipeline = Pipeline(config, make_estimator("ekf", config))
    replayed = {(e.t, e.east_m, e.north_m) for s in inputs for e in pipeline.push(s)}
    assert len(sent) >= 50 and sum(e.mode == "ekf" for e in sent) >= 50
    assert all((e.t, e.east_m, e.north_m) in replayed for e in sent)
    assert frozen[0] > 0 and gc.get_freeze_count() == 0  # frozen while it ran, undone when it stopped
    status = service.status()
    assert status["latency_slow"]["slow"] >= 1
    run = status["latency_run"]  # every send since the start, beside the status window's
    assert run["sends"] == len(sent) == service.stats.sent
    assert 0.0 < run["p50"] <= run["p99"] <= run["max"] * 10 ** (0.5 / 100)  # a bin's centre: half a bin over


def test_the_inbox_waits_tell_the_can_samples_that_waited_behind_a_fix():
    """Three CAN speed samples: one pushed at once, one that waited 4 ms while a fix was pushed, one yaw rate (no
    estimate: not counted); a second fix whose next sample came 140 ms after its push (the worker waited for input:
    not a push that held it), and a third whose next sample came during its push (and waited 5 ms)."""
    from sumhe.bench.live import inbox_waits
    from sumhe.service.inputs import Recorded

    fix = GnssFix(t=9.9, time_utc=None, lat_deg=48.1, lon_deg=11.5, alt_m=None, quality=1, valid=True)
    records = [
        Recorded(CanSample(10.0, "speed", 5.0), 100.000, 100.001),
        Recorded(fix, 100.010, 100.012),
        Recorded(CanSample(10.02, "speed", 5.0), 100.011, 100.015),
        Recorded(CanSample(10.03, "yaw_rate", 0.1), 100.016, 100.050),
        Recorded(dataclasses.replace(fix, t=10.0), 100.055, 100.060),
        Recorded(CanSample(10.2, "yaw_rate", 0.1), 100.200, 100.2005),
        Recorded(dataclasses.replace(fix, t=10.1), 100.201, 100.202),
        Recorded(CanSample(10.21, "yaw_rate", 0.1), 100.203, 100.208),
    ]
    waits = inbox_waits(records)
    assert waits["wait_ms"] == pytest.approx((2.5, 3.97, 4.0), abs=1e-6)
    assert waits["behind_fix"] == pytest.approx((1, 4.0, 4.0), abs=1e-6)
    assert waits["longest_fix_push"] == pytest.approx((6.0, 0.2), abs=1e-6)  # the third fix's; not the second's 140 ms
