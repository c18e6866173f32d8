"""End to end, real processes and sockets: a player process puts a simulated drive on the CAN bus (python-can
``udp_multicast`` on an interface-local IPv6 group, so nothing leaves the machine) and the NMEA into a pty at real
time; ``sumhe run`` runs as a subprocess; this test listens on 127.0.0.1 for the JSON, and a real gpsd reads
sumhe's NMEA. Faults on the way: a 50 m GPS jump, the pty closed and reopened, CAN silent for 3 s."""

from __future__ import annotations

import datetime as dt
import json
import math
import re
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from sumhe.bench.live import free_multicast_port, multicast_can_table

from live import DURATION_S, SIGNALS, Listener, check_drive, free_port, make_drive, sumhe_process, wait_for

pytestmark = pytest.mark.slow

GROUP = "ff11:7079:7468:6f6e:6465:6d6f:6d63:6173"  # interface-local: never leaves this machine
PTY_REOPEN_AT_S = 25.0
CAN_SILENCE = (30.0, 3.0)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    return make_drive(tmp_path_factory.mktemp("drive"))


def _configs(tmp: Path, udp_port: int, latency: float) -> tuple[Path, Path]:
    can_table = multicast_can_table(GROUP, free_multicast_port())  # a port of its own: other runs do not hear it
    service = tmp / "service.toml"
    dest = f'["127.0.0.1:{udp_port}"]'
    service.write_text(
        f'{can_table}e2e = ["ESP_YAW_RATE", "ESP_VEHICLE_SPEED"]\n{SIGNALS}'
        f'[gps]\nport = "{tmp / "gps"}"\nlatency_s = {latency}\nreconnect_max_s = 0.5\nreceive_timeout_s = 1.0\n'
        f"[output]\njson = {dest}\nnmea = {dest}\nstatus_interval_s = 2.0\n"
    )
    player = tmp / "player.toml"
    player.write_text(can_table)
    return service, player


def _gpsd(tmp: Path) -> tuple[subprocess.Popen | None, int | None, int | None]:
    if shutil.which("gpsd") is None or shutil.which("gpspipe") is None:
        return None, None, None
    udp_in, tcp_port = free_port(), free_port(socket.SOCK_STREAM)
    proc = subprocess.Popen(
        ["gpsd", "-N", "-n", "-S", str(tcp_port), "-F", str(tmp / "gpsd.sock"), f"udp://127.0.0.1:{udp_in}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return proc, udp_in, tcp_port


def _run_drive(drive, tmp: Path, with_gpsd: bool):
    drive_dir, sim = drive
    gpsd, gpsd_udp, gpsd_tcp = _gpsd(tmp) if with_gpsd else (None, None, None)
    listener = Listener(gpsd_udp)
    latency = sim.settings.gps_latency_s + sim.settings.gps_latency_jitter_s / 2
    service_cfg, player_cfg = _configs(tmp, listener.port, latency)
    svc_log, player_log = tmp / "service.log", tmp / "player.log"
    service = sumhe_process("run", "--config", str(service_cfg), stderr_path=svc_log)
    gpspipe_out: list[str] = []
    try:
        assert wait_for(svc_log, "sumhe starting", 60), svc_log.read_text()
        player = sumhe_process(
            "play",
            str(drive_dir),
            "--config",
            str(player_cfg),
            "--pty",
            str(tmp / "gps"),
            "--reopen-pty-at",
            str(PTY_REOPEN_AT_S),
            "--can-silence",
            f"{CAN_SILENCE[0]}+{CAN_SILENCE[1]}",
            stderr_path=player_log,
        )
        pipe = None
        if gpsd is not None:
            pipe = subprocess.Popen(
                ["gpspipe", "-w", f"127.0.0.1:{gpsd_tcp}"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
            )
            threading.Thread(target=lambda: gpspipe_out.extend(pipe.stdout), daemon=True).start()
        assert player.wait(DURATION_S + 30) == 0, player_log.read_text()
        time.sleep(1.0)
        service.send_signal(signal.SIGTERM)
        t_term = time.monotonic()
        code = service.wait(10)
        stop_s = time.monotonic() - t_term
        if pipe is not None:
            pipe.terminate()
            pipe.wait(5)
    finally:
        if service.poll() is None:
            service.kill()
        if gpsd is not None:
            gpsd.terminate()
            gpsd.wait(5)
        listener.close()
    offset = float(re.search(r"clock offset (-?\d+\.\d+) s", player_log.read_text()).group(1))
    return listener.json, code, stop_s, offset, gpspipe_out, svc_log.read_text()


@pytest.mark.skipif(not socket.has_ipv6, reason="needs IPv6 for the interface-local multicast group")
def test_live_drive_over_udp_multicast_with_faults_and_gpsd(drive, tmp_path):
    records, code, stop_s, offset, gpspipe, svc_text = _run_drive(drive, tmp_path, with_gpsd=True)
    check_drive(records, code, stop_s, offset, drive[1], svc_text)
    if shutil.which("gpsd") is None:
        pytest.skip("gpsd is not installed: the gpsd client check did not run (apt-get install gpsd gpsd-clients)")
    tpv = [json.loads(line) for line in gpspipe if '"class":"TPV"' in line]
    with_pos = [m for m in tpv if "lat" in m]
    assert len(with_pos) > 50, f"gpsd reported {len(tpv)} TPV"
    dr = [m for m in with_pos if m.get("status") == 5]  # gpsd's STATUS_DR: from GGA quality 6 / RMC mode E
    assert dr, "gpsd saw the dead-reckoning status during the outage"
    ours: dict[float, list[dict]] = {}
    for r in records:  # NMEA carries the time to 0.01 s: several estimates may share it
        ours.setdefault(round(r["t"], 2), []).append(r)
    matched = 0
    # gpsd's first report may come before it has read a date (RMC): a TPV without time
    assert sum("time" not in m for m in with_pos) <= 1
    for m in (m for m in with_pos if "time" in m):
        when = dt.datetime.fromisoformat(m["time"].replace("Z", "+00:00")).timestamp()
        # an estimate on a half-centisecond may round into the next bin here and not in the NMEA formatter
        candidates = [r for k in (-1, 0, 1) for r in ours.get(round(when + 0.01 * k, 2), [])]
        if ours.get(round(when, 2)):
            matched += 1
            gap = min(math.hypot(m["lat"] - r["lat"], m["lon"] - r["lon"]) for r in candidates)
            assert gap < 1e-6, f"gpsd's TPV at {m['time']} matches none of sumhe's estimates at that time"
    assert matched > 0.5 * len(with_pos)
    # the error estimates reach a gpsd client: gpsd's TPV carries eph (gpsd 3.22 makes it from the GGA's HDOP, which
    # sumhe grows with its own error estimate through an outage), and it grows in the outage over what it was
    with_eph = [m for m in with_pos if "eph" in m]
    assert len(with_eph) > 0.9 * len(with_pos), f"gpsd's TPV without eph: {with_pos[0]}"
    eph_dr = [m["eph"] for m in with_eph if m.get("status") == 5]
    first_dr = next((i for i, m in enumerate(with_eph) if m.get("status") == 5), len(with_eph))
    eph_gps = [m["eph"] for m in with_eph[:first_dr]]
    assert eph_dr and eph_gps and max(eph_dr) > max(eph_gps) > 0
