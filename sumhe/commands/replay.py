"""``sumhe replay CANLOG --nmea NMEALOG --config FILE``: run an estimator on a recorded drive.

Writes the same JSON objects the UDP output sends, one line per estimate, to ``--out`` (default stdout), and a
summary to stderr (samples, estimates, dropped samples, solve times, speed against real time).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from contextlib import nullcontext
from pathlib import Path
from typing import TextIO

from sumhe.commands.candump import reference_config
from sumhe.config import load_config, require_signals
from sumhe.estimator.registry import make_estimator
from sumhe.io.replay import log_samples
from sumhe.io.udp import estimate_to_json
from sumhe.messages import Estimate
from sumhe.service.app import percentile
from sumhe.service.pipeline import Pipeline


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("canlog", help="CAN log (candump -L .log, .asc, .blf, .trc, ...)")
    parser.add_argument("--nmea", metavar="NMEALOG", required=True, help="NMEA log (receive-time prefixed or not)")
    parser.add_argument("--config", metavar="FILE", help="TOML config (default: the reference vehicle)")
    parser.add_argument("--estimator", metavar="NAME", help="estimator to run (default: estimator.name)")
    parser.add_argument("--out", metavar="FILE", help="JSON lines output (default: stdout)")
    parser.add_argument("--offset", type=float, default=0.0, metavar="S", help="add S seconds to the NMEA times")


def _write(out: TextIO, estimates: list[Estimate], solve_ms: list[float]) -> None:
    for est in estimates:
        if est.solve_ms > 0:
            solve_ms.append(est.solve_ms)
        out.write(json.dumps(estimate_to_json(est), separators=(",", ":")) + "\n")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config) if args.config else reference_config()
    require_signals(config)
    estimator = make_estimator(args.estimator or config.estimator.name, config)
    pipeline = Pipeline(config, estimator)
    solve_ms: list[float] = []
    first_t = last_t = None
    wall0 = time.perf_counter()
    out_ctx = open(args.out, "w", encoding="utf-8") if args.out else nullcontext(sys.stdout)  # noqa: SIM115
    with out_ctx as out:
        for sample in log_samples(config, Path(args.canlog), Path(args.nmea), args.offset):
            first_t = sample.t if first_t is None else first_t
            last_t = sample.t
            _write(out, pipeline.push(sample), solve_ms)
        _write(out, pipeline.finish(), solve_ms)
    wall = time.perf_counter() - wall0
    span = (last_t - first_t) if first_t is not None and last_t is not None else 0.0
    ts, ps = pipeline.guard.stats, pipeline.stats
    print(
        f"replay: {estimator.name}: {ps.fixes} fixes ({ps.valid_fixes} valid), {ps.can_samples} CAN samples, "
        f"{ps.estimates} estimates; dropped late {ts.late}, duplicate {ts.duplicate}, zero time {ts.zero_time}, "
        f"clock resets {ts.clock_resets}; "
        f"solve p50/p99 {percentile(solve_ms, 50):.2f}/{percentile(solve_ms, 99):.2f} ms; "
        f"{span:.0f} s of data in {wall:.1f} s ({span / max(wall, 1e-9):.0f}x real time)",
        file=sys.stderr,
    )
    return 0
