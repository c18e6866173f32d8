"""``sumhe run --config FILE``: the daemon on a CAN bus and a serial GNSS receiver, positions over UDP.

Start-up refuses a config without the speed and yaw-rate signals, and stops with exit code 1 when the CAN bus cannot
be opened for a reason retrying cannot mend (no SocketCAN in the kernel, no such interface, a missing driver: see
:mod:`sumhe.io.can_source`); anything transient is retried. Its lifecycle lines (starting, ready, status, stopped)
are logged at INFO, which this command shows by default (for the service and its inputs and outputs).
"""

from __future__ import annotations

import argparse
import asyncio

from sumhe.config import load_config, require_signals
from sumhe.estimator.registry import check_live, make_estimator
from sumhe.io.can_source import CanBusSource
from sumhe.io.serial import SerialNmeaSource
from sumhe.service.app import Service, install_signal_handlers
from sumhe.service.inputs import InputRecorder

LOG_INFO_FROM = ("sumhe.service", "sumhe.io")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", required=True, help="TOML config (see configs/default.toml)")
    parser.add_argument("--estimator", metavar="NAME", help="estimator to run (default: estimator.name)")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: on a signal)")
    parser.add_argument(
        "--record-inputs",
        metavar="FILE",
        help="write every sample the estimator takes, in its order and with its times, as JSON lines (a replay of "
        "FILE gives the same estimates: sumhe.service.inputs)",
    )


async def serve(args: argparse.Namespace) -> None:
    config = load_config(args.config)
    name = args.estimator or config.estimator.name
    check_live(name)
    require_signals(config)
    sources: dict[str, CanBusSource | SerialNmeaSource] = {"can": CanBusSource.from_config(config)}
    if config.gps.source == "nmea":  # with "can" the fixes come decoded from the CAN bus: no serial port
        sources["gps"] = SerialNmeaSource(config.gps)
    estimator = make_estimator(name, config)
    stop = asyncio.Event()
    install_signal_handlers(stop)
    if args.duration is not None:
        asyncio.get_running_loop().call_later(args.duration, stop.set)
    recorder = InputRecorder(args.record_inputs) if args.record_inputs else None
    try:
        await Service(config, estimator, sources, record=recorder).run(stop)
    finally:
        if recorder is not None:
            recorder.close()


def run(args: argparse.Namespace) -> int:
    asyncio.run(serve(args))
    return 0
