"""``sumhe protocol [--placements N] [--scenario S] [...]``: the experimental protocol of paper 000 (sec. 5).

Simulates a drive (cm-level GNSS by default), cuts a 5 s outage with 10 epochs of GNSS before and after at
``--placements`` parts of it and prints, per placement and method, the max and mean errors (24) of the
position, then a summary: median/p95/worst of the max errors, the share under 0.5 m, IPOPT times. The
estimator settings come from ``--config`` (its ``[estimator]``, ``[vehicle]`` and ``[sensors]`` tables) or the
defaults. A benchmark, not a test: it takes about a second per placement and method (tens of seconds for
``paper``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging

from sumhe.bench.protocol import DEFAULT_METHODS, METHODS, ProtocolSettings, format_report, run_protocol, summarise
from sumhe.config import load_config
from sumhe.errors import ConfigError
from sumhe.sim.settings import GPS_ERROR_MODELS, SCENARIO_NAMES

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", choices=SCENARIO_NAMES, default="offroad", help="drive (default offroad)")
    parser.add_argument("--seed", type=int, default=1, metavar="N", help="random seed of the drive (default 1)")
    parser.add_argument("--duration", type=float, default=300.0, metavar="S", help="drive length, s (default 300)")
    parser.add_argument("--gps-error", choices=GPS_ERROR_MODELS, default="rtk", help="GNSS errors (default rtk)")
    parser.add_argument("--placements", type=int, default=24, metavar="N", help="outage placements (default 24)")
    parser.add_argument("--outage", type=int, default=50, metavar="EPOCHS", help="outage length (default 50)")
    parser.add_argument("--before", type=int, default=10, metavar="EPOCHS", help="N_B (default 10)")
    parser.add_argument("--after", type=int, default=10, metavar="EPOCHS", help="N_A (default 10)")
    parser.add_argument("--antennas", type=int, choices=(1, 2), default=1, help="2: the paper's su7 model")
    parser.add_argument(
        "--methods",
        default=",".join(DEFAULT_METHODS),
        help=f"comma-separated, of {', '.join(METHODS)} (default {','.join(DEFAULT_METHODS)})",
    )
    parser.add_argument("--config", metavar="FILE", help="take the estimator settings from this config")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON instead of the tables")


def run(args: argparse.Namespace) -> int:
    try:
        ps = ProtocolSettings(
            scenario=args.scenario,
            seed=args.seed,
            duration_s=args.duration,
            gps_error=args.gps_error,
            placements=args.placements,
            before=args.before,
            outage_epochs=args.outage,
            after=args.after,
            methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()),
            antennas=args.antennas,
        )
    except ValueError as e:
        raise ConfigError(f"protocol: {e}") from e
    est = load_config(args.config).estimation
    log.info("protocol %s with estimator %s", ps, dataclasses.asdict(est))
    runs = run_protocol(ps, est)
    if args.json:
        print(json.dumps(summarise(runs, ps.bar_m), indent=1))
    else:
        print(format_report(runs, ps))
    return 0
