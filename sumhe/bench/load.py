"""``sumhe bench load``: the daemon overloaded, as :mod:`sumhe.bench.live` runs it but with the player faster than
real time (2x, 4x, 8x by default): CAN and GNSS arrive that many times faster than the drive was recorded, stamped
on arrival (the udp_multicast bus stamps on receive; the serial source stamps its lines), so the daemon sees a
drive that many times denser. Printed per speed: the output rate in each second of wall time while the player
plays (its minimum: the output never stops), the share of estimates sent with ``mode = "degraded"`` (the
estimator behind its input: MHE epochs appended unsolved), the degraded episodes (status counter) and the recovery
time (the longest run of degraded output, s of wall time), the samples dropped for their time or from the backlog,
and the daemon's CPU use.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sumhe.bench.live import live_drive, run_daemon

SPEEDS = (2.0, 4.0, 8.0)


def longest_run_s(arrived: Sequence[float], degraded: Sequence[bool]) -> float:
    """The longest span (s) from the first to the last of consecutive degraded outputs."""
    best, start = 0.0, None
    for t, bad in zip(arrived, degraded, strict=True):
        if bad:
            start = t if start is None else start
            best = max(best, t - start)
        else:
            start = None
    return best


def per_second(arrived: Sequence[float], t0: float, t1: float) -> np.ndarray:
    """Outputs in each whole second from ``t0`` to ``t1`` (s, the arrival clock)."""
    edges = np.arange(t0, t1 - 1.0 + 1e-9, 1.0)
    a = np.asarray(arrived)
    return np.array([np.count_nonzero((a >= e) & (a < e + 1.0)) for e in edges], dtype=int)


def run_load(duration_s: float, estimator: str, speeds: Sequence[float] = SPEEDS) -> list[dict[str, Any]]:
    """Play a drive of ``duration_s`` at each of ``speeds`` through ``sumhe run``; figures per speed."""
    out = []
    for speed in speeds:
        with tempfile.TemporaryDirectory(prefix="sumhe-load-") as tmp_name:
            tmp = Path(tmp_name)
            sim, drive_dir = live_drive(duration_s, tmp / "drive")
            run = run_daemon(sim, drive_dir, tmp, estimator, speed=speed)
        degraded = [r.get("mode") == "degraded" for r in run.records]
        first = run.arrived[0] if run.arrived else math.nan
        # whole seconds from the first output until the player ended (the drive's end: a partial second, left out)
        end = min(first + run.play_s, run.arrived[-1]) - 1.0 if run.arrived else first
        counts = per_second(run.arrived, first, end) if run.arrived else np.zeros(0)
        status = run.status
        time_drops = sum(v for k, v in status.get("time", {}).items() if k in ("stale", "late", "future"))
        out.append(
            {
                "speed": speed,
                "estimates": len(run.records),
                "play_s": run.play_s,
                "rate_mean": float(np.mean(counts)) if counts.size else math.nan,
                "rate_min": int(np.min(counts)) if counts.size else 0,
                "rates": counts.tolist(),
                "degraded_share": float(np.mean(degraded)) if degraded else math.nan,
                "degraded_episodes": status.get("degraded"),
                "recovery_s": longest_run_s(run.arrived, degraded),
                "time_drops": time_drops,
                "backlog_dropped": status.get("backlog_dropped"),
                "cpu_percent": run.cpu_percent,
                "estimator_stats": status.get("estimator", {}),
            }
        )
    return out


def format_load(figs: list[dict[str, Any]], estimator: str, duration_s: float) -> str:
    speeds = ", ".join(f"{f['speed']:g}x" for f in figs)
    lines = [
        f"load: sumhe run ({estimator}) against sumhe play at {speeds}; "
        f"{duration_s:.0f} s urban drive (10 Hz GNSS, 150 Hz CAN at 1x), udp_multicast + pty, JSON to 127.0.0.1",
        "  speed  outputs/s mean  min  degraded  episodes  recovery s  time drops  backlog drops  CPU %",
    ]
    for f in figs:
        lines.append(
            f"  {f['speed']:4g}x  {f['rate_mean']:14.1f}  {f['rate_min']:3d}  {100 * f['degraded_share']:7.1f}%  "
            f"{f['degraded_episodes']!s:>8}  {f['recovery_s']:10.1f}  {f['time_drops']:10}  "
            f"{f['backlog_dropped']!s:>13}  {f['cpu_percent']:5.0f}"
        )
    for f in figs:
        lines.append(f"  {f['speed']:g}x outputs per second: {f['rates']}")
    return "\n".join(lines)
