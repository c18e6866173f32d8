"""``sumhe calibrate LOG [LOG ...] [--nmea FILE ...] --config FILE [--json]``: the installation parameters of a car
from one recorded drive (:mod:`sumhe.calibration`), with standard errors and sign checks.

The logs are read as ``sumhe replay`` reads them. Without ``--json`` the output is one TOML document: the report
as comments, then the tables the config accepts (``sumhe calibrate ... > calibration.toml``, then merge it into the
car's config). With ``--json``: one object with exactly the five parameters and ``<key>_std`` (null where the drive
does not determine one) on stdout, the report on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys

from sumhe.calibration import calibrate, read_signals, report_lines, toml_snippet
from sumhe.commands.replay import check_gps_source
from sumhe.config import load_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "logs", nargs="+", metavar="LOG", help="CAN logs of one drive (candump -L .log, .mf4, .asc, .blf, .trc, ...)"
    )
    parser.add_argument(
        "--nmea", nargs="+", action="extend", metavar="FILE", help="NMEA logs (with gps.source = 'nmea')"
    )
    parser.add_argument("--config", required=True, metavar="FILE", help="TOML config with the car's DBC mapping")
    parser.add_argument("--json", action="store_true", help="print one JSON object (the report goes to stderr)")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    check_gps_source(config, args.nmea)
    signals = read_signals(config, args.logs, args.nmea)
    cal = calibrate(signals, config.sensors.can.delay_s, config.sensors.can.speed_delay_s)
    report = report_lines(cal, signals)
    if args.json:
        print("\n".join(report), file=sys.stderr)
        print(json.dumps(cal.to_json()))
    else:
        print("\n".join(f"# {line}" for line in report) + "\n")
        print(toml_snippet(cal, config), end="")
    return 0
