"""``sumhe run --config FILE``: the daemon on a CAN bus and a serial GNSS receiver, positions over UDP."""

from __future__ import annotations

import argparse
import asyncio

from sumhe.config import load_config
from sumhe.estimator.registry import check_live, make_estimator
from sumhe.io.can_source import CanBusSource
from sumhe.io.serial import SerialNmeaSource
from sumhe.service.app import Service, install_signal_handlers


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", required=True, help="TOML config (see configs/default.toml)")
    parser.add_argument("--estimator", metavar="NAME", help="estimator to run (default: estimator.name)")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: on a signal)")


async def serve(args: argparse.Namespace) -> None:
    config = load_config(args.config)
    name = args.estimator or config.estimator.name
    check_live(name)
    estimator = make_estimator(name, config)
    sources: dict[str, CanBusSource | SerialNmeaSource] = {"can": CanBusSource.from_config(config)}
    if config.gps.source == "nmea":  # with "can" the fixes come decoded from the CAN bus: no serial port
        sources["gps"] = SerialNmeaSource(config.gps)
    stop = asyncio.Event()
    install_signal_handlers(stop)
    if args.duration is not None:
        asyncio.get_running_loop().call_later(args.duration, stop.set)
    for source in sources.values():
        await source.start()
    await Service(config, estimator, sources).run(stop)


def run(args: argparse.Namespace) -> int:
    asyncio.run(serve(args))
    return 0
