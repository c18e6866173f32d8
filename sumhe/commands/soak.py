"""``sumhe bench soak [--hours H] [--dir DIR] [--estimator NAME] [--daemon --speed X]``: a day of data replayed (or,
with ``--daemon``, fed to the daemon's service at X times real time), memory printed as it goes
(:mod:`sumhe.bench.soak`). The first run simulates the hour-long segments into DIR (about half a minute each);
later runs reuse them."""

from __future__ import annotations

import argparse
import asyncio
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from sumhe.bench.soak import chained_drive, format_daemon, format_result, soak_daemon, soak_replay
from sumhe.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hours", type=int, default=24, metavar="H", help="hours of data (default 24)")
    parser.add_argument("--dir", type=Path, default=Path("soak-drive"), metavar="DIR", help="where the segments go")
    parser.add_argument("--estimator", default="mhe", metavar="NAME", help="estimator (default mhe)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the first hour (default 0)")
    parser.add_argument("--daemon", action="store_true", help="the daemon's service, paced, instead of a replay")
    parser.add_argument("--speed", type=float, default=20.0, metavar="X", help="--daemon: times real time (20)")


def say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    if args.hours < 1:
        raise ConfigError("--hours: at least 1")
    # simulated in a process of its own: an hour's simulation peaks near 1 GB, which must not count as the replay's
    with ProcessPoolExecutor(1) as pool:
        can_logs, nmea_logs = pool.submit(chained_drive, args.dir, args.hours, args.seed, say).result()
    if args.daemon:
        if args.speed <= 0:
            raise ConfigError("--speed: must be positive")
        status, points, received = asyncio.run(soak_daemon(can_logs, nmea_logs, args.estimator, args.speed, say))
        print(format_daemon(status, points, received))
        return 0
    result = soak_replay(can_logs, nmea_logs, args.estimator, say)
    print("\n".join(format_result(result)))
    return 0
