"""``sumhe demo [--speed X] [--out FILE]``: the bundled drive through the full live path, then a summary against
the truth and a figure (overview, the outages zoomed, errors of raw GNSS, dead reckoning and sumhe over time)."""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT_OUT = Path("out") / "sumhe-demo.png"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--speed", type=float, default=4.0, help="replay speed factor (default 4; 1 = real time)")
    parser.add_argument("--estimator", metavar="NAME", help="estimator to run (default: the config's, mhe)")
    parser.add_argument(
        "--out", metavar="PNG", type=Path, default=DEFAULT_OUT, help=f"the figure (default {DEFAULT_OUT})"
    )
    parser.add_argument("--no-plot", action="store_true", help="no figure (it needs matplotlib: sumhe[plot])")


def run(args: argparse.Namespace) -> int:
    from sumhe.bench.demo import demo

    if args.speed <= 0:
        raise SystemExit("error: --speed must be positive")
    return demo(args.speed, args.estimator, None if args.no_plot else args.out, say=print)
