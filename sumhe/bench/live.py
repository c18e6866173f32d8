"""``sumhe bench live``: the daemon measured as it runs in a car, on this machine.

Two real processes, as in the end-to-end test: ``sumhe play`` puts a simulated drive (10 Hz GNSS, 100/50 Hz CAN)
on a python-can ``udp_multicast`` bus (an interface-local IPv6 group: nothing leaves the machine) and its NMEA
into a pseudo-terminal, in real time; ``sumhe run`` reads both and sends JSON to 127.0.0.1, where this
benchmark listens. Printed: the output rate, the end-to-end latency from the newest CAN frame's timestamp to the
UDP send (the service's own status figures), the epoch solve times, and the daemon's CPU use (user + system time
from ``/proc`` over the drive, in % of one core).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sumhe.bench.drives import BenchDrive, PeersSettings, simulated_drive
from sumhe.bench.peers import run_estimator
from sumhe.config import Config
from sumhe.io.serial import IDLE_S
from sumhe.messages import GnssFix, Sample
from sumhe.sim import SimSettings, profile_settings, simulate, write_drive

GROUP = "ff11:7079:7468:6f6e:6465:6d6f:6d63:6173"


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _sumhe(args: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    with open(log, "w") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "sumhe", "-v", *args], stderr=f, stdout=subprocess.DEVNULL, env=env
        )


def run_live(duration_s: float, estimator: str, say: Any = print) -> dict[str, Any]:
    """Play a drive of ``duration_s`` through ``sumhe run``; returns the measured figures."""
    with tempfile.TemporaryDirectory(prefix="sumhe-live-") as tmp_name:
        tmp = Path(tmp_name)
        sim = simulate(SimSettings(scenario="urban", seed=5, duration_s=duration_s, outages=((duration_s / 2, 10.0),)))
        write_drive(sim, tmp / "drive")
        est_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        est_sock.bind(("127.0.0.1", 0))
        status_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        status_sock.bind(("127.0.0.1", 0))
        for s in (est_sock, status_sock):
            s.setblocking(False)
        can = f'[can]\ninterface = "udp_multicast"\nchannel = "{GROUP}"\n'
        latency = sim.settings.gps_latency_s + sim.settings.gps_latency_jitter_s / 2
        (tmp / "service.toml").write_text(
            can + '[can.signals]\nspeed = "ESP_VEHICLE_SPEED.VEHICLE_SPEED"\nyaw_rate = "ESP_YAW_RATE.YAW_RATE"\n'
            f'[gps]\nport = "{tmp / "gps"}"\nlatency_s = {latency}\nreconnect_max_s = 0.5\n'
            f'[output]\njson = ["127.0.0.1:{est_sock.getsockname()[1]}"]\n'
            f'status_udp = "127.0.0.1:{status_sock.getsockname()[1]}"\nstatus_interval_s = 1.0\n'
            f'[estimator]\nname = "{estimator}"\n'
        )
        (tmp / "player.toml").write_text(can)
        service = _sumhe(["run", "--config", str(tmp / "service.toml")], tmp / "service.log")
        try:
            while "sumhe starting" not in (tmp / "service.log").read_text():
                time.sleep(0.1)
            cpu0, wall0 = _cpu_s(service.pid), time.monotonic()
            player = _sumhe(
                ["play", str(tmp / "drive"), "--config", str(tmp / "player.toml"), "--pty", str(tmp / "gps")],
                tmp / "player.log",
            )
            estimates, statuses = 0, []
            while player.poll() is None:
                time.sleep(0.05)
                estimates += _drain(est_sock, None)
                _drain(status_sock, statuses)
            cpu = (_cpu_s(service.pid) - cpu0) / (time.monotonic() - wall0) * 100.0
            time.sleep(1.5)
            estimates += _drain(est_sock, None)
            _drain(status_sock, statuses)
        finally:
            service.terminate()
            service.wait(10)
            est_sock.close()
            status_sock.close()
    last = statuses[-1] if statuses else {}
    return {
        "estimator": estimator,
        "drive_s": duration_s,
        "estimates": estimates,
        "rate_hz": estimates / duration_s,
        "latency_ms_p50": last.get("latency_ms_p50"),
        "latency_ms_p99": last.get("latency_ms_p99"),
        "solve_ms_p50": last.get("solve_ms_p50"),
        "solve_ms_p99": last.get("solve_ms_p99"),
        "skipped_epochs": last.get("skipped_epochs"),
        "source_rates_hz": last.get("rates_hz"),
        "cpu_percent_of_one_core": cpu,
    }


def _drain(sock: socket.socket, into: list[dict[str, Any]] | None) -> int:
    n = 0
    while True:
        try:
            data = sock.recv(65535)
        except BlockingIOError:
            return n
        n += 1
        if into is not None:
            into.append(json.loads(data))


def format_live(fig: dict[str, Any]) -> str:
    return "\n".join(
        [
            f"live daemon, estimator {fig['estimator']}, {fig['drive_s']:.0f} s drive in real time "
            f"(10 Hz GNSS, 100 Hz yaw rate + 50 Hz speed CAN, one 10 s outage), OPENBLAS_NUM_THREADS=1",
            f"  output: {fig['estimates']} estimates, {fig['rate_hz']:.1f} Hz; source rates {fig['source_rates_hz']}",
            f"  end-to-end latency (newest CAN timestamp -> UDP send) p50 {fig['latency_ms_p50']} ms, "
            f"p99 {fig['latency_ms_p99']} ms (the reorder hold is the GNSS latency + 100 ms)",
            f"  solve p50 {fig['solve_ms_p50']} ms, p99 {fig['solve_ms_p99']} ms; "
            f"skipped epochs {fig['skipped_epochs']}",
            f"  CPU: {fig['cpu_percent_of_one_core']:.1f} % of one core",
        ]
    )


def arrival_order(samples: list[Sample], fix_delay_s: float) -> list[Sample]:
    """Time-ordered ``samples`` (fixes at their measurement time) in the order a live service gets them: a CAN
    sample at its own time, a fix ``fix_delay_s`` after its time (the receiver's latency and the serial source's
    idle gap), so it comes after the CAN samples of that span (stable for equal times)."""
    keyed = sorted(
        ((s.t + fix_delay_s if isinstance(s, GnssFix) else s.t, i) for i, s in enumerate(samples)),
    )
    return [samples[i] for _, i in keyed]


def held_vs_arrival(estimator: str, drive: BenchDrive, fix_delay_s: float) -> dict[str, tuple[float, float, float]]:
    """Outage errors (m: mean, p95, max over the drive's outages) of ``estimator`` fed the drive in time order (what
    the reorder hold gave) and in arrival order (no hold, :func:`arrival_order`)."""
    out = {}
    for name, samples in (
        ("held", drive.samples),
        ("arrival", arrival_order(drive.samples, fix_delay_s)),
    ):
        result = run_estimator(estimator, dataclasses.replace(drive, samples=samples))
        err = np.concatenate([*result.outage_errors, np.zeros(0)])
        out[name] = (
            (float(np.mean(err)), float(np.percentile(err, 95)), float(np.max(err)))
            if err.size
            else (
                math.nan,
                math.nan,
                math.nan,
            )
        )
    return out


def ab_drive(base: Config, duration_s: float = 240.0, seed: int = 1) -> tuple[BenchDrive, float]:
    """The drive of the held/arrival comparison, the realistic profile's urban drive with outages of 5, 10, 30
    and 55 s placed as ``sumhe bench peers`` places them, and how long after its measurement time a fix of it
    reaches a live service (s: the drive's receiver latency, half its jitter, the serial idle gap)."""
    ps = PeersSettings(duration_s=duration_s, seeds=(seed,))
    sim = profile_settings("realistic", seed, scenario="urban", duration_s=duration_s)
    delay = sim.gps_latency_s + sim.gps_latency_jitter_s / 2.0 + IDLE_S
    return simulated_drive("urban", "", seed, ps, base, profile="realistic"), delay
