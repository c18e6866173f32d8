"""``sumhe replay LOG [LOG ...] [--nmea NMEALOG ...] --config FILE``: run an estimator on a recorded drive.

The CAN logs (candump, MF4, ...; several files of one drive in any order: shell globs welcome) and, with
``gps.source = "nmea"``, the NMEA logs are merged in time order (:class:`~sumhe.io.replay.RecordedDrive`). Writes
the same JSON objects the UDP output sends, one line per estimate, to ``--out`` (default stdout), and a summary to
stderr: samples, estimates, dropped samples, solve times, speed against real time, the estimates' modes (share of
epochs solved on widened bounds and of solver failures), the estimator's counters, and with ``--outage
START+LEN ...`` the errors against the fixes removed in those windows (START in seconds from the drive's first
CAN frame; :mod:`sumhe.bench.outages`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import TextIO

from sumhe.bench.outages import (
    MAX_INTERPOLATION_GAP_S,
    FixCut,
    ModeShares,
    OutageErrors,
    mode_shares,
    outage_errors,
    outage_windows,
)
from sumhe.commands.candump import reference_config
from sumhe.commands.simulate import outage
from sumhe.config import Config, load_config, require_signals
from sumhe.errors import ConfigError
from sumhe.estimator.registry import make_estimator
from sumhe.io.replay import RecordedDrive
from sumhe.io.udp import estimate_to_json
from sumhe.messages import Estimate
from sumhe.service.app import percentile
from sumhe.service.pipeline import Pipeline


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
    parser.add_argument(
        "--outage",
        nargs="+",
        action="extend",
        type=outage,
        default=[],
        metavar="START+LEN",
        help="remove the fixes of these windows (s from the first CAN frame) and report the errors against them",
    )


def check_gps_source(config: Config, nmea_logs: list[str] | None) -> None:
    """ConfigError when the NMEA logs given do not fit ``gps.source``."""
    if config.gps.source == "nmea" and not nmea_logs:
        raise ConfigError(
            f"{config.source}: gps.source = 'nmea': give the NMEA logs with --nmea (or set [gps] source = 'can')"
        )
    if config.gps.source == "can" and nmea_logs:
        raise ConfigError(f"{config.source}: gps.source = 'can': the fixes come from the CAN logs; drop --nmea")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config) if args.config else reference_config()
    require_signals(config)
    check_gps_source(config, args.nmea)
    drive = RecordedDrive(config, args.logs, args.nmea, args.offset)
    estimator = make_estimator(args.estimator or config.estimator.name, drive.config)
    pipeline = Pipeline(drive.config, estimator)
    t0 = drive.first_t
    try:
        cut = FixCut(outage_windows(args.outage, t0 if math.isfinite(t0) else 0.0))
    except ValueError as e:
        raise ConfigError(f"--outage: {e}") from e
    written = _Written(cut.windows)
    first_t = last_t = None
    wall0 = time.perf_counter()
    out_ctx = open(args.out, "w", encoding="utf-8") if args.out else nullcontext(sys.stdout)  # noqa: SIM115
    with out_ctx as out:
        for sample in drive.samples():
            first_t = sample.t if first_t is None else first_t
            last_t = sample.t
            if cut.keep(sample):
                written.write(out, pipeline.push(sample))
        written.write(out, pipeline.finish())
    wall = time.perf_counter() - wall0
    span = (last_t - first_t) if first_t is not None and last_t is not None else 0.0
    ts, ps = pipeline.guard.stats, pipeline.stats
    lines = [
        f"replay: {estimator.name}: {ps.fixes} fixes ({ps.valid_fixes} valid), {ps.can_samples} CAN samples, "
        f"{ps.estimates} estimates; dropped late {ts.late}, duplicate {ts.duplicate}, zero time {ts.zero_time}, "
        f"clock resets {ts.clock_resets}; "
        f"solve p50/p99 {percentile(written.solve_ms, 50):.2f}/{percentile(written.solve_ms, 99):.2f} ms; "
        f"{span:.0f} s of data in {wall:.1f} s ({span / max(wall, 1e-9):.0f}x real time)",
        _modes_line(mode_shares(written.modes.elements())),
        "estimator: "
        + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in estimator.stats().items()),
        *_input_lines(drive),
    ]
    if cut.windows:
        per_window, overall = outage_errors(cut.windows, cut.removed, written.t, written.lat, written.lon)
        lines.append("errors against the removed fixes (m):")
        lines += [_errors_line(f"{e.start - t0:g}+{e.end - e.start:g}", e) for e in per_window]
        lines.append(_errors_line("all", overall))
    print("\n".join(lines), file=sys.stderr)
    return 0


@dataclass
class _Written:
    """Writes estimates as JSON lines and keeps what the summary needs in bounded memory: solve times (ms), the
    count of each mode, and the times and positions of the estimates near the outage ``windows`` (absolute, s)."""

    windows: Sequence[tuple[float, float]]
    solve_ms: list[float] = field(default_factory=list)
    modes: Counter[str] = field(default_factory=Counter)
    t: list[float] = field(default_factory=list)
    lat: list[float] = field(default_factory=list)
    lon: list[float] = field(default_factory=list)

    def write(self, out: TextIO, estimates: list[Estimate]) -> None:
        margin = MAX_INTERPOLATION_GAP_S
        for est in estimates:
            if est.solve_ms > 0:
                self.solve_ms.append(est.solve_ms)
            self.modes[est.mode] += 1
            if any(start - margin <= est.t <= end + margin for start, end in self.windows):
                self.t.append(est.t)
                self.lat.append(est.lat_deg)
                self.lon.append(est.lon_deg)
            out.write(json.dumps(estimate_to_json(est), separators=(",", ":")) + "\n")


def _modes_line(shares: ModeShares) -> str:
    modes = ", ".join(f"{m} {n}" for m, n in sorted(shares.modes.items()))
    return (
        f"modes: {modes or 'none'}; of {shares.epochs} epoch estimates {100 * shares.widened_share:.1f} % on widened "
        f"bounds, {100 * shares.failed_share:.1f} % solver failures (prediction)"
    )


def _input_lines(drive: RecordedDrive) -> list[str]:
    """What the logs gave: files and frames, GNSS epochs from CAN, and mapped quantities that gave nothing."""
    ls = drive.log_stats
    out = []
    if drive.decoder is not None:
        ds = drive.decoder.stats
        out.append(
            f"CAN: {ls.files} files, {ds.frames} frames; unused {ds.unused}, other multiplexer values {ds.other_mux}, "
            f"flagged invalid {ds.invalid}, decode errors {ds.decode_errors}, malformed {ls.malformed}"
            + (f"; ended early: {ls.error}" if ls.error else "")
        )
        if drive.decoder.gnss is not None:
            gs = drive.decoder.gnss.stats
            out.append(
                f"GNSS from CAN: {gs.fixes} fixes ({gs.valid_fixes} valid), incomplete epochs {gs.incomplete}, "
                f"epochs without position {gs.no_position}, values out of range {gs.bad_values}"
            )
        out += [f"warning: {line}" for line in drive.decoder.silent()]
    return out


def _errors_line(label: str, e: OutageErrors) -> str:
    return f"  {label}: {e.scored} of {e.fixes} fixes; mean {e.mean_m:.2f}, p95 {e.p95_m:.2f}, max {e.max_m:.2f}"
