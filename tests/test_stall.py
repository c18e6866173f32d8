"""A stall of the daemon across processes: ``sumhe run`` stopped with SIGSTOP for 5 s while ``sumhe play`` goes on
feeding the udp_multicast bus and the pseudo-terminal, then SIGCONT: the epochs the receiver delivered meanwhile
are read from the port's buffer at once, stamped from their UTC time (``restamped``) and not dropped as "back in
time"; the output resumes and its time never goes back."""

from __future__ import annotations

import os
import signal
import socket
import time

import numpy as np
import pytest

from sumhe.bench.live import live_drive, run_daemon

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not socket.has_ipv6, reason="needs IPv6 for the interface-local multicast group"),
]

STOP_AT_S, STOP_FOR_S = 8.0, 5.0


def test_a_5_s_sigstop_loses_no_gnss_epoch(tmp_path):
    sim, drive_dir = live_drive(24.0, tmp_path / "drive")
    stopped = []

    def stall(service, played_s: float) -> None:
        if played_s >= STOP_AT_S and not stopped:
            stopped.append(time.monotonic())
            os.kill(service.pid, signal.SIGSTOP)
            time.sleep(STOP_FOR_S)
            os.kill(service.pid, signal.SIGCONT)

    run = run_daemon(sim, drive_dir, tmp_path, "ekf", during=stall)
    status = run.status
    assert stopped and run.records, (tmp_path / "service.log").read_text()[-3000:]
    est = status["estimator"]
    gps = status["sources"]["gps"]
    assert status["stalls"] >= 1
    assert gps["restamped"] >= 10  # the epochs read at once after SIGCONT
    assert sum(est.get(k, 0) for k in ("dropped_backwards", "late_fixes", "fixes_after_missed")) <= 3
    t = np.array([r["t"] for r in run.records])
    assert np.all(np.diff(t) >= 0.0)
    after = np.array(run.arrived) > stopped[0] + STOP_FOR_S + 1.0
    assert after.sum() > 100, "the output resumed"
