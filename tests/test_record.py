import os
import threading
import time

import can
import pytest

from sumhe.cli import main
from sumhe.io.can import read_log
from sumhe.io.nmea import iter_fixes
from sumhe.io.nmea_format import format_gga, format_rmc

from canframes import speed_frame


@pytest.fixture
def pty_port():
    master, slave = os.openpty()
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


def _config(tmp_path, port: str, channel: str) -> str:
    path = tmp_path / "rec.toml"
    path.write_text(f'[can]\ninterface = "virtual"\nchannel = "{channel}"\n[gps]\nport = "{port}"\n')
    return str(path)


def test_record_writes_replayable_can_and_nmea_logs_on_one_clock(tmp_path, pty_port):
    master, port = pty_port
    channel = f"rec-{os.getpid()}"
    out = tmp_path / "out"
    result: list[int] = []
    worker = threading.Thread(
        target=lambda: result.append(
            main(["record", "--config", _config(tmp_path, port, channel), "--out", str(out), "--duration", "2.5"])
        )
    )
    worker.start()
    time.sleep(0.8)  # let both sources open
    sent_t = time.time()
    with can.Bus(interface="virtual", channel=channel) as bus:
        for i in range(20):
            bus.send(speed_frame(0.0, 50.0 + i, i))
            if i % 5 == 0:
                t = time.time()
                lines = [format_gga(t, 48.1, 11.5, 1, sats=9, hdop=0.9), format_rmc(t, 48.1, 11.5, speed_mps=14.0)]
                os.write(master, ("\r\n".join(lines) + "\r\n").encode())
            time.sleep(0.02)
        os.write(master, b"\x00\xffgarbage$GPGGA,bad*00\r\n")
    worker.join(10)
    assert result == [0]
    frames = list(read_log(out / "drive.log"))
    assert len(frames) == 20
    assert all(abs(f.timestamp - sent_t) < 5 for f in frames)  # CAN stamped on the Unix clock
    fixes = [f for f in iter_fixes(out / "drive.nmea") if f.valid]
    assert len(fixes) == 4
    assert all(abs(f.t - sent_t) < 5 for f in fixes)  # receive times on the same clock
    nmea_text = (out / "drive.nmea").read_bytes()
    assert nmea_text.startswith(b"(")  # receive-time prefix
    assert b"garbage" in nmea_text  # recorded as received: the decoder, not the recorder, judges lines


def test_record_refuses_to_record_nothing(tmp_path, capsys):
    assert (
        main(
            ["record", "--config", _config(tmp_path, "/dev/null", "x"), "--out", str(tmp_path), "--no-can", "--no-gps"]
        )
        == 1
    )
    assert "nothing to record" in capsys.readouterr().err


def test_record_with_bad_config_names_the_key(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text('[can]\ninterface = "nosuchbus"\n')
    assert main(["record", "--config", str(path), "--out", str(tmp_path), "--no-gps", "--duration", "0.1"]) == 1
    assert "can.interface" in capsys.readouterr().err
