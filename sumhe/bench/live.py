"""``sumhe bench live``: the daemon measured as it runs in a car, on this machine.

Two real processes, as in the end-to-end test: ``sumhe play`` puts a simulated drive (10 Hz GNSS, 100/50 Hz CAN)
on a python-can ``udp_multicast`` bus (an interface-local IPv6 group: nothing leaves the machine) and its NMEA
into a pseudo-terminal, in real time; ``sumhe run`` reads both and sends JSON to 127.0.0.1, where this
benchmark listens. Printed: the output rate, the end-to-end latency from the CAN frame's timestamp to the UDP send
(the service's own status figures: no reorder hold, each CAN sample's estimate leaves when computed), the epoch
solve times, the daemon's CPU use (user + system time from ``/proc`` over the drive, in % of one core), and the
outage errors against the truth: the live run's own; the same drive files replayed in-process in time order (with
the fixes' UTC times) and in arrival order (:func:`arrival_order`: each fix after the CAN samples of its latency);
and the daemon's own inputs (``sumhe run --record-inputs``: what it received, with the times it gave them)
replayed as received, with the count of the estimates it sent that the replay gives again, and in time order:
the held version of the same inputs, what the former reorder hold would have given the estimator, against which
the live error is judged. The daemon's clock is not on the drive's UTC, so it stamps fixes by their UTC times
and the clock offset it learns (:class:`~sumhe.io.fixtime.FixClock`), not as the file replay does.

Runs at the same time on one machine (two benches, a bench beside a test suite) would hear each other: python-can's
``udp_multicast`` bus binds its port on every group, so each run takes a port of its own as well as a group
(:func:`free_multicast_port`, the config's ``can.bus``); a daemon that took more CAN samples than the drive has still
says so (a WARNING line).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from sumhe.config import Config, load_config
from sumhe.estimator.registry import make_estimator
from sumhe.frontend.fixes import LocalFix
from sumhe.io.replay import log_samples
from sumhe.io.serial import IDLE_S
from sumhe.messages import CanSample, GnssFix, Sample
from sumhe.service.app import SOLVE_WINDOW
from sumhe.service.inputs import Recorded, read_records
from sumhe.service.pipeline import Pipeline
from sumhe.sim import Drive, SimSettings, simulate, write_drive

S = TypeVar("S", Sample, LocalFix | CanSample)
GROUP_PREFIX = "ff11:7079:7468:6f6e:6465:6d6f"
"""Interface-local IPv6 multicast: each run takes its own group below it, and its own port (module docstring)."""
OUTAGE_S = 10.0
INPUTS = "inputs.jsonl"
"""The daemon's recorded inputs (``sumhe run --record-inputs``) in the run's directory."""


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _run_queue(pid: int) -> tuple[float, int]:
    """Seconds the threads of a process have waited for a CPU so far (run queue) and the time slices they ran (Linux
    ``/proc/PID/task/*/schedstat``: CPU time, wait time, time slices; a thread that has ended no longer counts)."""
    waited, slices = 0, 0
    for stat in Path(f"/proc/{pid}/task").glob("*/schedstat"):
        with contextlib.suppress(OSError, IndexError, ValueError):
            fields = stat.read_text().split()
            waited, slices = waited + int(fields[1]), slices + int(fields[2])
    return waited / 1e9, slices


def _sumhe(args: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    with open(log, "w") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "sumhe", "-v", *args], stderr=f, stdout=subprocess.DEVNULL, env=env
        )


@dataclass
class DaemonRun:
    """What one run of ``sumhe run`` against ``sumhe play`` gave: the JSON estimates with the benchmark's
    ``time.monotonic()`` at their arrival (``arrived``), the status datagrams, the player's clock offset (s:
    service time = drive time + offset), the daemon's CPU use (% of one core), how long its threads waited for a
    CPU (``run_queue_ms_per_s``: ms per s of the drive; ``run_queue_ms_per_slice``: the mean wait before each time
    slice it ran; CPU starvation) and the wall time the player took."""

    records: list[dict[str, Any]] = field(default_factory=list)
    arrived: list[float] = field(default_factory=list)
    statuses: list[dict[str, Any]] = field(default_factory=list)
    offset_s: float = math.nan
    cpu_percent: float = math.nan
    run_queue_ms_per_s: float = math.nan
    run_queue_ms_per_slice: float = math.nan
    play_s: float = math.nan

    @property
    def status(self) -> dict[str, Any]:
        return self.statuses[-1] if self.statuses else {}


def live_drive(duration_s: float, directory: Path) -> tuple[Drive, Path]:
    """The benchmark's drive (urban, seed 5, one outage of ``OUTAGE_S`` at half time) written to ``directory``."""
    sim = simulate(SimSettings(scenario="urban", seed=5, duration_s=duration_s, outages=((duration_s / 2, OUTAGE_S),)))
    write_drive(sim, directory)
    return sim, directory


def free_multicast_port() -> int:
    """A UDP port free on every IPv6 address now, for one run's ``udp_multicast`` bus (module docstring)."""
    with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
        s.bind(("::", 0))
        return int(s.getsockname()[1])


def multicast_can_table(group: str, port: int) -> str:
    """The ``[can]`` table of a ``udp_multicast`` bus on the interface-local ``group`` and ``port``."""
    return f'[can]\ninterface = "udp_multicast"\nchannel = "{group}"\nbus = {{ port = {port} }}\n'


def service_config(
    sim: Drive, tmp: Path, estimator: str, group: str, bus_port: int, json_port: int, status_port: int
) -> Path:
    """The daemon's config file: the udp_multicast bus on ``group`` and ``bus_port``, the pty, JSON and status to
    127.0.0.1."""
    latency = sim.settings.gps_latency_s + sim.settings.gps_latency_jitter_s / 2
    path = tmp / "service.toml"
    can_table = multicast_can_table(group, bus_port)
    path.write_text(
        f"{can_table}"
        '[can.signals]\nspeed = "ESP_VEHICLE_SPEED.VEHICLE_SPEED"\nyaw_rate = "ESP_YAW_RATE.YAW_RATE"\n'
        f'[gps]\nport = "{tmp / "gps"}"\nlatency_s = {latency}\nreconnect_max_s = 0.5\n'
        f'[output]\njson = ["127.0.0.1:{json_port}"]\n'
        f'status_udp = "127.0.0.1:{status_port}"\nstatus_interval_s = 1.0\n'
        f'[estimator]\nname = "{estimator}"\n'
    )
    return path


def run_daemon(
    sim: Drive,
    drive_dir: Path,
    tmp: Path,
    estimator: str,
    speed: float = 1.0,
    during: Callable[[subprocess.Popen, float], None] | None = None,
) -> DaemonRun:
    """Play ``drive_dir`` at ``speed`` through ``sumhe run`` (two processes); what came out. ``during`` is called
    with the daemon's process and the seconds played, every 20 ms while the player plays (fault injection)."""
    est_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    est_sock.bind(("127.0.0.1", 0))
    status_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    status_sock.bind(("127.0.0.1", 0))
    for s in (est_sock, status_sock):
        s.setblocking(False)
    group = f"{GROUP_PREFIX}:{os.getpid() & 0xFFFF:x}:{est_sock.getsockname()[1]:x}"
    bus_port = free_multicast_port()
    config = service_config(
        sim, tmp, estimator, group, bus_port, est_sock.getsockname()[1], status_sock.getsockname()[1]
    )
    (tmp / "player.toml").write_text(multicast_can_table(group, bus_port))
    run = DaemonRun()
    service = _sumhe(["run", "--config", str(config), "--record-inputs", str(tmp / INPUTS)], tmp / "service.log")
    try:
        while "sumhe starting" not in (tmp / "service.log").read_text():
            if service.poll() is not None:
                raise RuntimeError(f"sumhe run ended: {(tmp / 'service.log').read_text()[-2000:]}")
            time.sleep(0.1)
        cpu0, (queued0, slices0), wall0 = _cpu_s(service.pid), _run_queue(service.pid), time.monotonic()
        player = _sumhe(
            [
                "play",
                str(drive_dir),
                "--config",
                str(tmp / "player.toml"),
                "--pty",
                str(tmp / "gps"),
                "--speed",
                f"{speed:g}",
            ],
            tmp / "player.log",
        )
        while player.poll() is None:
            time.sleep(0.02)
            if during is not None:
                during(service, time.monotonic() - wall0)
            _drain(est_sock, run)
            _drain_status(status_sock, run.statuses)
        run.play_s = time.monotonic() - wall0
        run.cpu_percent = (_cpu_s(service.pid) - cpu0) / run.play_s * 100.0
        queued, slices = _run_queue(service.pid)
        run.run_queue_ms_per_s = (queued - queued0) / run.play_s * 1000.0
        run.run_queue_ms_per_slice = (queued - queued0) / max(slices - slices0, 1) * 1000.0
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            time.sleep(0.02)
            _drain(est_sock, run)
            _drain_status(status_sock, run.statuses)
    finally:
        service.terminate()
        service.wait(10)
        est_sock.close()
        status_sock.close()
    text = (tmp / "player.log").read_text()
    marker = "clock offset "
    if marker in text:
        run.offset_s = float(text.split(marker, 1)[1].split()[0])
    return run


def _drain(sock: socket.socket, run: DaemonRun) -> None:
    while True:
        try:
            data = sock.recv(65535)
        except BlockingIOError:
            return
        run.records.append(json.loads(data))
        run.arrived.append(time.monotonic())


def _drain_status(sock: socket.socket, into: list[dict[str, Any]]) -> None:
    while True:
        try:
            data = sock.recv(65535)
        except BlockingIOError:
            return
        into.append(json.loads(data))


def outage_errors_of(records: list[dict[str, Any]], sim: Drive, offset_s: float) -> tuple[float, float, float]:
    """Mean, p95 and max horizontal error (m) of the JSON ``records`` inside the drive's outages, their times on
    the service clock (drive time + ``offset_s``)."""
    if not records:
        return (math.nan, math.nan, math.nan)
    t = np.array([r["t"] for r in records]) - offset_s
    enu = sim.frame.to_enu(np.array([r["lat"] for r in records]), np.array([r["lon"] for r in records]), 0.0)
    at = sim.truth.at(t)
    err = np.hypot(enu[:, 0] - at.east, enu[:, 1] - at.north)
    inside = np.asarray(sim.in_outage(t), dtype=bool)
    return _summary(err[inside])


def _summary(err: np.ndarray) -> tuple[float, float, float]:
    if not err.size:
        return (math.nan, math.nan, math.nan)
    return float(np.mean(err)), float(np.percentile(err, 95)), float(np.max(err))


def replayed_outage_errors(sim: Drive, config: Config, drive_dir: Path, estimator: str) -> dict[str, Any]:
    """The drive's files replayed in-process in time order (``held``) and in arrival order (``arrival``): outage
    errors of the estimator's own outputs (m: mean, p95, max)."""
    samples = list(log_samples(config, drive_dir / "drive.log", drive_dir / "drive.nmea"))
    delay = sim.settings.gps_latency_s + sim.settings.gps_latency_jitter_s / 2.0 + IDLE_S
    out: dict[str, Any] = {}
    for name, ordered in (("held", samples), ("arrival", arrival_order(samples, delay))):
        pipeline = Pipeline(config, make_estimator(estimator, config))
        records = [{"t": e.t, "lat": e.lat_deg, "lon": e.lon_deg} for s in ordered for e in pipeline.push(s)]
        out[name] = outage_errors_of(records, sim, 0.0)
    return out


def replayed_inputs(
    sim: Drive, config: Config, path: Path, estimator: str, sent: list[dict[str, Any]], offset_s: float
) -> dict[str, Any]:
    """The daemon's own inputs (``sumhe run --record-inputs``: its samples in its order, with its times) replayed
    in-process: as received, with the count of the estimates it sent that the replay gives again (the same time,
    latitude and longitude as the JSON carries them), and in time order (``held``: what a reorder hold would have
    given the estimator from the same inputs); outage errors (m: mean, p95, max) of both, and the CAN samples it
    took."""
    records = list(read_records(path))
    samples = [r.sample for r in records]
    out: dict[str, Any] = {"can_samples": sum(isinstance(s, CanSample) for s in samples), **inbox_waits(records)}
    for name, ordered in (("as_received", samples), ("held", sorted(samples, key=lambda s: s.t))):
        pipeline = Pipeline(config, make_estimator(estimator, config))
        estimates = [e for s in ordered for e in pipeline.push(s)]
        out[name] = outage_errors_of([{"t": e.t, "lat": e.lat_deg, "lon": e.lon_deg} for e in estimates], sim, offset_s)
        if name == "as_received":
            made = {(round(e.t, 4), round(e.lat_deg, 9), round(e.lon_deg, 9)) for e in estimates}
            out["identical"] = sum((r["t"], r["lat"], r["lon"]) in made for r in sent)
    return out


BUSY_WAIT_S = 1e-3
"""A sample that waited longer than this (s) between its arrival and its push waited for the worker
(:func:`inbox_waits`; a sample taken from an idle worker's inbox waits ~0.1 ms)."""


def inbox_waits(records: Sequence[Recorded]) -> dict[str, Any]:
    """How long the daemon's CAN speed samples (each makes an estimate) waited between their arrival in its inbox
    and their push (ms: p50, p99, max), and those of them during whose wait a GNSS fix was pushed (a late fix's
    re-run, the MHE's solve): their count, p50 and max; the longest a fix's push held the worker (ms: from its
    push to the next sample's, which includes sending its estimates; only where that sample waited, having come
    before the fix's push began or waited over ``BUSY_WAIT_S`` for its own: else the worker was waiting for input,
    not busy) and how long after the first fix that fix came (s, on the fixes' own clock)."""
    fixes = np.array([r.pushed for r in records if isinstance(r.sample, GnssFix)])
    first_fix_t = next((r.sample.t for r in records if isinstance(r.sample, GnssFix)), math.nan)
    speed = [r for r in records if isinstance(r.sample, CanSample) and r.sample.quantity == "speed"]
    wait = np.array([(r.pushed - r.arrived) * 1000.0 for r in speed])
    before = np.searchsorted(fixes, [r.arrived for r in speed], side="right")
    upto = np.searchsorted(fixes, [r.pushed for r in speed], side="left")
    behind = wait[upto > before] if len(speed) else wait

    def figures(w: np.ndarray, qs: tuple[float, ...]) -> tuple[float, ...]:
        return tuple(float(np.percentile(w, q)) for q in qs) if w.size else (math.nan,) * len(qs)

    held = [
        (b.pushed - a.pushed, a.sample.t)
        for a, b in itertools.pairwise(records)
        if isinstance(a.sample, GnssFix) and (b.arrived <= a.pushed or b.pushed - b.arrived > BUSY_WAIT_S)
    ]
    longest = max(held, default=(math.nan, math.nan))
    return {
        "wait_ms": figures(wait, (50, 99, 100)),
        "behind_fix": (int(behind.size), *figures(behind, (50, 100))),
        "longest_fix_push": (longest[0] * 1000.0, longest[1] - first_fix_t),
    }


def run_live(duration_s: float, estimator: str, say: Any = print) -> dict[str, Any]:
    """Play a drive of ``duration_s`` through ``sumhe run``; returns the measured figures."""
    with tempfile.TemporaryDirectory(prefix="sumhe-live-") as tmp_name:
        tmp = Path(tmp_name)
        sim, drive_dir = live_drive(duration_s, tmp / "drive")
        run = run_daemon(sim, drive_dir, tmp, estimator)
        config = load_config(tmp / "service.toml")
        replayed = replayed_outage_errors(sim, config, drive_dir, estimator)
        own = replayed_inputs(sim, config, tmp / INPUTS, estimator, run.records, run.offset_s)
        drive_can = sum(isinstance(s, CanSample) for s in log_samples(config, drive_dir / "drive.log", None))
    last = run.status
    return {
        "estimator": estimator,
        "drive_s": duration_s,
        "estimates": len(run.records),
        "rate_hz": len(run.records) / duration_s,
        "latency_run": last.get("latency_run", {}),
        "latency_ms_p50": last.get("latency_ms_p50"),
        "latency_ms_p99": last.get("latency_ms_p99"),
        "latency_slow": last.get("latency_slow", {}),
        "gc": last.get("gc", {}),
        "solve_ms_p50": last.get("solve_ms_p50"),
        "solve_ms_p99": last.get("solve_ms_p99"),
        "out_of_order": last.get("out_of_order"),
        "late_fixes": {k: v for k, v in last.get("estimator", {}).items() if k.startswith("late_fixes")},
        "degraded_sent": last.get("degraded_sent"),
        "source_rates_hz": last.get("rates_hz"),
        "cpu_percent_of_one_core": run.cpu_percent,
        "run_queue_ms_per_s": run.run_queue_ms_per_s,
        "run_queue_ms_per_slice": run.run_queue_ms_per_slice,
        "outage_live": outage_errors_of(run.records, sim, run.offset_s),
        "outage_held": replayed["held"],
        "outage_arrival": replayed["arrival"],
        "outage_received": own["as_received"],
        "outage_received_held": own["held"],
        "identical": own["identical"],
        "wait_ms": own["wait_ms"],
        "behind_fix": own["behind_fix"],
        "longest_fix_push": own["longest_fix_push"],
        "can_samples": (own["can_samples"], drive_can),
        "offset_s": run.offset_s,
        "nonmonotonic": int(np.sum(np.diff([r["t"] for r in run.records]) < 0)) if run.records else 0,
    }


def format_live(fig: dict[str, Any]) -> str:
    def err(key: str) -> str:
        mean, p95, worst = fig[key]
        return f"{mean:.2f} / {p95:.2f} / {worst:.2f}"

    held = fig["outage_held"][0]
    run = fig["latency_run"]
    took, played = fig["can_samples"]
    crosstalk = (
        [
            f"  WARNING: the daemon took {took} CAN samples, the drive has {played}: another run's udp_multicast "
            "traffic on this machine reached it (on the same port); figures not valid"
        ]
        if took > 1.02 * played
        else []
    )
    return "\n".join(
        [
            f"live daemon, estimator {fig['estimator']}, {fig['drive_s']:.0f} s drive in real time "
            f"(10 Hz GNSS, 100 Hz yaw rate + 50 Hz speed CAN, one {OUTAGE_S:.0f} s outage), OPENBLAS_NUM_THREADS=1",
            f"  output: {fig['estimates']} estimates, {fig['rate_hz']:.1f} Hz; source rates {fig['source_rates_hz']}",
            "  end-to-end latency (CAN frame timestamp -> UDP send, no reorder hold), all "
            f"{run.get('sends')} sends: p50 {run.get('p50')} ms, p99 {run.get('p99')} ms, max {run.get('max')} ms "
            f"(the last {SOLVE_WINDOW} sends: p50 {fig['latency_ms_p50']} ms, p99 {fig['latency_ms_p99']} ms)",
            f"  {gc_line(fig['gc'], fig['latency_slow'])}",
            "  inbox wait of the CAN speed samples (arrival -> push, ms) p50 / p99 / max "
            f"{' / '.join(f'{w:.2f}' for w in fig['wait_ms'])}; {fig['behind_fix'][0]} waited while a GNSS fix was "
            f"pushed (p50 / max {fig['behind_fix'][1]:.2f} / {fig['behind_fix'][2]:.2f}); the longest push of a fix "
            f"{fig['longest_fix_push'][0]:.1f} ms (the fix {fig['longest_fix_push'][1]:.1f} s after the first)",
            f"  solve p50 {fig['solve_ms_p50']} ms, p99 {fig['solve_ms_p99']} ms; sent degraded "
            f"{fig['degraded_sent']}; left out as out of order {fig['out_of_order']}; t decreasing between "
            f"datagrams {fig['nonmonotonic']}",
            f"  CPU: {fig['cpu_percent_of_one_core']:.1f} % of one core; its threads waited for a CPU (run queue) "
            f"{fig['run_queue_ms_per_s']:.1f} ms per s, {fig['run_queue_ms_per_slice']:.3f} ms before each time slice "
            f"on average; late fixes {fig['late_fixes'] or 'none'}",
            "  outage error (m, mean / p95 / max): "
            f"live {err('outage_live')}; replayed in time order (held) {err('outage_held')}; "
            f"replayed in arrival order {err('outage_arrival')} "
            f"({(fig['outage_arrival'][0] / held - 1.0) * 100.0:+.1f} % mean vs held)",
            f"  the daemon's own inputs replayed: as received {err('outage_received')} ({fig['identical']} of "
            f"{fig['estimates']} sent estimates given again); in time order (held) {err('outage_received_held')} "
            f"(live {(fig['outage_live'][0] / fig['outage_received_held'][0] - 1.0) * 100.0:+.1f} % mean vs held)",
            *crosstalk,
        ]
    )


def gc_line(gc: dict[str, Any], slow: dict[str, int]) -> str:
    """The daemon's garbage collections (its final status: count and longest pause per generation, objects frozen)
    and how many of its slowest sends (at or above the p99 of the last status window) were in flight while one
    ran."""
    pauses = ", ".join(
        f"gen{g} {gc[f'gen{g}']['count']} x, max {gc[f'gen{g}']['max_ms']:.2f} ms" for g in range(3) if f"gen{g}" in gc
    )
    coincide = " / ".join(str(slow.get(f"gc_gen{g}", 0)) for g in range(3))
    return (
        f"GC in the daemon: {pauses or 'not reported'}; {gc.get('frozen', 0)} objects frozen; of its "
        f"{slow.get('slow', 0)} sends at or above the p99, {coincide} were in flight during a gen0 / gen1 / gen2 "
        "collection"
    )


def arrival_order(samples: Sequence[S], fix_delay_s: float) -> list[S]:
    """Time-ordered ``samples`` (fixes at their measurement time) in the order a live service gets them: a CAN
    sample at its own time, a fix ``fix_delay_s`` after its time (the receiver's latency and the serial source's
    idle gap), so it comes after the CAN samples of that span (stable for equal times)."""
    keyed = sorted(
        ((s.t if isinstance(s, CanSample) else s.t + fix_delay_s, i) for i, s in enumerate(samples)),
    )
    return [samples[i] for _, i in keyed]
