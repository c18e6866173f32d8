"""``sumhe bench [NAME]``: the benchmarks, one sub-benchmark each: ``peers`` (every estimator side by side,
:mod:`sumhe.bench.peers`; what ``sumhe bench`` without a NAME runs), ``mhe`` (:mod:`sumhe.bench.mhe`),
``protocol`` (paper 000's protocol, the same as ``sumhe protocol``) and ``tune`` (the peers' noise tuning,
:mod:`sumhe.bench.tune`).

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
    "peers": (
        "every estimator on the same drives and outages: errors, latency, speed, memory (the default)",
        "sumhe.commands.bench:add_peers_arguments",
        "sumhe.commands.bench:run_peers",
    ),
    "mhe": (
        "latency, accuracy and replay speed of the moving-horizon estimator",
        "sumhe.commands.bench:add_mhe_arguments",
        "sumhe.commands.bench:run_mhe",
    ),
    "live": (
        "the daemon in real time against a player process: output rate, end-to-end latency, CPU use",
        "sumhe.commands.bench:add_live_arguments",
        "sumhe.commands.bench:run_live",
    ),
    "protocol": (
        "paper 000's outage protocol: batch SU methods side by side (as sumhe protocol)",
        "sumhe.commands.protocol:add_arguments",
        "sumhe.commands.protocol:run",
    ),
    "tune": (
        "the peers' noise tuning: grid search on training drives, evaluation on test drives",
        "sumhe.bench.tune:add_arguments",
        "sumhe.commands.bench:run_tune",
    ),
}
"""Sub-benchmarks: name -> (help, ``module:function`` adding its arguments, ``module:function`` running it)."""


def _load(target: str) -> Callable[..., Any]:
    module_name, _, attr = target.partition(":")
    return getattr(importlib.import_module(module_name), attr)  # type: ignore[no-any-return]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="benchmark", metavar="NAME")
    for name, (text, add, run_target) in BENCHMARKS.items():
        p = sub.add_parser(name, help=text, description=text)
        _load(add)(p)
        p.set_defaults(_bench=run_target)
    add_peers_arguments(parser)
    parser.set_defaults(_bench=BENCHMARKS["peers"][2])


def run(args: argparse.Namespace) -> int:
    return int(_load(args._bench)(args))


def add_mhe_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="one seed, short latency runs, a 10 min replay")
    parser.add_argument("--solvers", help="comma-separated solvers to time (default sqp,ipopt,fatrop)")
    parser.add_argument("--parts", metavar="A,B", help="parts to run (default latency,accuracy,multipath,replay)")


def run_mhe(args: argparse.Namespace) -> int:
    from sumhe.bench.mhe import MheBenchSettings
    from sumhe.bench.mhe_report import run_benchmark

    bs = MheBenchSettings.quick() if args.quick else MheBenchSettings()
    if args.solvers:
        bs = dataclasses.replace(bs, solvers=tuple(s.strip() for s in args.solvers.split(",") if s.strip()))
    if args.parts:
        try:
            bs = dataclasses.replace(bs, parts=tuple(s.strip() for s in args.parts.split(",") if s.strip()))
        except ValueError as e:
            raise SystemExit(f"error: --{e}") from e
    for line in run_benchmark(bs, lambda msg: print(msg, file=sys.stderr, flush=True)):
        print(line, flush=True)
    return 0


def add_peers_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="a one-minute subset: one 120 s drive, 5/10/30 s outages")
    parser.add_argument("--estimators", metavar="A,B", help="comma-separated estimators (default: every registered)")
    parser.add_argument("--scenarios", metavar="A,B", help="simulated scenarios (default urban,highway,offroad)")
    parser.add_argument("--gps-errors", metavar="A,B", help="GPS error models (default uniform,gaussian,walk)")
    parser.add_argument("--seeds", metavar="1,2,3", help="simulation seeds (default 1,2,3)")
    parser.add_argument("--duration", type=float, metavar="S", help="length of each simulated drive (default 240 s)")
    parser.add_argument(
        "--drive", action="append", default=[], metavar="DIR", help="a recorded drive: drive.log, drive.nmea, truth.csv"
    )
    parser.add_argument("--no-sim", action="store_true", help="only the --drive recordings, no simulated drives")
    parser.add_argument("--config", metavar="FILE", help="TOML config: the vehicle's CAN mapping, estimator settings")
    parser.add_argument("--timeout", type=float, metavar="S", help="time limit of one run (s); beyond it: failed")
    parser.add_argument("--out", metavar="DIR", help="write peers.json and peers.md into DIR")


def _names(text: str) -> tuple[str, ...]:
    return tuple(s.strip() for s in text.split(",") if s.strip())


def _peers_settings(args: argparse.Namespace) -> Any:
    from sumhe.bench.drives import PeersSettings
    from sumhe.errors import ConfigError
    from sumhe.estimator.registry import estimator_names

    changes: dict[str, Any] = {"recordings": tuple(args.drive)}
    if args.estimators:
        changes["estimators"] = _names(args.estimators)
        unknown = [n for n in changes["estimators"] if n not in estimator_names()]
        if unknown:
            raise ConfigError(f"--estimators: unknown {', '.join(unknown)} (known: {', '.join(estimator_names())})")
    for option, key in (("scenarios", "scenarios"), ("gps_errors", "gps_errors")):
        if getattr(args, option):
            changes[key] = _names(getattr(args, option))
    try:
        if args.seeds:
            changes["seeds"] = tuple(int(s) for s in _names(args.seeds))
        if args.no_sim:
            changes["seeds"] = ()
        if args.duration is not None:
            changes["duration_s"] = args.duration
        if args.timeout is not None:
            changes["timeout_s"] = args.timeout
        ps = dataclasses.replace(PeersSettings.quick() if args.quick else PeersSettings(), **changes)
    except ValueError as e:
        raise ConfigError(f"bench: {e}") from e
    if ps.drive_count() == 0:
        raise ConfigError("bench: no drives to run (--no-sim needs --drive DIR)")
    return ps


def _command_line(args: argparse.Namespace) -> str:
    parts = ["sumhe bench"]
    for option in ("quick", "no_sim"):
        if getattr(args, option):
            parts.append("--" + option.replace("_", "-"))
    for option in ("estimators", "scenarios", "gps_errors", "seeds", "duration", "config", "timeout", "out"):
        value = getattr(args, option)
        if value is not None:
            parts.append(f"--{option.replace('_', '-')} {value}")
    parts += [f"--drive {d}" for d in args.drive]
    return " ".join(parts)


class _ProgressBar:
    """tqdm on stderr: one step per run, the run going on as postfix, failed runs as lines above the bar."""

    def __init__(self, total: int) -> None:
        from tqdm import tqdm

        tqdm.monitor_interval = 0  # no monitor thread: every run is a forked process
        self.bar = tqdm(total=total, unit="run", file=sys.stderr, dynamic_ncols=True)

    def starting(self, label: str) -> None:
        self.bar.set_postfix_str(label)

    def finished(self, result: Any) -> None:
        self.bar.update(1)
        if not result.ok:
            self.bar.write(f"failed: {result.estimator} on {result.drive}: {result.error}", file=sys.stderr)

    def close(self) -> None:
        self.bar.close()


def run_peers(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from sumhe.bench.peers import run_bench
    from sumhe.bench.report import how_it_ran, main_table, markdown, summarise
    from sumhe.commands.candump import reference_config
    from sumhe.config import load_config

    ps = _peers_settings(args)
    base = load_config(args.config) if args.config else reference_config()
    bar = _ProgressBar(ps.drive_count() * len(ps.names()))
    try:
        report = run_bench(ps, base, bar)
    finally:
        bar.close()
    summary = summarise(report, _command_line(args))
    for line in [*how_it_ran(summary), "", *main_table(summary)]:
        print(line, flush=True)
    if summary["failures"]:
        print(f"{len(summary['failures'])} runs failed (see the failures in the report)", file=sys.stderr)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "peers.json").write_text(json.dumps(summary, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        (out / "peers.md").write_text(markdown(summary), encoding="utf-8")
        print(f"wrote {out / 'peers.json'} and {out / 'peers.md'}", file=sys.stderr)
    return 0


def run_tune(args: argparse.Namespace) -> int:
    from sumhe.bench.tune import run

    return run(args, lambda line: print(line, flush=True))


def add_live_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=60.0, metavar="S", help="length of the drive (default 60 s)")
    parser.add_argument("--estimator", default="mhe", metavar="NAME", help="estimator the daemon runs (default mhe)")


def run_live(args: argparse.Namespace) -> int:
    from sumhe.bench.live import format_live, run_live

    print(format_live(run_live(args.duration, args.estimator)), flush=True)
    return 0
