"""``sumhe bench NAME``: the benchmarks, one sub-benchmark each: ``mhe`` (:mod:`sumhe.bench.mhe`) and
``protocol`` (paper 000's protocol, the same as ``sumhe protocol``).

A benchmark prints figures (latency percentiles, errors, speed) and how it ran; it asserts nothing. BLAS is
pinned to one thread by :func:`sumhe.cli.main` before numpy loads. Adding a benchmark is one line in
:data:`BENCHMARKS`.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
from collections.abc import Callable
from typing import Any

BENCHMARKS: dict[str, tuple[str, str, str]] = {
    "mhe": (
        "latency, accuracy and replay speed of the moving-horizon estimator",
        "sumhe.commands.bench:add_mhe_arguments",
        "sumhe.commands.bench:run_mhe",
    ),
    "protocol": (
        "paper 000's outage protocol: batch SU methods side by side (as sumhe protocol)",
        "sumhe.commands.protocol:add_arguments",
        "sumhe.commands.protocol:run",
    ),
}
"""Sub-benchmarks: name -> (help, ``module:function`` adding its arguments, ``module:function`` running it)."""


def _load(target: str) -> Callable[..., Any]:
    module_name, _, attr = target.partition(":")
    return getattr(importlib.import_module(module_name), attr)  # type: ignore[no-any-return]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="benchmark", metavar="NAME", required=True)
    for name, (text, add, run_target) in BENCHMARKS.items():
        p = sub.add_parser(name, help=text, description=text)
        _load(add)(p)
        p.set_defaults(_bench=run_target)


def run(args: argparse.Namespace) -> int:
    return int(_load(args._bench)(args))


def add_mhe_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="one seed, short latency runs, a 10 min replay")
    parser.add_argument("--solvers", help="comma-separated solvers to time (default sqp,ipopt,fatrop)")
    parser.add_argument("--no-replay", action="store_true", help="skip the long replay")


def run_mhe(args: argparse.Namespace) -> int:
    from sumhe.bench.mhe import MheBenchSettings, run_benchmark

    bs = MheBenchSettings.quick() if args.quick else MheBenchSettings()
    if args.solvers:
        bs = dataclasses.replace(bs, solvers=tuple(s.strip() for s in args.solvers.split(",") if s.strip()))
    if args.no_replay:
        bs = dataclasses.replace(bs, replay_s=0.0)
    for line in run_benchmark(bs, lambda msg: print(msg, file=sys.stderr, flush=True)):
        print(line, flush=True)
    return 0
