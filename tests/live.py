"""Test helpers of the end-to-end tests (``test_e2e.py`` over udp_multicast, ``test_socketcan.py`` on vcan0):
the simulated drive with its faults, a UDP listener on 127.0.0.1, ``sumhe`` subprocesses, and the checks of what
arrived against the truth."""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pynmea2

from sumhe.io.nmea_format import format_gga, format_rmc
from sumhe.sim import SimSettings, simulate, write_drive

DURATION_S = 40.0
OUTAGE = (10.0, 6.0)
JUMP_AT_S = 22.0
SIGNALS = '[can.signals]\nspeed = "ESP_VEHICLE_SPEED.VEHICLE_SPEED"\nyaw_rate = "ESP_YAW_RATE.YAW_RATE"\n'


def jump(lines: list[str], t_lo: float, t_hi: float, metres: float) -> list[str]:
    """Move the GNSS position of the epochs received in [t_lo, t_hi) ``metres`` north (a multipath jump)."""
    out = []
    for line in lines:
        m = re.match(r"^\((\d+\.\d+)\) (.*)$", line)
        assert m
        t, text = float(m.group(1)), m.group(2)
        if t_lo <= t < t_hi and ("GGA" in text[:6] or "RMC" in text[:6]):
            msg = pynmea2.parse(text)
            lat = msg.latitude + metres / 111_200.0
            day = dt.datetime.fromtimestamp(t, dt.timezone.utc).date()
            fix_t = dt.datetime.combine(day, msg.timestamp.replace(tzinfo=dt.timezone.utc)).timestamp()
            if isinstance(msg, pynmea2.GGA):
                text = format_gga(fix_t, lat, msg.longitude, int(msg.gps_qual), sats=8, hdop=0.9)
            else:
                text = format_rmc(fix_t, lat, msg.longitude)
        out.append(f"({t:.6f}) {text}")
    return out


def make_drive(d: Path):
    """The 40 s urban drive: an outage of 6 s at 10 s, a 50 m GPS jump at 22 s; returns (dir, simulation)."""
    settings = SimSettings(scenario="urban", seed=11, duration_s=DURATION_S, outages=(OUTAGE,), outage_style="nofix")
    sim = simulate(settings)
    write_drive(sim, d)
    t0 = settings.start_unix_s
    lines = (d / "drive.nmea").read_text().splitlines()
    (d / "drive.nmea").write_text("\n".join(jump(lines, t0 + JUMP_AT_S, t0 + JUMP_AT_S + 0.1, 50.0)) + "\n")
    return d, sim


class Listener:
    """Receives sumhe's datagrams on 127.0.0.1: JSON estimates kept, the newest JSON status in ``status`` (the
    daemon sends its last one as it stops), NMEA forwarded to gpsd (when it runs)."""

    def __init__(self, forward_port: int | None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.json: list[dict] = []
        self.status: dict = {}
        self.nmea = 0
        self.forward_port = forward_port
        self._out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65535)
            except TimeoutError:
                continue
            if data.startswith(b"{"):
                obj = json.loads(data)
                if obj.get("class") == "STATUS":
                    self.status = obj
                else:
                    self.json.append(obj)
            else:
                self.nmea += 1
                if self.forward_port:
                    self._out.sendto(data, ("127.0.0.1", self.forward_port))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.sock.close()
        self._out.close()


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sumhe_process(*args: str, stderr_path: Path) -> subprocess.Popen:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "sumhe", "-v", *args],
        stdout=subprocess.DEVNULL,
        stderr=open(stderr_path, "w"),
        env=env,
    )


def wait_for(path: Path, text: str, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and text in path.read_text(errors="replace"):
            return True
        time.sleep(0.1)
    return False


def went_back(t: np.ndarray, records: list[dict], status: dict | None, svc_text: str) -> str:
    """Where the output's time went back (drive time), what the estimates around there said, the daemon's time
    counters and the log lines that tell why (a clock jump, a stall, a fall behind)."""
    back = np.flatnonzero(np.diff(t) < 0.0)
    around = [
        {k: records[j].get(k) for k in ("seq", "t", "gps", "mode", "window")} | {"drive_s": round(float(t[j]), 3)}
        for i in back[:3]
        for j in range(max(i - 1, 0), min(i + 2, len(t)))
    ]
    why = [
        line
        for line in svc_text.splitlines()
        if any(k in line for k in ("clock jump", "stall", "behind", "caught up", "dropped for their time"))
    ]
    return (
        f"output time went back {back.size} times (first at estimate {back[0]} of {len(t)}): {around}; "
        f"time counters {(status or {}).get('time')}; out_of_order {(status or {}).get('out_of_order')}; "
        f"log: {why[:20]}"
    )


def check_drive(
    records, code, stop_s, offset, sim, svc_text, max_stop_s: float = 2.0, emulated: bool = False, status=None
):
    """What arrived against the truth, for a daemon that kept real time, taken in the order it was sent (the
    datagrams' ``seq``: UDP may deliver them out of it).

    ``emulated`` (the CI virtual machine: Python 10 to 50 times slower on shared cores) asserts correctness, not
    real-time speed. There the daemon may fall behind real time and shed load as it is built to: degraded output
    (``degraded`` episodes; the MHE appends epochs unsolved) and, more than 10 s behind, drops samples as stale
    (``time.stale``; measured there: from 10 s behind at 30 s of the drive to about 10 s behind throughout, as the
    machine's load varies). Checked then: a second without an estimate only where the final ``status`` counts
    stale samples; the shedding logged, never silent. The estimates' GPS flags and errors against the truth are
    checked only where the daemon shed nothing: with most epochs unsolved they measure the machine, not sumhe; the
    SocketCAN data's flags and accuracy are checked by replaying its recording (``test_socketcan.py``)."""
    assert code == 0, svc_text[-3000:]
    assert stop_s < max_stop_s, f"SIGTERM took {stop_s:.2f} s"
    assert "sumhe stopped" in svc_text
    t0 = sim.settings.start_unix_s + offset
    seq = [r["seq"] for r in records]
    assert len(set(seq)) == len(seq), "a datagram number sent twice"
    records = sorted(records, key=lambda r: r["seq"])
    t = np.array([r["t"] for r in records]) - t0  # drive time of each estimate
    assert np.all(np.diff(t) >= 0.0), went_back(t, records, status, svc_text)
    gps = np.array([r["gps"] for r in records])
    assert (gps == "ok").any(), f"{len(records)} estimates, none on GPS"
    first_ok = t[gps == "ok"].min()
    # output rate >= 9 Hz in every second of the drive after the first fix, through every fault
    bins = np.arange(math.ceil(first_ok) + 1, DURATION_S - 1.0)
    counts = np.array([np.sum((t >= b) & (t < b + 1.0)) for b in bins])
    if emulated:
        status = status or {}
        stale, skipped = status.get("time", {}).get("stale", 0), status.get("degraded", 0)
        gaps = bins[counts == 0]
        assert not gaps.size or stale > 0, (
            f"seconds without an estimate {gaps.tolist()}; samples dropped as stale: {stale} (the daemon fell "
            f"{'more' if stale else 'less'} than 10 s behind real time)"
        )
        assert not skipped or "estimator behind" in svc_text
        assert not stale or "samples dropped for their time" in svc_text
        if stale or skipped:
            return
    else:
        assert counts.min() >= 9, dict(zip(bins.tolist(), counts.tolist(), strict=True))
    # gps flags: outage inside the outage, the 50 m jump rejected, ok again afterwards
    inside = (t > OUTAGE[0] + 0.3) & (t < OUTAGE[0] + OUTAGE[1] - 0.2)
    assert set(gps[inside]) == {"outage"}
    near_jump = (t > JUMP_AT_S - 0.2) & (t < JUMP_AT_S + 0.3)
    assert "rejected" in set(gps[near_jump])
    after = (t > OUTAGE[0] + OUTAGE[1] + 1.5) & (t < JUMP_AT_S - 0.5)
    assert set(gps[after]) == {"ok"}, [
        (round(float(a), 2), g) for a, g in zip(t[after], gps[after], strict=True) if g != "ok"
    ][:10]
    # errors against the truth
    frame = sim.frame
    enu = frame.to_enu(np.array([r["lat"] for r in records]), np.array([r["lon"] for r in records]), frame.alt0_m)
    at = sim.truth.at(t + sim.settings.start_unix_s)
    err = np.hypot(enu[:, 0] - at.east, enu[:, 1] - at.north)
    steady = (t > first_ok + 3) & ~inside & ~near_jump
    assert np.mean(err[steady & (gps == "ok")]) < 2.5
    assert np.max(err[inside]) < 12.0
    assert np.max(err[near_jump], initial=0.0) < 5.0, "one 50 m jump must not pull the estimate"
    # every datagram carries the error estimates, the MHE's its SU bound too; both grow through the outage
    assert all({"eph", "epx", "epy", "eps", "epd"} <= r.keys() for r in records), records[0]
    assert all("bound_east" in r and "bound_north" in r for r in records), records[0]
    eph, bound = np.array([r["eph"] for r in records]), np.array([r["bound_east"] for r in records])
    ok_steady = steady & (gps == "ok")
    order = np.argsort(t[inside])
    for name, values in (("eph", eph), ("bound_east", bound)):
        grown = values[inside][order]
        assert grown[-1] > grown[0] and grown[-1] > np.median(values[ok_steady]), (name, grown[[0, -1]])
