"""``sumhe demo``: the bundled drive through the full live path, with no hardware.

CAN frames go onto a python-can ``virtual`` bus and NMEA into a pseudo-terminal (:mod:`sumhe.io.player`);
the service reads them as it reads a car (:class:`~sumhe.io.can_source.CanBusSource`,
:class:`~sumhe.io.serial.SerialNmeaSource`), runs the estimator and sends UDP JSON to 127.0.0.1, where the demo
listens like any client. Faster than real time (``speed`` > 1), everything runs on one scaled clock
``t0 + (wall - wall0) * speed``: the player keeps the frames' timestamps (``preserve_timestamps``) and the serial
source stamps lines with the same clock, so the estimator sees the drive as it happened.
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
from sumhe.io.player import Player, Pty, read_nmea_log
from sumhe.io.replay import log_samples
from sumhe.io.serial import SerialNmeaSource
from sumhe.io.udp import estimate_to_json
from sumhe.service.app import Service, install_signal_handlers
from sumhe.service.pipeline import Pipeline
from sumhe.sim import Truth, bundled_drive_dir, load_settings, load_truth

LIVE_LINE_S = 1.0


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
        "output.udp": [f"127.0.0.1:{udp_port}"],
        "output.formats": ["json"],
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
        player = Player(frames, lines, bus, pty, speed=speed, clock=clock)
        sources = {"can": CanBusSource.from_config(config), "gps": SerialNmeaSource(config.gps, clock=clock)}
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
        wall0[0] = time.time()  # the service clock reads t0 when the drive starts
        player.start()
        task = asyncio.create_task(service.run(stop))
        try:
            while not player.join(0) and not stop.is_set():
                await asyncio.sleep(LIVE_LINE_S)
                if records:
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


def plot(
    path: Path, truth: Truth, frame: LocalFrame, runs: dict[str, list[dict[str, Any]]], outages: list[list[float]]
) -> bool:
    """Trajectory and error-over-time PNG (outages shaded); False when matplotlib is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, (ax, ax_err) = plt.subplots(1, 2, figsize=(14, 7), gridspec_kw={"width_ratios": [1, 1.6]})
    ax.plot(truth.east, truth.north, color="black", lw=1.0, label="truth")
    t0 = truth.t[0]
    for start, length in outages:
        sel = (truth.t >= t0 + start) & (truth.t <= t0 + start + length)
        ax.plot(truth.east[sel], truth.north[sel], color="orange", lw=7, alpha=0.35)
        ax_err.axvspan(start, start + length, color="orange", alpha=0.25)
    for name, recs in runs.items():
        if recs:
            enu = frame.to_enu(np.array([r["lat"] for r in recs]), np.array([r["lon"] for r in recs]), frame.alt0_m)
            ax.plot(enu[:, 0], enu[:, 1], lw=0.8, label=name)
            err, _ = position_errors(recs, truth, frame)
            ax_err.plot(np.array([r["t"] for r in recs]) - t0, err, lw=0.8, label=name)
    ax.plot([], [], color="orange", lw=7, alpha=0.35, label="GPS outage")
    ax.set(xlabel="east (m)", ylabel="north (m)", title="bundled drive")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)
    ax_err.set(xlabel="time (s)", ylabel="horizontal error (m)", title="error against the truth (outages shaded)")
    ax_err.legend(loc="upper left", fontsize=8)
    ax_err.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def demo(speed: float, estimator: str | None, png: Path | None, say: Callable[[str], None]) -> int:
    """Run the demo; returns the exit code (0 when estimates arrived at the expected rate)."""
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
    p50, p99, skipped = status["solve_ms_p50"], status["solve_ms_p99"], status["skipped_epochs"]
    say(f"epoch update p50/p99 {p50}/{p99} ms, skipped epochs {skipped}")
    say("position error (m)           with GPS: mean / p95 / max      GPS out: mean / p95 / max")
    for name, recs in (("sumhe " + (estimator or "default"), records), ("dead reckoning", dr)):
        s = summarise(recs, truth, frame)
        say(
            f"  {name:<24} {s.ok[0]:8.2f} / {s.ok[1]:6.2f} / {s.ok[2]:6.2f}      "
            f"{s.outage[0]:8.2f} / {s.outage[1]:6.2f} / {s.outage[2]:6.2f}"
        )
    if png is not None:
        runs = {"sumhe": records, "dead reckoning": dr}
        if plot(png, truth, frame, runs, [list(o) for o in sim.outages]):
            say(f"trajectory plot: {png}")
        else:
            say("matplotlib is not installed: no plot (pip install 'sumhe[plot]')")
    return 0 if records else 1
