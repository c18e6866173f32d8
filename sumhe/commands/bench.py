"""``sumhe bench [NAME]``: the benchmarks, one sub-benchmark each: ``peers`` (every estimator side by side,
:mod:`sumhe.bench.peers`; what ``sumhe bench`` without a NAME runs), ``mhe`` (:mod:`sumhe.bench.mhe`),
``protocol`` (paper 000's protocol, the same as ``sumhe protocol``), ``fuzz`` (the input decoders on fuzzed
lines, :mod:`sumhe.bench.fuzz`), ``compare`` (two results outage by outage, :mod:`sumhe.bench.compare`) and
``tune`` (the peers' noise tuning, :mod:`sumhe.bench.tune`).

A benchmark prints figures (latency percentiles, errors, speed) and how it ran; it asserts nothing. BLAS is
pinned to one thread by :func:`sumhe.cli.main` before numpy loads. Adding a benchmark is one line in
:data:`BENCHMARKS`.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import sys
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

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
    "calibrate": (
        "sumhe calibrate on realistic simulated drives against their true installation parameters",
        "sumhe.commands.bench:add_calibrate_arguments",
        "sumhe.commands.bench:run_calibrate",
    ),
    "live": (
        "the daemon in real time against a player process: output rate, end-to-end latency, CPU use",
        "sumhe.commands.bench:add_live_arguments",
        "sumhe.commands.bench:run_live",
    ),
    "load": (
        "the daemon against a player at 2x, 4x, 8x: output rate per second, degraded share, recovery",
        "sumhe.commands.bench:add_load_arguments",
        "sumhe.commands.bench:run_load",
    ),
    "soak": (
        "a day of simulated data replayed: resident memory after every hour, throughput",
        "sumhe.commands.soak:add_arguments",
        "sumhe.commands.soak:run",
    ),
    "protocol": (
        "paper 000's outage protocol: batch SU methods side by side (as sumhe protocol)",
        "sumhe.commands.protocol:add_arguments",
        "sumhe.commands.protocol:run",
    ),
    "fuzz": (
        "the NMEA and candump decoders on 10^6 fuzzed lines: lines/s, crashes (none expected)",
        "sumhe.commands.bench:add_fuzz_arguments",
        "sumhe.commands.bench:run_fuzz",
    ),
    "compare": (
        "two benchmark results (sumhe bench --out) outage by outage: how many got better, how many worse",
        "sumhe.commands.bench:add_compare_arguments",
        "sumhe.commands.bench:run_compare",
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


def add_fuzz_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--lines", type=int, default=1_000_000, metavar="N", help="lines in all (default 10^6)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="random seed (default 0)")


def run_fuzz(args: argparse.Namespace) -> int:
    from sumhe.bench import fuzz

    report = fuzz.run(args.lines, args.seed, progress=lambda text: print(text, file=sys.stderr, flush=True))
    print("\n".join(fuzz.lines(report, args.seed)))
    return 1 if report.crashes or report.problems else 0


def add_compare_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "before", metavar="BEFORE", help="peers.json or recorded.json of sumhe bench --out (or its DIR)"
    )
    parser.add_argument("after", nargs="?", metavar="AFTER", help="the same of the run to compare (default: BEFORE)")
    parser.add_argument(
        "--estimators",
        metavar="A[,B]",
        help="one estimator (in both), or two: A in BEFORE against B in AFTER (default: each estimator in both)",
    )
    parser.add_argument("--tolerance", type=float, default=0.05, metavar="M", help="a change smaller is none (m)")
    parser.add_argument("--top", type=int, default=10, metavar="N", help="the N largest changes listed (default 10)")


def run_compare(args: argparse.Namespace) -> int:
    """``sumhe bench compare``: :mod:`sumhe.bench.compare` on two results (files or the folders holding them)."""
    import json
    from pathlib import Path

    from sumhe.bench.compare import calibration_cells, calibration_lines, compare, lines, outage_errors, pick_names
    from sumhe.errors import ConfigError

    def read(text: str) -> tuple[dict[str, Any], dict[str, Any]]:
        path = Path(text)
        if path.is_dir():
            found = [path / n for n in ("peers.json", "recorded.json") if (path / n).is_file()]
            if not found:
                raise ConfigError(f"bench compare: {text}: no peers.json or recorded.json in it")
            path = found[0]
        try:
            result = json.loads(path.read_text(encoding="utf-8"))
            return outage_errors(result), calibration_cells(result)
        except (OSError, ValueError) as e:
            raise ConfigError(f"bench compare: {text}: {e}") from e

    for name, value in (("--tolerance", args.tolerance), ("--top", args.top)):
        if not value >= 0:
            raise ConfigError(f"bench compare: {name}: must be 0 or more, got {value!r}")
    before, cells_before = read(args.before)
    after, cells_after = read(args.after) if args.after else (before, cells_before)
    try:
        pairs = pick_names(before, after, _names(args.estimators or ""))
    except ValueError as e:
        raise ConfigError(f"bench compare: {e}") from e
    for k, (old, new) in enumerate(pairs):
        text = lines(compare(before[old], after[new], (old, new), args.tolerance, args.top))
        cells = calibration_lines(cells_before.get(old, {}), cells_after.get(new, {}), (old, new))
        print(("\n" if k else "") + "\n".join(text + (["", *cells] if cells else [])))
    return 0


def add_mhe_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="one seed, short latency runs, a 10 min replay")
    parser.add_argument("--solvers", help="comma-separated solvers to time (default sqp,ipopt,fatrop)")
    parser.add_argument("--parts", metavar="A,B", help="parts to run (default latency,accuracy,multipath,replay)")
    parser.add_argument(
        "--profile", metavar="A,B", help="simulator profiles of the accuracy part (default kind,realistic)"
    )


def run_mhe(args: argparse.Namespace) -> int:
    from sumhe.bench.mhe import MheBenchSettings
    from sumhe.bench.mhe_report import run_benchmark

    options = (("solvers", "solvers", _names), ("parts", "parts", _names), ("profile", "profiles", _names))
    bs = _with_options(MheBenchSettings.quick() if args.quick else MheBenchSettings(), "bench mhe", args, options)
    for line in run_benchmark(bs, lambda msg: print(msg, file=sys.stderr, flush=True)):
        print(line, flush=True)
    return 0


def add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="an urban and a highway drive of 300 s")
    parser.add_argument("--scenarios", metavar="A,B", help="simulated scenarios (default urban,highway,offroad)")
    parser.add_argument("--seeds", metavar="1,2,3", help="simulation seeds (default 1,2,3,4)")
    parser.add_argument("--duration", type=float, metavar="S", help="length of each drive (default 600 s)")


T = TypeVar("T")
Options = Sequence[tuple[str, str, Callable[[Any], Any]]]
"""Command-line options that change settings: (option, settings field, conversion of the option's value)."""


def _with_options(defaults: T, label: str, args: argparse.Namespace, options: Options) -> T:
    """``defaults`` (a settings dataclass) with the fields of ``options`` the command line gives; ConfigError
    naming ``label`` for a bad value (the settings validate themselves)."""
    from sumhe.errors import ConfigError

    try:
        changes = {key: convert(getattr(args, opt)) for opt, key, convert in options if getattr(args, opt) is not None}
        return dataclasses.replace(defaults, **changes)  # type: ignore[type-var]
    except ValueError as e:
        raise ConfigError(f"{label}: {e}") from e


def _seeds(text: str) -> tuple[int, ...]:
    return tuple(int(s) for s in _names(text))


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in _names(text))


def run_calibrate(args: argparse.Namespace) -> int:
    from sumhe.bench.calibrate import CalibrateBenchSettings, run_benchmark

    options = (("scenarios", "scenarios", _names), ("seeds", "seeds", _seeds), ("duration", "duration_s", float))
    bs = _with_options(
        CalibrateBenchSettings.quick() if args.quick else CalibrateBenchSettings(), "bench calibrate", args, options
    )
    for line in run_benchmark(bs, lambda msg: print(msg, file=sys.stderr, flush=True)):
        print(line, flush=True)
    return 0


def add_peers_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--quick", action="store_true", help="a short subset: a 120 s drive of each profile, 5/10/30 s outages"
    )
    parser.add_argument("--estimators", metavar="A,B", help="comma-separated estimators (default: every registered)")
    parser.add_argument("--profile", metavar="A,B", help="simulator profiles (default kind,realistic)")
    parser.add_argument("--scenarios", metavar="A,B", help="simulated scenarios (default urban,highway,offroad)")
    parser.add_argument("--gps-errors", metavar="A,B", help="GPS error models (default uniform,gaussian,walk)")
    parser.add_argument("--seeds", metavar="1,2,3", help="simulation seeds (default 1,2,3)")
    parser.add_argument("--duration", type=float, metavar="S", help="length of each simulated drive (default 240 s)")
    parser.add_argument(
        "--drive",
        nargs="+",
        action="append",
        default=[],
        metavar="DIR_OR_LOGS",
        help="instead of simulated drives, a recorded one without a reference: a folder (drive.log, drive.nmea, "
        "config.toml, truth.csv if any) or its log files (MF4, candump, ... and *.nmea); 10/30/60 s outages placed "
        "on it, every live estimator and two dead-reckoning floors against the fixes removed (repeat for more)",
    )
    parser.add_argument("--lengths", metavar="10,30,60", help="with --drive: outage lengths (s)")
    parser.add_argument("--config", metavar="FILE", help="TOML config: the vehicle's CAN mapping, estimator settings")
    parser.add_argument("--timeout", type=float, metavar="S", help="time limit of one run (s); beyond it: failed")
    parser.add_argument("--out", metavar="DIR", help="write peers.json and peers.md into DIR")


def _names(text: str) -> tuple[str, ...]:
    return tuple(s.strip() for s in text.split(",") if s.strip())


def _peers_settings(args: argparse.Namespace) -> Any:
    from sumhe.bench.drives import PeersSettings
    from sumhe.errors import ConfigError

    options = (
        ("estimators", "estimators", _estimators),
        ("scenarios", "scenarios", _names),
        ("gps_errors", "gps_errors", _names),
        ("profile", "profiles", _names),
        ("seeds", "seeds", _seeds),
        ("duration", "duration_s", float),
        ("timeout", "timeout_s", float),
    )
    ps = _with_options(PeersSettings.quick() if args.quick else PeersSettings(), "bench", args, options)
    if ps.drive_count() == 0:
        raise ConfigError("bench: no drives to run")
    return ps


def _estimators(text: str) -> tuple[str, ...]:
    from sumhe.errors import ConfigError
    from sumhe.estimator.registry import estimator_names

    names = _names(text)
    unknown = [n for n in names if n not in estimator_names()]
    if unknown:
        raise ConfigError(f"--estimators: unknown {', '.join(unknown)} (known: {', '.join(estimator_names())})")
    return names


def _command_line(args: argparse.Namespace) -> str:
    parts = ["sumhe bench"]
    if args.quick:
        parts.append("--quick")
    for option in ("estimators", "profile", "scenarios", "gps_errors", "seeds", "duration", "config", "timeout", "out"):
        value = getattr(args, option)
        if value is not None:
            parts.append(f"--{option.replace('_', '-')} {value}")
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
    from sumhe.bench.report import calibration_table, how_it_ran, main_table, markdown, profile_title, summarise
    from sumhe.commands.candump import reference_config
    from sumhe.config import load_config

    if args.drive:
        return run_recorded(args)
    ps = _peers_settings(args)
    base = load_config(args.config) if args.config else reference_config()
    bar = _ProgressBar(ps.drive_count() * len(ps.names()))
    try:
        report = run_bench(ps, base, bar)
    finally:
        bar.close()
    summary = summarise(report, _command_line(args))
    lines = how_it_ran(summary)
    for profile in summary["profiles"]:
        lines += ["", profile_title(profile, summary), "", *main_table(summary, profile)]
        lines += ["", "error estimates and bound boxes:", "", *calibration_table(summary, profile)]
    for line in lines:
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


def run_recorded(args: argparse.Namespace) -> int:
    """``sumhe bench --drive ...``: the recorded-drive bench (:mod:`sumhe.bench.recorded`)."""
    import json
    from pathlib import Path

    from sumhe.bench.recorded import RecordedBenchSettings, load_recording, markdown, run_recording, summary
    from sumhe.commands.candump import reference_config

    options = (
        ("estimators", "estimators", _estimators),
        ("lengths", "lengths_s", _floats),
        ("timeout", "timeout_s", float),
    )
    bs = _with_options(RecordedBenchSettings(), "bench --drive", args, options)
    out = []
    for spec in args.drive:
        recording = load_recording(spec, args.config, reference_config)
        data = summary(recording, run_recording(recording, bs, lambda m: print(m, file=sys.stderr, flush=True)))
        out.append(data)
        for line in markdown(data):
            print(line, flush=True)
    if args.out:
        path = Path(args.out)
        path.mkdir(parents=True, exist_ok=True)
        (path / "recorded.json").write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
        (path / "recorded.md").write_text("\n".join(line for d in out for line in markdown(d)) + "\n", encoding="utf-8")
        print(f"wrote {path / 'recorded.json'} and {path / 'recorded.md'}", file=sys.stderr)
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


def add_load_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=60.0, metavar="S", help="length of the drive (default 60 s)")
    parser.add_argument("--estimator", default="mhe", metavar="NAME", help="estimator the daemon runs (default mhe)")
    parser.add_argument(
        "--speeds", type=float, nargs="+", default=[2.0, 4.0, 8.0], metavar="X", help="player speeds (default 2 4 8)"
    )


def run_load(args: argparse.Namespace) -> int:
    from sumhe.bench.load import format_load, run_load

    figs = run_load(args.duration, args.estimator, args.speeds)
    print(format_load(figs, args.estimator, args.duration), flush=True)
    return 0
