"""``sumhe plot EST.jsonl [EST2.jsonl ...] --truth truth.csv --out plot.png``: a PNG of replays.

Each file is the JSON lines of one ``sumhe replay --out`` (one estimator), named by its stem or ``--label``. The
figure (:mod:`sumhe.plot`): trajectory with outages shaded, error against the truth (with ``--truth``), window
length, error estimate (``eph``) and feasible-set bounds against time. Needs matplotlib (``pip install 'sumhe[plot]'``).
"""

from __future__ import annotations

import argparse
import sys

from sumhe.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("replays", nargs="+", metavar="EST.jsonl", help="JSON lines of sumhe replay, one per estimator")
    parser.add_argument("--label", action="append", default=[], help="name of each file in turn (default: its stem)")
    parser.add_argument("--truth", metavar="CSV", help="the drive's truth.csv (simulator format)")
    parser.add_argument("--out", metavar="PNG", default="plot.png", help="the PNG to write (default plot.png)")
    parser.add_argument("--title", default="", help="title of the trajectory panel")


def run(args: argparse.Namespace) -> int:
    from sumhe.plot import load_track, plot_replays
    from sumhe.sim import load_truth

    if args.label and len(args.label) != len(args.replays):
        raise ConfigError(f"--label: {len(args.label)} labels for {len(args.replays)} files")
    labels = args.label or [None] * len(args.replays)
    tracks = [load_track(path, label) for path, label in zip(args.replays, labels, strict=True)]
    truth = None
    if args.truth:
        try:
            truth = load_truth(args.truth)
        except ValueError as e:
            raise ConfigError(str(e)) from e
    path = plot_replays(tracks, args.out, truth, args.title)
    print(f"wrote {path} ({', '.join(t.label for t in tracks)})", file=sys.stderr)
    return 0
