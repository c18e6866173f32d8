"""``sumhe record --config FILE --out DIR``: record a drive for later replay.

Writes ``DIR/drive.log`` (every CAN frame of the configured bus, candump ``-L`` format) and ``DIR/drive.nmea``
(every line the receiver sends, prefixed with its receive time ``(t) ``). Both are stamped from the same clock
(Unix time: socketcan's kernel timestamps and ``time.time()`` at line arrival), so ``sumhe replay`` merges them
correctly. Runs until SIGINT/SIGTERM or ``--duration``; a source that vanishes is reconnected, and what was
recorded so far is flushed every second, so nothing is lost when the process is killed.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from pathlib import Path
from typing import IO

import can

from sumhe.config import load_config
from sumhe.errors import ConfigError
from sumhe.io.can_source import CanFrameSource
from sumhe.io.nmea import format_log_line
from sumhe.io.serial import NmeaLine, SerialLineSource
from sumhe.io.source import SourceTimeout, ThreadedSource, wait_event

log = logging.getLogger(__name__)

FLUSH_S = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", required=True, help="TOML config ([can] bus, [gps] port)")
    parser.add_argument("--out", metavar="DIR", required=True, help="directory for drive.log and drive.nmea")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until a signal)")
    parser.add_argument("--no-gps", action="store_true", help="record the CAN bus only")
    parser.add_argument("--no-can", action="store_true", help="record the GNSS receiver only")


async def _pump_can(source: ThreadedSource[can.Message], writer: can.CanutilsLogWriter, counts: dict[str, int]) -> None:
    async with source:
        while True:
            try:
                msg = await anext(source)
            except SourceTimeout:
                continue
            writer.on_message_received(msg)
            counts["can_frames"] += 1


async def _pump_nmea(source: ThreadedSource[NmeaLine], out: IO[bytes], counts: dict[str, int]) -> None:
    async with source:
        while True:
            try:
                line = await anext(source)
            except SourceTimeout:
                continue
            out.write(format_log_line(line.t, line.raw))
            counts["nmea_lines"] += 1


async def _flush_every(files: list[IO[bytes]], writer: can.CanutilsLogWriter | None) -> None:
    while True:
        await asyncio.sleep(FLUSH_S)
        for f in files:
            f.flush()
        if writer is not None:
            writer.file.flush()


async def record(args: argparse.Namespace) -> dict[str, int]:
    """Record until a signal or the duration; returns the counts written."""
    if args.no_can and args.no_gps:
        raise ConfigError("record: --no-can and --no-gps leave nothing to record")
    config = load_config(args.config)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)
    can_src = None if args.no_can else CanFrameSource.from_config(config)
    gps_src = None if args.no_gps else SerialLineSource(config.gps)
    writer = None if can_src is None else can.CanutilsLogWriter(str(out_dir / "drive.log"))
    nmea_file = None if gps_src is None else open(out_dir / "drive.nmea", "ab")  # noqa: SIM115 - closed below
    tasks = []
    counts = {"can_frames": 0, "nmea_lines": 0}
    try:
        if can_src is not None and writer is not None:
            tasks.append(asyncio.create_task(_pump_can(can_src, writer, counts)))
        if gps_src is not None and nmea_file is not None:
            tasks.append(asyncio.create_task(_pump_nmea(gps_src, nmea_file, counts)))
        tasks.append(asyncio.create_task(_flush_every([f for f in (nmea_file,) if f], writer)))
        log.info("recording to %s", out_dir)
        await wait_event(stop, args.duration)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if writer is not None:
            writer.stop()
        if nmea_file is not None:
            nmea_file.close()
    return counts


def run(args: argparse.Namespace) -> int:
    counts = asyncio.run(record(args))
    print(
        f"recorded {counts['can_frames']} CAN frames and {counts['nmea_lines']} NMEA lines to {args.out}",
        file=sys.stderr,
    )
    return 0
