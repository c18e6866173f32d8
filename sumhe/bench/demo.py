"""``sumhe demo``: the bundled drive through the full live path, with no hardware.

CAN frames go onto a python-can ``virtual`` bus and NMEA into a pseudo-terminal (:mod:`sumhe.io.player`);
the service reads them as it reads a car (:class:`~sumhe.io.can_source.CanBusSource`,
:class:`~sumhe.io.serial.SerialNmeaSource`), runs the estimator and sends UDP JSON to 127.0.0.1, where the demo
listens like any client. Faster than real time (``speed`` > 1), everything runs on one scaled clock
``t0 + (wall - wall0) * speed``: the player keeps the frames' timestamps (``preserve_timestamps``) and the serial
source stamps lines with the same clock, so the estimator sees the drive as it happened. Wall-clock delays (the
serial source's 50 ms idle gap that closes an epoch, thread hand-overs) last ``speed`` times longer on that clock,
so a fix comes that much further behind the CAN data (the estimators insert it at its time, up to the front-end's
``MAX_FIX_LAG_S``).
"""

from __future__ import annotations

import asyncio
import json
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from sumhe.bench import metrics
from sumhe.config import Config, load_config
from sumhe.estimator.registry import check_live, make_estimator
from sumhe.geo import LocalFrame
from sumhe.io.can import REFERENCE_E2E, REFERENCE_SIGNALS, read_log
from sumhe.io.can_source import CanBusSource
from sumhe.io.nmea import iter_fixes
from sumhe.io.player import Player, Pty, read_nmea_log
from sumhe.io.replay import log_samples
from sumhe.io.serial import SerialNmeaSource
from sumhe.io.udp import estimate_to_json
from sumhe.service.app import Service, install_signal_handlers
from sumhe.service.pipeline import Pipeline
from sumhe.sim import Truth, bundled_drive_dir, load_settings, load_truth

LIVE_LINE_S = 1.0
POLL_S = 0.05


@dataclass(frozen=True)
class ErrorSummary:
    """Horizontal position errors (m) of one estimator against the truth, split by GPS status."""

    n_ok: int
    n_outage: int
    ok: tuple[float, float, float]
    outage: tuple[float, float, float]


def position_errors(records: list[dict[str, Any]], truth: Truth, frame: LocalFrame) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal error (m) of each JSON estimate against the truth at its time, and its ``gps`` flag."""
    if not records:
        return np.zeros(0), np.zeros(0, dtype=object)
    err = metrics.geodetic_errors(
        [r["t"] for r in records], [r["lat"] for r in records], [r["lon"] for r in records], truth, frame
    )
    return err, np.array([r["gps"] for r in records], dtype=object)


def summarise(records: list[dict[str, Any]], truth: Truth, frame: LocalFrame) -> ErrorSummary:
    err, gps = position_errors(records, truth, frame)
    ok = err[gps == "ok"]
    out = err[gps != "ok"]
    return ErrorSummary(int(ok.size), int(out.size), metrics.mean_p95_max(ok), metrics.mean_p95_max(out))


def demo_config(channel: str, pty_link: Path, udp_port: int, latency_s: float, estimator: str | None) -> Config:
    """The reference vehicle on a private ``virtual`` channel, GNSS on the pty, JSON to 127.0.0.1."""
    overrides: dict[str, Any] = {
        "can.interface": "virtual",
        "can.channel": channel,
        "can.signals": REFERENCE_SIGNALS,
        "can.e2e": list(REFERENCE_E2E),
        "gps.port": str(pty_link),
        "gps.latency_s": latency_s,
        "output.json": [f"127.0.0.1:{udp_port}"],
    }
    if estimator:
        overrides["estimator.name"] = estimator
    return load_config(None, env={}, overrides=overrides)


class _Collector(asyncio.DatagramProtocol):
    def __init__(self, records: list[dict[str, Any]]) -> None:
        self.records = records
        self.bad = 0

    def datagram_received(self, data: bytes, addr: Any) -> None:
        try:
            self.records.append(json.loads(data))
        except ValueError:
            self.bad += 1


def _live_line(rec: dict[str, Any], truth: Truth, frame: LocalFrame) -> str:
    err, _ = position_errors([rec], truth, frame)
    return (
        f"t={rec['t'] - truth.t[0]:6.1f}s gps={rec['gps']:<8} mode={rec['mode']:<14} window={rec['window']:>3} "
        f"solve={rec['solve_ms'] or 0:6.2f}ms east={rec['east']:8.1f} north={rec['north']:8.1f} "
        f"speed={rec['speed'] or 0:5.1f} error={err[0]:5.2f}m"
    )


async def run_live(
    drive_dir: Path, speed: float, estimator: str | None, say: Callable[[str], None]
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Play the drive through the live path; returns the JSON estimates received and the final status."""
    sim = load_settings(drive_dir / "scenario.toml")
    truth = load_truth(drive_dir / "truth.csv")
    frame = LocalFrame(sim.datum_lat_deg, sim.datum_lon_deg, sim.datum_alt_m)
    frames = list(read_log(drive_dir / "drive.log"))
    lines = read_nmea_log(drive_dir / "drive.nmea")
    loop = asyncio.get_running_loop()
    records: list[dict[str, Any]] = []
    transport, _ = await loop.create_datagram_endpoint(lambda: _Collector(records), local_addr=("127.0.0.1", 0))
    udp_port = transport.get_extra_info("sockname")[1]
    with tempfile.TemporaryDirectory(prefix="sumhe-demo-") as tmp:
        link = Path(tmp) / "gps"
        latency = sim.gps_latency_s + sim.gps_latency_jitter_s / 2.0
        config = demo_config(f"sumhe-demo-{os.getpid()}", link, udp_port, latency, estimator)
        t0 = min(frames[0].timestamp, lines[0].t)
        wall0 = [time.time()]

        def clock() -> float:
            return t0 + (time.time() - wall0[0]) * speed

        pty = Pty(link)
        bus = can.Bus(interface="virtual", channel=config.can.channel, preserve_timestamps=True)
        # the service clock reads t0 exactly when the player starts pacing (on_start), so the frames are stamped
        # with their drive times: a thread's start-up delay (x speed) would otherwise make CAN lag the GNSS
        player = Player(frames, lines, bus, pty, speed=speed, clock=lambda: t0)
        player.on_start = lambda: wall0.__setitem__(0, time.time())
        sources = {
            "can": CanBusSource.from_config(config, clock=clock),
            "gps": SerialNmeaSource(config.gps, clock=clock),
        }
        check_live(config.estimator.name)
        service = Service(
            config,
            make_estimator(config.estimator.name, config),
            sources,
            clock=clock,
            clock_rate=speed,
        )
        stop = asyncio.Event()
        install_signal_handlers(stop)
        for src in sources.values():
            await src.start()
        await asyncio.sleep(0.3)  # let the sources open before the first frame
        wall0[0] = time.time()
        player.start()
        task = asyncio.create_task(service.run(stop))
        try:
            next_line = time.monotonic() + LIVE_LINE_S
            while not player.join(0) and not stop.is_set() and not task.done():
                await asyncio.sleep(POLL_S)  # the end of the drive is noticed at once, before CAN times out
                if records and time.monotonic() >= next_line:
                    next_line += LIVE_LINE_S
                    say(_live_line(records[-1], truth, frame))
            await asyncio.sleep(max(0.5, 2.0 * latency / speed))
        finally:
            stop.set()
            player.stop()
            await task
            bus.shutdown()
            pty.close()
            transport.close()
    return records, service.status()


def dead_reckoning_records(drive_dir: Path) -> list[dict[str, Any]]:
    """The same drive through the dead-reckoning peer, offline (for the summary's comparison)."""
    sim = load_settings(drive_dir / "scenario.toml")
    config = demo_config("unused", drive_dir / "unused", 9, sim.gps_latency_s, "dead-reckoning")
    pipeline = Pipeline(config, make_estimator("dead-reckoning", config))
    out = []
    for sample in log_samples(config, drive_dir / "drive.log", drive_dir / "drive.nmea"):
        out.extend(estimate_to_json(e) for e in pipeline.push(sample))
    return out


def gnss_records(nmea_log: Path) -> list[dict[str, Any]]:
    """The receiver's own valid fixes as JSON-like records at the time their position refers to (UTC)."""
    return [
        {"t": fix.time_utc.timestamp(), "lat": fix.lat_deg, "lon": fix.lon_deg, "gps": "ok"}
        for fix in iter_fixes(nmea_log)
        if fix.valid and fix.time_utc is not None and fix.lat_deg is not None
    ]


@dataclass(frozen=True)
class DemoRun:
    """What one demo run gives its figure: the estimates of sumhe and of dead reckoning (JSON-like records), the
    receiver's own fixes, the truth and the outages (absolute start and end, s)."""

    runs: dict[str, list[dict[str, Any]]]
    fixes: list[dict[str, Any]]
    truth: Truth
    outages: list[tuple[float, float]]


def demo(speed: float, estimator: str | None, say: Callable[[str], None]) -> DemoRun:
    """Run the demo, saying its summary against the truth."""
    drive_dir = bundled_drive_dir()
    sim = load_settings(drive_dir / "scenario.toml")
    truth = load_truth(drive_dir / "truth.csv")
    frame = LocalFrame(sim.datum_lat_deg, sim.datum_lon_deg, sim.datum_alt_m)
    say(f"sumhe demo: {sim.duration_s:.0f} s urban drive, outages {sim.outages}, speed x{speed:g}")
    wall0 = time.monotonic()
    records, status = asyncio.run(run_live(drive_dir, speed, estimator, say))
    wall = time.monotonic() - wall0
    dr = dead_reckoning_records(drive_dir)
    say("")
    say(f"received {len(records)} estimates over UDP in {wall:.1f} s")
    span = (records[-1]["t"] - records[0]["t"]) if len(records) > 1 else 0.0
    if span > 0:
        say(f"output rate {len(records) / span:.1f} Hz of drive time")
    p50, p99, degraded = status["solve_ms_p50"], status["solve_ms_p99"], status["degraded_sent"]
    say(f"epoch update p50/p99 {p50}/{p99} ms, estimates sent degraded {degraded}")
    say("position error (m)           with GPS: mean / p95 / max      GPS out: mean / p95 / max")
    for name, recs in (("sumhe " + (estimator or "default"), records), ("dead reckoning", dr)):
        s = summarise(recs, truth, frame)
        say(
            f"  {name:<24} {s.ok[0]:8.2f} / {s.ok[1]:6.2f} / {s.ok[2]:6.2f}      "
            f"{s.outage[0]:8.2f} / {s.outage[1]:6.2f} / {s.outage[2]:6.2f}"
        )
    outages = [(truth.t[0] + start, truth.t[0] + start + length) for start, length in sim.outages]
    return DemoRun({"sumhe": records, "dead reckoning": dr}, gnss_records(drive_dir / "drive.nmea"), truth, outages)
