import asyncio
import time

import can
import pytest

from sumhe.config import GpsSettings
from sumhe.io.nmea_format import format_gga, format_rmc
from sumhe.io.player import Player, Pty, TcpNmeaServer, TimedLine, read_nmea_log
from sumhe.io.serial import SerialNmeaSource
from sumhe.io.source import SourceTimeout

T0 = 1780300800.0


def _lines(n: int, t0: float = T0) -> list[TimedLine]:
    out = []
    for i in range(n):
        t = t0 + 0.1 * i
        out.append(TimedLine(t + 0.05, format_gga(t, 50.0 + i * 1e-6, 14.4, 1, sats=9, hdop=0.8).encode()))
        out.append(TimedLine(t + 0.06, format_rmc(t, 50.0 + i * 1e-6, 14.4, speed_mps=5.0).encode()))
    return out


async def _collect(source: SerialNmeaSource, n: int, timeout_s: float = 5.0) -> list:
    """Up to ``n`` fixes from a running source, waiting at most ``timeout_s``."""
    out = []
    end = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < end:
        try:
            out.append(await anext(source))
        except SourceTimeout:
            continue
    return out


def test_read_nmea_log_keeps_prefixed_lines_only(tmp_path):
    p = tmp_path / "d.nmea"
    p.write_bytes(b"(1.5) $GPGGA,x*00\r\n$GPRMC,no-prefix*00\r\n(2.25) $GPRMC,y*00\n")
    assert read_nmea_log(p) == [TimedLine(1.5, b"$GPGGA,x*00"), TimedLine(2.25, b"$GPRMC,y*00")]


def test_player_paces_and_restamps_can_frames_on_the_service_clock():
    channel = "player-test"
    frames = [can.Message(timestamp=T0 + 0.05 * i, arbitration_id=0x1A0, data=bytes(8)) for i in range(10)]
    with (
        can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as tx,
        can.Bus(interface="virtual", channel=channel) as rx,
    ):
        player = Player(frames, [], tx, None, speed=5.0, clock=lambda: 1000.0)
        start = time.monotonic()
        player.run()
        elapsed = time.monotonic() - start
        got = [rx.recv(1) for _ in range(10)]
    assert elapsed >= 0.45 / 5.0 * 0.9  # 0.45 s of drive at 5x
    assert [m.timestamp for m in got] == pytest.approx([1000.0 + 0.05 * i for i in range(10)])
    assert player.sent_frames == 10


def test_pty_reopen_keeps_the_link_and_the_reader_resumes(tmp_path):
    link = tmp_path / "gps"
    pty = Pty(link)
    settings = GpsSettings(port=str(link), receive_timeout_s=0.3, reconnect_max_s=0.2)

    async def scenario() -> list:
        source = SerialNmeaSource(settings)
        got = []
        async with source:
            await asyncio.sleep(0.3)
            for line in _lines(3):
                pty.write(line.raw + b"\r\n")
            got += await _collect(source, 3)
            pty.close()
            pty.open()  # the receiver is plugged back in at the same path
            await asyncio.sleep(1.0)
            for line in _lines(3, T0 + 10):
                pty.write(line.raw + b"\r\n")
            got += await _collect(source, 3)
        return got

    try:
        fixes = asyncio.run(scenario())
    finally:
        pty.close()
    assert link.is_symlink()
    assert len(fixes) == 6 and all(f.valid for f in fixes)
    assert fixes[-1].lat_deg == pytest.approx(50.0 + 2e-6)


def test_nmea_over_tcp_is_read_through_a_socket_url():
    server = TcpNmeaServer("127.0.0.1", 0)
    host, port = server.address
    settings = GpsSettings(port=f"socket://{host}:{port}", receive_timeout_s=0.3, reconnect_max_s=0.2)

    async def scenario() -> list:
        source = SerialNmeaSource(settings)
        async with source:
            await asyncio.sleep(0.5)  # connect
            for line in _lines(4):
                server.write(line.raw + b"\r\n")
            return await _collect(source, 4)

    try:
        fixes = asyncio.run(scenario())
    finally:
        server.close()
    assert len(fixes) == 4
    assert fixes[0].speed_mps == pytest.approx(5.0, abs=0.01)


def test_player_rejects_a_bad_speed():
    with pytest.raises(ValueError, match="speed"):
        Player([], [], None, None, speed=0)
