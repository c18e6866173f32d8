"""The live CAN sources on python-can's in-process ``virtual`` bus (and on socketcan vcan0 where it is up)."""

import asyncio
import itertools
import math
import socket
import time
from pathlib import Path

import can
import can.interfaces.virtual
import pytest

from sumhe.config import CanSettings, load_config
from sumhe.errors import ConfigError
from sumhe.io.can import REFERENCE_E2E, REFERENCE_SIGNALS
from sumhe.io.can_source import CAN_ERR_BUSOFF, CanBusSource, CanFrameSource
from sumhe.io.source import SourceTimeout

from canframes import speed_frame, yaw_frame

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
            with sender(channel) as bus:
                bus.send(speed_frame(0, 36.0, 0))
                assert (await anext(source)).value == pytest.approx(10.0)
                first_bus.shutdown()  # the link goes down under the reader: recv raises CanOperationError
                await until(lambda: reopened(source, first_bus))
                assert source.stats.reconnects == 1
                assert "Cannot operate on a closed bus" in source.stats.last_error
                bus.send(speed_frame(0, 72.0, 1))
                assert (await anext(source)).value == pytest.approx(20.0)

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


def test_a_bus_that_cannot_open_is_retried_not_fatal(channel):
    async def main():
        settings = CanSettings(interface="socketcan", channel="sumhe-no-such-if0", receive_timeout_s=0.3)
        async with CanFrameSource(settings) as source:
            await until(lambda: source.stats.errors >= 2)
            assert not source.stats.connected and source.stats.last_error.startswith("open")
            with pytest.raises(SourceTimeout):
                await anext(source)

    run(main())


def test_unknown_interface_and_bad_mapping_fail_at_construction(channel):
    with pytest.raises(ConfigError, match=r"can\.interface: unknown python-can interface 'nope'"):
        CanFrameSource(CanSettings(interface="nope"))
    config = load_config(None, env={}, overrides={"can.interface": "virtual", "can.signals": {"speed": "NOPE.X"}})
    with pytest.raises(ConfigError, match=r"can\.signals\.speed"):
        CanBusSource.from_config(config)


def _vcan0_up() -> bool:
    flags = Path("/sys/class/net/vcan0/flags")
    return hasattr(socket, "AF_CAN") and flags.is_file() and int(flags.read_text(), 16) & 0x1 == 1


@pytest.mark.skipif(not _vcan0_up(), reason="needs socketcan (socket.AF_CAN) and an up vcan0 interface")
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
