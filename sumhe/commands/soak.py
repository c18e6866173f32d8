"""``sumhe bench soak [--hours H] [--dir DIR] [--estimator NAME]``: a day of data replayed, memory printed as it goes
(:mod:`sumhe.bench.soak`). The first run simulates the hour-long segments into DIR (about half a minute each);
later runs reuse them."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sumhe.bench.soak import chained_drive, format_result, soak_replay
from sumhe.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hours", type=int, default=24, metavar="H", help="hours of data (default 24)")
    parser.add_argument("--dir", type=Path, default=Path("soak-drive"), metavar="DIR", help="where the segments go")
    parser.add_argument("--estimator", default="mhe", metavar="NAME", help="estimator (default mhe)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the first hour (default 0)")


def run(args: argparse.Namespace) -> int:
    if args.hours < 1:
        raise ConfigError("--hours: at least 1")

    def say(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    can_logs, nmea_logs = chained_drive(args.dir, args.hours, args.seed, say)
    result = soak_replay(can_logs, nmea_logs, args.estimator, say)
    print("\n".join(format_result(result)))
    return 0
