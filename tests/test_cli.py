"""The command line as a user meets it: the daemon's messages at the default log level, start-up errors, flags
after the command, ``sumhe listen`` and ``sumhe can-up``. Real processes, a real pty, UDP on 127.0.0.1."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sumhe.cli import main
from sumhe.io.player import Pty
from sumhe.io.udp import encode_nmea
from sumhe.messages import Estimate

from vcan import kernel_has_socketcan

REPO = Path(__file__).resolve().parents[1]
SIGNALS = '[can.signals]\nspeed = "ESP_VEHICLE_SPEED.VEHICLE_SPEED"\nyaw_rate = "ESP_YAW_RATE.YAW_RATE"\n'


def _sumhe(*args: str, env: dict[str, str] | None = None, **kw) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "sumhe", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", **(env or {})},
        **kw,
    )


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def _daemon(tmp_path: Path, channel: str) -> Iterator[tuple[subprocess.Popen, socket.socket]]:
    """``sumhe run`` on a virtual bus and a pty receiver that stay silent, its JSON status every 0.5 s to the
    socket given; killed and closed after the block if still running."""
    pty = Pty(tmp_path / "gps")
    status_rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    status_rx.bind(("127.0.0.1", 0))
    status_rx.settimeout(10)
    config = tmp_path / "c.toml"
    config.write_text(
        f'[can]\ninterface = "virtual"\nchannel = "{channel}"\n{SIGNALS}[gps]\nport = "{tmp_path / "gps"}"\n'
        f'[output]\njson = ["127.0.0.1:{_free_udp_port()}"]\nstatus_interval_s = 0.5\n'
        f'status_udp = "127.0.0.1:{status_rx.getsockname()[1]}"\n'
    )
    proc = _sumhe("run", "--config", str(config))
    try:
        yield proc, status_rx
    finally:
        if proc.poll() is None:
            proc.kill()
        pty.close()
        status_rx.close()


@pytest.mark.slow
def test_the_daemon_says_starting_ready_status_and_stopped_at_the_default_level(tmp_path):
    """No ``-v``: the lifecycle lines show; a CAN bus with no traffic and a receiver that says nothing are warned
    about; SIGTERM stops it with exit 0 and a stopped line with the counters."""
    with _daemon(tmp_path, "sumhe-cli-test") as (proc, status_rx):
        status = json.loads(status_rx.recv(65535))
        time.sleep(0.6)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert status["class"] == "STATUS" and status["sources"]["can"]["connected"] is True
    assert {"fd_frames", "error_frames", "reconnects"} <= set(status["sources"]["can"])
    lines = err.splitlines()
    starting = "sumhe starting (version 0.1.0): estimator mhe; reading can virtual sumhe-cli-test"
    order = [starting, "sumhe ready:", "status:"]
    found = [next(i for i, line in enumerate(lines) if want in line) for want in order]
    assert found == sorted(found), err
    assert re.search(r"sumhe stopped after \d+\.\d s: can=0Hz gps=0Hz fix=no fix yet", err)
    assert "config: {" in err, "the resolved config is logged once"
    assert "can: nothing received" in err


def test_a_config_without_yaw_rate_stops_at_start_up_with_the_key(tmp_path, capsys):
    config = tmp_path / "c.toml"
    config.write_text('[can]\ninterface = "virtual"\n[can.signals]\nspeed = "ESP_VEHICLE_SPEED.VEHICLE_SPEED"\n')
    assert main(["run", "--config", str(config)]) == 1
    assert f"error: {config}: can.signals.yaw_rate: not mapped" in capsys.readouterr().err


@pytest.mark.socketcan
def test_a_socketcan_interface_that_cannot_be_opened_exits_1_naming_it_with_the_fix(tmp_path, monkeypatch, capsys):
    """The default config here (no AF_CAN) and in the CI virtual machine (vcan97 does not exist): both permanent.
    The EKF: building the MHE's solvers takes minutes under emulation, and the estimator is not what is tested. In
    this process: a new one's start-up takes a minute under emulation."""
    monkeypatch.setenv("SUMHE_CAN__CHANNEL", "vcan97")
    monkeypatch.setenv("SUMHE_GPS__PORT", str(tmp_path / "no-gps"))
    monkeypatch.setenv("SUMHE_ESTIMATOR__NAME", "ekf")
    assert main(["run", "--config", str(REPO / "configs" / "default.toml")]) == 1
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert last.startswith("error: can: cannot use socketcan channel 'vcan97': ")
    fix = "ip link add dev vcan97 type vcan" if kernel_has_socketcan() else "no SocketCAN (AF_CAN)"
    assert fix in last
    assert "sumhe stopped" in err


def test_verbose_and_debug_are_accepted_after_the_command(tmp_path, capsys):
    log = tmp_path / "x.nmea"
    log.write_text("$GPGGA,080000.00,5004.5301720,N,01426.2670152,E,1,11,0.95,206.255,M,45.000,M,,*58\n")
    date = ["--date", "2026-06-01"]
    assert main(["nmea", str(log), *date, "-v"]) == 0
    assert main(["nmea", "--debug", str(log), *date]) == 0
    assert main(["-v", "nmea", str(log), *date]) == 0
    out = capsys.readouterr().out
    assert out.count('"lat": 50.07550286666667') == 3


def _send(port: int, payloads: list[bytes]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for p in payloads:
            s.sendto(p, ("127.0.0.1", port))
            time.sleep(0.05)


def test_listen_prints_positions_from_json_and_nmea():
    json_port, nmea_port = _free_udp_port(), _free_udp_port()
    proc = _sumhe("listen", f"127.0.0.1:{json_port}", f"127.0.0.1:{nmea_port}", "--every", "0", "--count", "3")
    try:
        assert "listening on" in proc.stderr.readline()
        tpv = {"class": "TPV", "t": 1780300800.25, "lat": 50.0755, "lon": 14.4378, "alt": 206.3, "speed": 13.9}
        _send(json_port, [b"not json", json.dumps({**tpv, "track": 271.5, "gps": "ok", "mode": "mhe"}).encode()])
        dead_reckoning = Estimate(
            1780300801.0, 0.0, 0.0, 50.0755, 14.4378, 206.3, 0.5 * math.pi, 13.9, 0.0, "outage", "mhe"
        )
        _send(nmea_port, [encode_nmea(dead_reckoning), json.dumps({**tpv, "gps": "outage", "mode": "can"}).encode()])
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    lines = out.splitlines()
    assert len(lines) == 3
    assert lines[0].startswith("08:00:00.2Z  lat 50.0755000 lon 14.4378000 alt 206.3 m  speed 13.90 m/s  track 271.5")
    assert f"gps ok  mode mhe  [127.0.0.1:{json_port}, 1 datagrams]" in lines[0]
    assert lines[1].startswith("08:00:01.0Z  lat 50.0755000 lon 14.4378000 alt 206.3 m  speed 13.90 m/s  track 90.0")
    assert "gps outage  mode nmea (dead reckoning)" in lines[1]
    assert "gps outage  mode can" in lines[2]
    assert "3 datagrams with a position" in err


def test_listen_takes_the_highest_seq_as_the_newest_and_counts_lost_and_overtaken_datagrams():
    """Datagrams 0 and 3 of one daemon, then 0, 2, 5, 4 of the daemon started again: 1, 2, 1, 3 lost and 4
    overtaken, which fills its gap and is not shown as the newest position (the last line is datagram 5's)."""
    port = _free_udp_port()
    proc = _sumhe("listen", f"127.0.0.1:{port}", "--every", "60", "--count", "6")
    try:
        assert "listening on" in proc.stderr.readline()
        tpv = {"class": "TPV", "t": 1780300800.0, "lon": 14.4378, "gps": "ok", "mode": "mhe"}
        numbers = [(0, 50.0), (3, 50.3), (0, 51.0), (2, 51.2), (5, 51.5), (4, 51.4)]
        _send(port, [json.dumps({**tpv, "lat": lat, "seq": seq}).encode() for seq, lat in numbers])
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    first, last = out.splitlines()  # the first datagram's line at once, then the newest at the count
    assert first.startswith("08:00:00.0Z  lat 50.0000000") and last.startswith("08:00:00.0Z  lat 51.5000000")
    assert last.endswith(", 5 datagrams]")
    assert "6 datagrams with a position (4 lost, 1 out of order by their seq, 0 repeated)" in err


def test_numbering_counts_gaps_filled_later_and_repeats_apart():
    from sumhe.commands.listen import REMEMBERED, Numbering

    n = Numbering()
    assert [n.see(k) for k in (0, 3, 1, 3, 1, 0, 2)] == [True, True, False, False, False, True, True]
    # 1 filled one of the two gaps; 3 and 1 again are repeats, which neither fill a gap nor count as overtaken;
    # after the restart at 0, 1 is lost again and 2 (a number seen before the restart) is new
    assert (n.top, n.lost, n.overtaken, n.repeated) == (2, 2, 1, 2)
    assert not n.see(1) and (n.lost, n.overtaken, n.missing) == (1, 2, set())
    # a gap longer than the numbers remembered: the oldest missing ones, if they come, count as repeats
    n.see(2 + 3 * REMEMBERED)
    assert n.lost == 1 + 3 * REMEMBERED - 1 and len(n.missing) == REMEMBERED
    assert not n.see(3) and n.repeated == 3 and not n.see(2 + 3 * REMEMBERED - 1) and n.overtaken == 3


def test_can_up_prints_the_commands_from_the_config(tmp_path, capsys):
    assert main(["can-up", "--config", str(REPO / "configs" / "default.toml"), "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    if not Path("/sys/class/net/vcan0").exists():
        assert out == ["modprobe vcan", "ip link add dev vcan0 type vcan", "ip link set up vcan0"]
    real = tmp_path / "can.toml"
    real.write_text('[can]\nchannel = "can7"\n')
    assert main(["can-up", "--config", str(real), "--dry-run"]) == 1
    assert f"error: {real}: can.bitrate: needed to bring up can7" in capsys.readouterr().err
    real.write_text('[can]\nchannel = "can7"\nbitrate = 250000\n')
    assert main(["can-up", "--config", str(real), "--dry-run"]) == 1
    assert "can7: no such interface: plug in the adapter" in capsys.readouterr().err
    other = tmp_path / "pcan.toml"
    other.write_text('[can]\ninterface = "pcan"\nchannel = "PCAN_USBBUS1"\n')
    assert main(["can-up", "--config", str(other)]) == 0
    assert "nothing to bring up" in capsys.readouterr().err


def test_link_commands_for_real_and_virtual_interfaces():
    from sumhe.io.can_source import link_commands

    assert link_commands("vcan1", 0, exists=True, up=False) == [["ip", "link", "set", "up", "vcan1"]]
    assert link_commands("vcan1", 0, exists=True, up=True) == []
    assert link_commands("can0", 500000, exists=True, up=True) == [
        ["ip", "link", "set", "can0", "down"],
        ["ip", "link", "set", "can0", "up", "type", "can", "bitrate", "500000", "restart-ms", "100"],
    ]


@pytest.mark.slow
def test_sighup_stops_the_daemon_cleanly_with_the_stopped_line(tmp_path):
    """SIGHUP (the terminal hung up) stops the daemon as SIGTERM does: exit 0 and the stopped line (it used to kill
    it with exit 129 and no line); it does not re-read the config (README)."""
    with _daemon(tmp_path, "sumhe-sighup-test") as (proc, status_rx):
        status_rx.recv(65535)  # running
        proc.send_signal(signal.SIGHUP)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert re.search(r"sumhe stopped after \d+\.\d s:", err), err


def _python_can_mf4(argv: list[str]) -> str:
    """In a fresh interpreter: ``skip_mf4_reader(argv)``, then whether python-can's MF4 reader has asammdf and
    whether asammdf can still be imported afterwards."""
    code = (
        "import sys; from sumhe.cli import skip_mf4_reader; skip_mf4_reader(sys.argv[1:]); import can.io.mf4; "
        "import importlib.util; print(can.io.mf4.asammdf is not None, importlib.util.find_spec('asammdf') is not None)"
    )
    run = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, check=True)
    return run.stdout.strip()


def test_the_live_commands_and_a_replay_of_candump_logs_load_python_can_without_its_mf4_reader_others_with_it():
    pytest.importorskip("asammdf")
    assert _python_can_mf4(["-v", "replay", "drive.log", "--nmea", "drive.nmea"]) == "False True"
    assert _python_can_mf4(["replay", "a.log", "b.MF4"]) == "True True"
    assert _python_can_mf4(["run", "--config", "x.toml"]) == "False True"
    assert _python_can_mf4(["can-up", "--config", "x.toml"]) == "False True"
    assert _python_can_mf4(["bench", "--drive", "folder"]) == "True True"
    assert _python_can_mf4(["fleet", "d1", "--out", "o"]) == "True True"


def _ends(code: str, **kw) -> subprocess.CompletedProcess:
    """``code`` run after ``from sumhe.cli import end_process`` in a fresh interpreter, its outputs piped."""
    return subprocess.run(
        [sys.executable, "-c", f"import logging, sys; from sumhe.cli import end_process; {code}"],
        **({"capture_output": True} if not kw else {}),
        text=True,
        timeout=60,
        **kw,
    )


def test_end_process_exits_with_the_code_after_flushing_the_streams_and_the_log():
    run = _ends("logging.basicConfig(); sys.stdout.write('out'); logging.warning('said'); end_process(3)")
    assert (run.returncode, run.stdout) == (3, "out")
    assert "WARNING:root:said" in run.stderr
    run = _ends("import atexit; atexit.register(print, 'teardown'); end_process(0)")
    assert (run.returncode, run.stdout) == (0, "")  # no atexit handler but logging's runs


def test_end_process_takes_a_reader_gone_for_no_error():
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the text still buffered is flushed
    try:
        buffered = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}  # kept until end_process
        run = _ends("sys.stdout.write('lost'); end_process(0)", stdout=write, stderr=subprocess.PIPE, env=buffered)
    finally:
        os.close(write)
    assert (run.returncode, run.stderr) == (0, "")


def test_the_script_ends_a_replay_at_once_with_every_line_written_and_its_exit_code(tmp_path):
    drive = REPO / "sumhe" / "data" / "drive"
    proc = _sumhe("replay", str(drive / "drive.log"), "--nmea", str(drive / "drive.nmea"))
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    lines = out.splitlines()
    assert len(lines) == 12602 and out.endswith("}\n")
    assert json.loads(lines[-1])["class"] == "TPV"
    assert re.search(r"^replay: mhe: 2101 fixes \(1651 valid\), 31502 CAN samples, 12602 estimates", err), err
    (tmp_path / "none.nmea").write_text("$GPGGA,080000.00,,,,,0,00,,,M,,M,,*6A\n")
    proc = _sumhe("replay", str(drive / "drive.log"), "--nmea", str(tmp_path / "none.nmea"))
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 1 and "error: nothing to estimate from" in err, err
