"""Command-line options several subcommands share (parsers only: importing this loads nothing heavy)."""

from __future__ import annotations

import argparse


def outage(text: str) -> tuple[float, float]:
    """``START+LEN`` (s) -> (start_s, length_s)."""
    start, plus, length = text.partition("+")
    try:
        if not plus:
            raise ValueError(text)
        return float(start), float(length)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START+LENGTH in seconds (e.g. 60+10), got {text!r}") from None


def add_outage_option(parser: argparse.ArgumentParser, flag: str, origin: str) -> None:
    """``flag START+LEN ...``: outage windows whose fixes are removed, starts in seconds from ``origin``."""
    parser.add_argument(
        flag,
        nargs="+",
        action="extend",
        type=outage,
        default=[],
        metavar="START+LEN",
        help=f"remove the fixes of these windows (s from {origin}) and report the errors against them",
    )
