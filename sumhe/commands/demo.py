"""``sumhe demo [--speed X]``: the bundled drive through the full live path, then a summary against the truth."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--speed", type=float, default=4.0, help="replay speed factor (default 4; 1 = real time)")
    parser.add_argument("--estimator", metavar="NAME", help="estimator to run (default: the config's, mhe)")
    parser.add_argument("--png", metavar="FILE", default="sumhe-demo.png", help="trajectory plot (needs matplotlib)")
    parser.add_argument("--no-png", action="store_true", help="do not write the plot")


def run(args: argparse.Namespace) -> int:
    from sumhe.bench.demo import demo

    if args.speed <= 0:
        raise SystemExit("error: --speed must be positive")
    return demo(args.speed, args.estimator, None if args.no_png else Path(args.png), say=print)
