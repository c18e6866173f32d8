"""The live CAN sources on python-can's in-process ``virtual`` bus (and on socketcan vcan0 where it is up)."""

import asyncio
import errno
import itertools
import logging
import math
import re
import socket
import time

import can
import can.interfaces.virtual
import pytest

from sumhe.bench.live import free_multicast_port
from sumhe.config import CanSettings, load_config
from sumhe.errors import ConfigError, SourceError
from sumhe.io.can import REFERENCE_E2E, REFERENCE_SIGNALS
from sumhe.io.can_source import (
    CAN_ERR_BUSOFF,
    CanBusSource,
    CanFrameSource,
    ClockRebase,
    FrameGaps,
    explain_open_error,
    is_permanent,
)
from sumhe.io.source import SourceTimeout

from canframes import speed_frame, yaw_frame
from vcan import kernel_has_socketcan, needs_vcan0

DEG = math.pi / 180
_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"sumhe-test-{next(_channels)}"


def config_for(channel: str, **can_settings):
    overrides = {
        "can.interface": "virtual",
        "can.channel": channel,
        "can.signals": REFERENCE_SIGNALS,
        "can.e2e": list(REFERENCE_E2E),
        "can.receive_timeout_s": 2.0,
        "can.reconnect_max_s": 0.2,
    }
    overrides.update({f"can.{k}": v for k, v in can_settings.items()})
    return load_config(None, env={}, overrides=overrides)


def run(coro, timeout_s: float = 15.0):
    async def bounded():
        return await asyncio.wait_for(coro, timeout_s)

    return asyncio.run(bounded())


async def until(predicate, timeout_s: float = 5.0) -> None:
    """Yield to the loop until ``predicate()`` holds; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached in time"
        await asyncio.sleep(0.01)


def reopened(source, old_bus) -> bool:
    """The source closed ``old_bus`` and opened a new one (``stats.connected`` alone stays True during back-off)."""
    return source.bus is not None and source.bus is not old_bus and source.stats.connected


def sender(channel: str) -> can.BusABC:
    return can.Bus(interface="virtual", channel=channel)


def test_samples_arrive_decoded_and_unknown_ids_never_reach_the_decoder(channel):
    async def main():
        async with CanBusSource.from_config(config_for(channel)) as source:
            await until(lambda: source.stats.connected)
            with sender(channel) as bus:
                bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)))
                bus.send(can.Message(arbitration_id=0x130, is_extended_id=True, data=bytes(8)))
                bus.send(speed_frame(0, 36.0, 0))
                bus.send(yaw_frame(0, -5.0, 0, lat=0.5, lon=1.0))
                got = [await anext(source) for _ in range(4)]
            assert [(s.quantity, pytest.approx(s.value)) for s in got] == [
                ("speed", 10.0),
                ("yaw_rate", -5.0 * DEG),
                ("lat_accel", 0.5),
                ("lon_accel", 1.0),
            ]
            assert all(s.t > 1e9 for s in got)  # the bus's receive time
            stats = source.decoder.stats
            assert (stats.frames, stats.unused, stats.decoded) == (2, 0, 2)  # the bus filters dropped the others

    run(main())


def test_garbage_payloads_are_counted_and_the_stream_goes_on(channel):
    async def main():
        async with CanBusSource.from_config(config_for(channel)) as source:
            await until(lambda: source.stats.connected)
            with sender(channel) as bus:
                bus.send(can.Message(arbitration_id=0x130, is_extended_id=False, data=bytes(range(8))))  # bad CRC
                bus.send(can.Message(arbitration_id=0x1B0, is_extended_id=False, data=b"\x01\x02"))  # short
                bus.send(speed_frame(0, 18.0, 0))
                sample = await anext(source)
            assert (sample.quantity, sample.value) == ("speed", pytest.approx(5.0))
            assert (source.decoder.stats.crc_errors, source.decoder.stats.decode_errors) == (1, 1)

    run(main())


def test_queue_overflow_drops_the_oldest_and_counts(channel):
    async def main():
        async with CanBusSource.from_config(config_for(channel, queue_size=5)) as source:
            await until(lambda: source.stats.connected)
            with sender(channel) as bus:
                for i in range(20):
                    bus.send(speed_frame(0, float(i), i))
                await until(lambda: source.stats.dropped == 15)
            got = [await anext(source) for _ in range(5)]
            assert [round(s.value * 3.6) for s in got] == [15, 16, 17, 18, 19]
            assert source.stats.received == 20

    run(main())


def test_receive_timeout_raises_and_iteration_continues(channel):
    async def main():
        async with CanBusSource.from_config(config_for(channel, receive_timeout_s=0.3)) as source:
            with pytest.raises(SourceTimeout):
                await anext(source)
            await until(lambda: source.stats.connected)
            with sender(channel) as bus:
                bus.send(speed_frame(0, 3.6, 0))
                assert (await anext(source)).value == pytest.approx(1.0)

    run(main())


def test_bus_shut_down_and_brought_back_resumes_samples(channel):
    async def main():
        async with CanBusSource.from_config(config_for(channel)) as source:
            await until(lambda: source.stats.connected)
            first_bus = source.bus
            assert source.stats.last_received_s == 0.0
            with sender(channel) as bus:
                bus.send(speed_frame(0, 36.0, 0))
                assert (await anext(source)).value == pytest.approx(10.0)
                read_before = source.stats.last_received_s
                assert 0.0 < read_before <= time.time()
                first_bus.shutdown()  # the link goes down under the reader: recv raises CanOperationError
                await until(lambda: reopened(source, first_bus))
                assert source.stats.reconnects == 1
                assert "Cannot operate on a closed bus" in source.stats.last_error
                reopened_at = time.time()
                bus.send(speed_frame(0, 72.0, 1))
                assert (await anext(source)).value == pytest.approx(20.0)
                assert source.stats.last_received_s >= reopened_at > read_before, "the read after the reopen"
        # closed by the stop, not down: the final status line marks no DOWN with the mended error
        assert source.stats.connected and "closed bus" in source.stats.last_error

    run(main())


def test_bus_off_error_frame_reopens_the_bus_and_raw_frames_resume(channel):
    async def main():
        async with CanFrameSource.from_config(config_for(channel)) as source:
            await until(lambda: source.stats.connected)
            first_bus = source.bus
            with sender(channel) as bus:
                bus.send(can.Message(is_error_frame=True, arbitration_id=0x04))  # controller warning: kept
                assert (await anext(source)).is_error_frame
                bus.send(can.Message(is_error_frame=True, arbitration_id=CAN_ERR_BUSOFF))
                await until(lambda: reopened(source, first_bus))
                assert source.stats.reconnects == 1
                assert "bus-off" in source.stats.last_error
                frame = yaw_frame(0, 1.0, 0)
                bus.send(frame)
                got = await anext(source)
            assert (got.arbitration_id, bytes(got.data)) == (0x130, bytes(frame.data))

    run(main())


@pytest.mark.socketcan
def test_a_socketcan_interface_that_cannot_exist_ends_the_source_with_the_fix(caplog):
    """Here the kernel has no AF_CAN (EAFNOSUPPORT); in the CI virtual machine vcan97 does not exist (ENODEV):
    both are permanent at start-up, and the message names interface and channel and says what to do."""

    async def main():
        settings = CanSettings(interface="socketcan", channel="vcan97", receive_timeout_s=5.0)
        async with CanFrameSource(settings) as source:
            with pytest.raises(SourceError) as err:
                await anext(source)
            assert source.stats.reconnects == 0, "not retried"
        msg = str(err.value)
        assert "socketcan channel 'vcan97'" in msg
        if kernel_has_socketcan():
            assert "ip link add dev vcan97 type vcan" in msg
        else:
            assert "no SocketCAN (AF_CAN)" in msg

    run(main())
    # python-can leaves the socket of a failed bind to the garbage collector, and logs the error; the captured
    # record keeps that error, its frames and so the socket alive until the test ends: let them go
    caplog.clear()


ENETDOWN = OSError(errno.ENETDOWN, "Network is down")
ENODEV = OSError(errno.ENODEV, "No such device")


@pytest.mark.parametrize(
    ("err", "first", "after"),
    [
        (OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol"), True, False),
        (ENODEV, True, False),  # a typo at start-up; an adapter unplugged later comes back
        (OSError(errno.EACCES, "Permission denied"), True, False),
        (OSError("pcanbasic library not found."), True, False),  # what python-can's pcan raises
        (can.CanInterfaceNotImplementedError("no driver"), True, False),
        (ImportError("canlib"), True, False),
        (ENETDOWN, False, False),
        (can.CanOperationError("Error receiving: Network is down", errno.ENETDOWN), False, False),
        (can.CanInitializationError("adapter busy"), False, False),
        (OSError(errno.EBUSY, "Device or resource busy"), False, False),
    ],
)
def test_permanent_and_transient_open_errors(err, first, after):
    settings = CanSettings(interface="socketcan", channel="can1", bitrate=250000)
    assert is_permanent(settings, err, connected_before=False) is first
    assert is_permanent(settings, err, connected_before=True) is after


@pytest.mark.parametrize(
    ("channel", "err", "fix"),
    [
        ("vcan0", ENODEV, "modprobe vcan; ip link add dev vcan0 type vcan; ip link set up vcan0"),
        (
            "can1",
            ENODEV,
            "plug in the adapter, load its driver, then `ip link set can1 up type can bitrate 250000 restart-ms 100`",
        ),
        ("can1", ENETDOWN, "the interface is down: `ip link set can1 up type can bitrate 250000 restart-ms 100`"),
        ("vcan0", OSError(errno.EAFNOSUPPORT, "x"), "modprobe can_raw"),
    ],
)
def test_open_errors_name_interface_and_channel_and_give_the_fix(channel, err, fix):
    msg = explain_open_error(CanSettings(interface="socketcan", channel=channel, bitrate=250000), err)
    assert msg.startswith(f"cannot use socketcan channel {channel!r}: ")
    assert fix in msg


def test_fd_frames_on_a_classic_id_are_ignored_and_counted(channel):
    """(Error frames: python-can's software filters drop them on the virtual bus; the SocketCAN kernel filters let
    them through, and the virtual machine's test counts them there.)"""

    async def main():
        async with CanBusSource.from_config(config_for(channel)) as source:
            await until(lambda: source.stats.connected)
            with sender(channel) as bus:
                classic = speed_frame(0, 250.0, 0)
                bus.send(
                    can.Message(
                        arbitration_id=classic.arbitration_id,
                        is_extended_id=False,
                        is_fd=True,
                        data=bytes(classic.data) + bytes(56),
                    )
                )
                bus.send(speed_frame(0, 36.0, 1))
                sample = await anext(source)
            assert (sample.quantity, sample.value) == ("speed", pytest.approx(10.0))
            counters = source.counters()
            assert (counters["fd_frames"], counters["frames"], counters["decoded"]) == (1, 2, 1)
            assert counters["reconnects"] == 0

    run(main())


@pytest.mark.parametrize("adapter_t0", [1234.5, 0.001])
def test_adapter_times_not_unix_are_rebased_on_the_host_clock(channel, adapter_t0, caplog):
    """python-can's pcan stamps frames with the time since boot: they would all be dropped as stale."""

    async def main():
        async with CanBusSource.from_config(config_for(channel)) as source:
            await until(lambda: source.stats.connected)
            with can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as bus:
                got = []
                for i in range(3):
                    bus.send(speed_frame(adapter_t0 + 0.01 * i, 36.0, i))
                    got.append(await anext(source))
                    await asyncio.sleep(0.01)
        now = time.time()
        assert all(abs(s.t - now) < 1.0 for s in got), [s.t for s in got]
        gaps = [b.t - a.t for a, b in itertools.pairwise(got)]
        assert gaps == [pytest.approx(0.01, abs=0.005)] * 2, "adapter time differences are kept"

    with caplog.at_level(logging.INFO, logger="sumhe.io.can_source"):
        run(main())
    assert sum("not Unix time" in r.message for r in caplog.records) == 1, "logged once"


def test_unix_times_are_kept_and_drift_does_not_accumulate():
    clock = [1_700_000_000.0]
    rebase = ClockRebase("can", clock=lambda: clock[0])
    assert rebase(clock[0] - 0.002) == clock[0] - 0.002 and rebase.active is False
    rebase.restart()
    adapter = 50.0
    out = []
    for i in range(3000):  # 30 s at 100 Hz; the adapter's clock runs 100 ppm slow; each frame waits 0.1-1.1 ms
        clock[0] += 0.01
        adapter += 0.01 * (1 - 1e-4)
        out.append(rebase(adapter) - (clock[0] - 0.0001 - 0.001 * ((i * 7) % 11) / 10))
    assert rebase.active
    assert max(abs(e) for e in out[-1000:]) < 0.0015, "within the frames' wait, drift (3 ms in 30 s) not kept"


def test_unknown_interface_and_bad_mapping_fail_at_construction(channel):
    with pytest.raises(ConfigError, match=r"can\.interface: unknown python-can interface 'nope'"):
        CanFrameSource(CanSettings(interface="nope"))
    config = load_config(None, env={}, overrides={"can.interface": "virtual", "can.signals": {"speed": "NOPE.X"}})
    with pytest.raises(ConfigError, match=r"can\.signals\.speed"):
        CanBusSource.from_config(config)


@pytest.mark.socketcan
@needs_vcan0()
def test_socketcan_vcan0_with_kernel_filters():
    async def main():
        config = config_for("vcan0", interface="socketcan")
        async with CanBusSource.from_config(config) as source:
            await until(lambda: source.stats.connected)
            with can.Bus(interface="socketcan", channel="vcan0") as bus:
                bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)))
                bus.send(speed_frame(0, 36.0, 0))
                sample = await anext(source)
            assert (sample.quantity, sample.value) == ("speed", pytest.approx(10.0))
            assert source.decoder.stats.unused == 0

    run(main())


def test_frames_lost_before_they_were_read_are_inferred_from_the_gaps_of_each_id():
    gaps = FrameGaps()
    t = 1000.0
    for k in range(50):  # 0x100 at 100 Hz, 0x200 at 50 Hz, with jitter
        gaps.see(0x100, t + 0.01 * k + 0.002 * (k % 3))
        if k % 2 == 0:
            gaps.see(0x200, t + 0.01 * k)
    assert gaps.lost == 0
    resume = t + 0.49 + 1.0  # a 1 s overrun: about 99 frames of 0x100 and 49 of 0x200 never read
    gaps.see(0x100, resume)
    gaps.see(0x200, resume)
    assert 140 <= gaps.lost <= 155
    before = gaps.lost
    gaps.see(0x100, resume + 60.0)  # a sender that stopped for a minute: not an overrun
    assert gaps.lost == before


@pytest.mark.skipif(not socket.has_ipv6, reason="needs IPv6 for the interface-local multicast group")
def test_buses_on_two_ports_of_one_multicast_group_do_not_hear_each_other():
    """``can.bus`` passes python-can's Bus arguments: two runs on one machine (two test suites, a bench beside
    them) on the same interface-local group keep apart by their ``udp_multicast`` ports (python-can binds its port
    on every group, so one port heard every run)."""
    group = "ff11:7375:6d68:6500::1"  # interface-local: never leaves this machine
    own, other = free_multicast_port(), free_multicast_port()
    config = config_for(group, interface="udp_multicast", bus={"port": own})
    assert config.can.bus == {"port": own} and own != other

    async def main():
        async with CanBusSource.from_config(config) as source:
            await until(lambda: source.stats.connected)
            with (
                can.Bus(interface="udp_multicast", channel=group, port=other) as theirs,
                can.Bus(interface="udp_multicast", channel=group, port=own) as ours,
            ):
                for k in range(3):
                    theirs.send(speed_frame(0, 72.0, k))
                ours.send(speed_frame(0, 36.0, 0))
                first = await anext(source)
                for k in range(3, 6):
                    theirs.send(speed_frame(0, 72.0, k))
                ours.send(speed_frame(0, 36.0, 1))
                second = await anext(source)
            assert [s.value for s in (first, second)] == [pytest.approx(10.0)] * 2
            assert source.decoder.stats.frames == 2  # none of the other port's six

    run(main())


@pytest.mark.parametrize(
    "bus, key", [({"channel": "vcan1"}, "can.bus.channel"), ({"port": [1]}, "can.bus.port"), (5, "can.bus")]
)
def test_a_bad_bus_argument_stops_start_up_naming_the_key(bus, key):
    with pytest.raises(ConfigError, match=re.escape(key) + ":"):
        config_for("x", bus=bus)
