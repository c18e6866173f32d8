"""``sumhe replay LOG [LOG ...] [--nmea NMEALOG ...] --config FILE``: run an estimator on a recorded drive.

The CAN logs (candump, MF4, ...; several files of one drive in any order: shell globs welcome) and, with
``gps.source = "nmea"``, the NMEA logs are merged in time order (:class:`~sumhe.io.replay.RecordedDrive`). Writes
the same JSON objects the UDP output sends, one line per estimate, to ``--out`` (default stdout), and a summary to
stderr: samples, estimates, dropped samples, solve times, speed against real time, the estimates' modes (share of
epochs solved on widened bounds and of solver failures), the estimator's counters, and with ``--outage
START+LEN ...`` the errors against the fixes removed in those windows (START in seconds from the drive's first
CAN frame; :mod:`sumhe.bench.outages`). A drive without a valid fix or without CAN samples of the mapped signals
exits 1 with the reason (the log and its counters).
"""

from __future__ import annotations

import argparse
import sys
from contextlib import nullcontext

from sumhe.bench.reprocess import replay_drive
from sumhe.commands.options import add_outage_option
from sumhe.config import load_config, require_signals
from sumhe.estimator.registry import make_estimator
from sumhe.frontend.can import CAN_USED
from sumhe.io.can import reference_config
from sumhe.io.replay import RecordedDrive, check_gps_source

EXIT_AT_ONCE = True
"""The ``sumhe`` script ends the process when :func:`run` returns (:func:`sumhe.cli.end_process`): the output file
is closed and the summary printed by then, and a replay starts no thread nor child process."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "logs", nargs="+", metavar="LOG", help="CAN logs of one drive (candump -L .log, .mf4, .asc, .blf, .trc, ...)"
    )
    parser.add_argument(
        "--nmea", nargs="+", action="extend", metavar="NMEALOG", help="NMEA logs (with gps.source = 'nmea')"
    )
    parser.add_argument("--config", metavar="FILE", help="TOML config (default: the reference vehicle)")
    parser.add_argument("--estimator", metavar="NAME", help="estimator to run (default: estimator.name)")
    parser.add_argument("--out", metavar="FILE", help="JSON lines output (default: stdout)")
    parser.add_argument("--offset", type=float, default=0.0, metavar="S", help="add S seconds to the NMEA times")
    add_outage_option(parser, "--outage", "the first CAN frame")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config) if args.config else reference_config()
    require_signals(config)
    check_gps_source(config, args.nmea)
    drive = RecordedDrive(config, args.logs, args.nmea, args.offset, CAN_USED)
    estimator = make_estimator(args.estimator or config.estimator.name, drive.config)
    out_ctx = open(args.out, "w", encoding="utf-8") if args.out else nullcontext(sys.stdout)  # noqa: SIM115
    with out_ctx as out:
        summary = replay_drive(drive, estimator, args.outage, out)
    print("\n".join(summary.lines()), file=sys.stderr)
    reason = drive.unusable(summary.valid_fixes, summary.can_samples)
    if reason is not None:
        print(f"error: nothing to estimate from: {reason}", file=sys.stderr)
        return 1
    return 0
