"""``sumhe demo [--speed X] [--out FILE]``: the bundled drive through the full live path, then a summary against
the truth and a figure (overview, the outages zoomed, errors of raw GNSS, dead reckoning and sumhe over time)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sumhe.bench.demo import DemoRun

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
    result = demo(args.speed, args.estimator, say=print)
    if not args.no_plot:
        draw(result, args.out)
    return 0 if result.runs["sumhe"] else 1


def draw(result: DemoRun, out: Path) -> None:
    """The demo's figure into ``out`` (its folder made); says why where it cannot be drawn."""
    from sumhe.plot import PlotError, plot_outages, track_from_records

    tracks = [track_from_records(recs, name) for name, recs in result.runs.items() if recs]
    fixes = track_from_records(result.fixes, "raw GNSS")
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        plot_outages(tracks, result.truth, result.outages, out, fixes, title="bundled drive (GPS outages shaded)")
    except PlotError as e:
        print(e)
    else:
        print(f"plot: {out}")
