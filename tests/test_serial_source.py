"""The serial GNSS sources on a real pseudo-terminal: pyserial opens the slave, the test writes NMEA to the master."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import time
import tty
from pathlib import Path

import pynmea2
import pytest

from sumhe.config import GpsSettings
from sumhe.errors import ConfigError
from sumhe.io.serial import NmeaLine, SerialLineSource, SerialNmeaSource
from sumhe.io.source import SourceTimeout


def nmea(body: str) -> bytes:
    return f"${body}*{pynmea2.NMEASentence.checksum(body):02X}\r\n".encode()


def epoch(second: int) -> bytes:
    """GGA and RMC of 12:00:<second> on 17 May 2024 at 48.1173 N, 11.5167 E, 10 kn on 84.4 deg."""
    t = f"1200{second:02d}.00"
    return nmea(f"GPGGA,{t},4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") + nmea(
        f"GPRMC,{t},A,4807.038,N,01131.000,E,10.0,84.4,170524,3.1,W,A"
    )


class Pty:
    """A pseudo-terminal; ``path`` is the slave device pyserial opens."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation before pyserial configures the port
        self.path = os.ttyname(self.slave)

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    def open_fds(self) -> int:
        """How many of this process's file descriptors are open on the slave device."""
        n = 0
        for fd in os.listdir("/proc/self/fd"):
            with contextlib.suppress(OSError):
                n += os.readlink(f"/proc/self/fd/{fd}") == self.path
        return n


@pytest.fixture
def pty():
    p = Pty()
    yield p
    p.close()


def settings(port: str, **kw) -> GpsSettings:
    kw.setdefault("receive_timeout_s", 3.0)
    kw.setdefault("reconnect_max_s", 0.2)
    return GpsSettings(port=port, baudrate=115200, **kw)


def run(coro, timeout_s: float = 20.0):
    async def bounded():
        return await asyncio.wait_for(coro, timeout_s)

    return asyncio.run(bounded())


async def until(predicate, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)


def test_fixes_arrive_with_their_values_and_receive_time_after_an_idle_gap(pty):
    async def main():
        async with SerialNmeaSource(settings(pty.path)) as source:
            await until(lambda: source.stats.connected)
            before = time.time()
            pty.write(epoch(0))
            fix = await anext(source)
            after = time.time()
            assert before <= fix.t <= after
            assert fix.valid and fix.time_utc.isoformat() == "2024-05-17T12:00:00+00:00"
            assert fix.lat_deg == pytest.approx(48 + 7.038 / 60, abs=1e-12)
            assert fix.lon_deg == pytest.approx(11 + 31 / 60, abs=1e-12)
            assert (fix.alt_m, fix.sats, fix.hdop) == (545.4, 8, 0.9)
            assert fix.speed_mps == pytest.approx(10 * 1852 / 3600)
            pty.write(epoch(1) + epoch(2))  # one burst: epoch 1 ends when epoch 2 starts, epoch 2 on the idle gap
            assert [(await anext(source)).time_utc.second for _ in range(2)] == [1, 2]
            assert source.decoder.counters.fixes == 3

    run(main())


def test_receive_timeout_raises_and_iteration_continues(pty):
    async def main():
        async with SerialNmeaSource(settings(pty.path, receive_timeout_s=0.3)) as source:
            await until(lambda: source.stats.connected)
            with pytest.raises(SourceTimeout):
                await anext(source)
            pty.write(epoch(0))
            fix = await anext(source)
            assert fix.valid and fix.time_utc.second == 0

    run(main())


def test_garbage_on_the_line_is_counted_not_fatal(pty, caplog):
    async def main():
        async with SerialNmeaSource(settings(pty.path), report_every_s=0.0) as source:
            await until(lambda: source.stats.connected)
            bad_checksum = epoch(0).replace(b"545.4", b"545.5", 1)  # the GGA of epoch 0 no longer matches its *hh
            pty.write(b"\xb5b\x01\x07\x5c\x00\x80\xff\xfe\r\n" + bad_checksum + b"\x00\x00$GPGG\r\n")
            pty.write(epoch(1))
            first, second = await anext(source), await anext(source)
            assert first.valid and first.time_utc.second == 0 and first.alt_m is None  # from its RMC alone
            assert second.valid and second.time_utc.second == 1 and second.alt_m == 545.4
            c = source.decoder.counters
            assert (c.sentences, c.checksum_errors, c.garbled) == (3, 1, 2)
            assert source.stats.errors == 0 and source.stats.reconnects == 0
            await until(lambda: "bad NMEA input so far" in caplog.text)  # the periodic summary

    run(main())


def test_a_replugged_device_is_reopened_and_fixes_resume(tmp_path: Path):
    """The port is a symlink (like a udev name) re-pointed at a new pseudo-terminal after the old one vanished."""
    first, second = Pty(), None
    link = tmp_path / "gps"
    link.symlink_to(first.path)

    async def feed(p: Pty, stop: asyncio.Event) -> None:
        second_of_minute = 10
        while not stop.is_set():
            with contextlib.suppress(OSError):
                p.write(epoch(second_of_minute % 60))
            second_of_minute += 1
            await asyncio.sleep(0.1)

    async def main():
        nonlocal second
        async with SerialNmeaSource(settings(str(link))) as source:
            await until(lambda: source.stats.connected)
            first.write(epoch(0))
            assert (await anext(source)).time_utc.second == 0
            first.close()  # unplugged: reads fail with EIO / end of file
            await until(lambda: source.stats.reconnects >= 1)
            second = Pty()
            fresh = tmp_path / "gps.new"
            fresh.symlink_to(second.path)
            fresh.replace(link)
            stop = asyncio.Event()
            writer = asyncio.create_task(feed(second, stop))
            try:
                fix = await anext(source)
            finally:
                stop.set()
                await writer
            assert fix.valid and fix.time_utc.second >= 10
            assert source.stats.connected and source.stats.reconnects >= 1
            assert second.open_fds() == 2  # the test's slave fd and the source's

    try:
        run(main())
    finally:
        first.close()
        if second is not None:
            second.close()


def test_a_port_that_is_absent_at_start_is_opened_when_it_appears(tmp_path: Path, pty):
    link = tmp_path / "gps"

    async def main():
        async with SerialNmeaSource(settings(str(link))) as source:
            await until(lambda: source.stats.errors >= 2)
            assert not source.stats.connected and "open" in source.stats.last_error
            link.symlink_to(pty.path)
            await until(lambda: source.stats.connected)
            pty.write(epoch(5))
            assert (await anext(source)).time_utc.second == 5

    run(main())


def test_async_with_closes_the_port(pty):
    async def main():
        baseline = pty.open_fds()
        async with SerialNmeaSource(settings(pty.path)) as source:
            await until(lambda: source.stats.connected)
            assert pty.open_fds() == baseline + 1
        assert pty.open_fds() == baseline
        assert not source.port.is_open

    run(main())


def test_the_line_source_yields_raw_lines_with_receive_times(pty):
    async def main():
        async with SerialLineSource(settings(pty.path)) as source:
            await until(lambda: source.stats.connected)
            before = time.time()
            pty.write(b"$GPTXT,hello*00\r\r\n\r\nsecond line\rthird")
            lines = [await anext(source) for _ in range(3)]
            assert [line.raw for line in lines] == [b"$GPTXT,hello*00", b"second line", b"third"]
            assert all(isinstance(line, NmeaLine) and before <= line.t <= time.time() for line in lines)

    run(main())


def test_a_gps_without_a_port_is_a_config_error():
    with pytest.raises(ConfigError, match=r"gps\.port"):
        SerialNmeaSource(GpsSettings(port=None))


def epoch_at(tenths: int) -> bytes:
    """GGA and RMC of 12:00:00 + ``tenths`` tenths of a second on 17 May 2024 (the position of :func:`epoch`)."""
    t = f"1200{tenths // 10:02d}.{tenths % 10}0"
    return nmea(f"GPGGA,{t},4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") + nmea(
        f"GPRMC,{t},A,4807.038,N,01131.000,E,10.0,84.4,170524,3.1,W,A"
    )


def test_a_fix_read_with_the_next_epochs_lines_is_stamped_before_it(pty):
    """Two epochs read at once before the decoder knows the receiver's last sentence: the first is emitted on the
    second's first line, the second on the idle gap after them, one read later. The first is stamped from its UTC
    time, not with their common read time, which the second then had too (dropped as not newer: the backlog check
    failed so in a loaded CI run)."""

    async def main():
        async with SerialNmeaSource(settings(pty.path)) as source:
            await until(lambda: source.stats.connected)
            live = []
            start = time.monotonic()
            for k in range(3):
                await asyncio.sleep(max(0.0, start + 0.1 * k - time.monotonic()))
                pty.write(epoch_at(k))
                live.append(await anext(source))
            await asyncio.sleep(max(0.0, start + 0.5 - time.monotonic()))
            pty.write(epoch_at(3) + epoch_at(4))
            first, second = await anext(source), await anext(source)
            assert first.t < second.t
            if source.receive_times.restamped:  # else the reader saw them apart (a loaded machine)
                lowest = min(f.t - f.time_utc.timestamp() for f in live)
                assert first.t == pytest.approx(first.time_utc.timestamp() + lowest, abs=0.01)

    run(main())


def test_epochs_read_from_a_backlog_are_stamped_from_their_utc_time(pty):
    """A stall: 15 epochs the receiver sent over 1.5 s are read at once. Read times alone would give them one time
    (all but one then dropped as back in time); they get their UTC time plus the quickest offset seen before."""

    async def main():
        async with SerialNmeaSource(settings(pty.path)) as source:
            await until(lambda: source.stats.connected)
            live = []
            start = time.monotonic()
            for k in range(5):  # a 10 Hz receiver
                await asyncio.sleep(max(0.0, start + 0.1 * k - time.monotonic()))
                pty.write(epoch_at(k))
                live.append(await anext(source))
            await asyncio.sleep(max(0.0, start + 2.0 - time.monotonic()))  # nobody reads: written late, at once
            pty.write(b"".join(epoch_at(k) for k in range(5, 20)))
            backlog = [await anext(source) for _ in range(15)]
            lowest = min(f.t - f.time_utc.timestamp() for f in live)
            t = [f.t for f in live + backlog]
            assert all(b > a for a, b in itertools.pairwise(t)), t
            # all but the newest of the backlog: their UTC time plus the lowest offset (quickest delivery)
            assert source.receive_times.restamped >= 14
            for f in backlog[:14]:
                assert f.t == pytest.approx(f.time_utc.timestamp() + lowest, abs=0.01)
            assert source.counters()["restamped"] == source.receive_times.restamped

    run(main())
