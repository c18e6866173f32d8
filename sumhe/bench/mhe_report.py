"""The report of ``sumhe bench mhe`` (:mod:`sumhe.bench.mhe` runs the parts): latency, accuracy, multipath and
replay lines, the MHE's ratios to its baselines."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from sumhe.bench.metrics import mean_p95_max
from sumhe.bench.mhe import (
    CORRELATED_GPS_ERRORS,
    MheBenchSettings,
    Progress,
    accuracy_drive,
    drive_stream,
    environment,
    latency_run,
    outage_latency_run,
    outage_plan,
    position_errors,
    replay_run,
    run_stream,
)
from sumhe.config import Config
from sumhe.errors import SumheError
from sumhe.estimator.mhe import MovingHorizonEstimator
from sumhe.estimator.registry import make_estimator
from sumhe.sim import SimSettings, simulate

log = logging.getLogger(__name__)


def multipath_report(bs: MheBenchSettings, say: Progress) -> list[str]:
    """Error of every estimate (m) on drives with multipath jumps (5-50 m for 1-10 s) and white GNSS errors:
    what the gates let through."""
    names = ["mhe", *bs.baselines]
    pooled: dict[str, list[NDArray]] = {n: [] for n in names}
    config = Config.of(bs.estimator)
    for scenario in bs.scenarios:
        say(f"multipath {scenario}")
        sim = SimSettings(
            scenario=scenario,
            seed=bs.seeds[0],
            duration_s=bs.duration_s,
            gps_error="gaussian",
            multipath_per_min=bs.multipath_per_min,
        )
        drive = simulate(sim)
        stream = drive_stream(drive)
        for name in names:
            try:
                est = MovingHorizonEstimator(bs.estimator) if name == "mhe" else make_estimator(name, config)
            except SumheError as e:
                log.warning("baseline %s not available: %s", name, e)
                continue
            pooled[name].append(position_errors(drive, run_stream(est, stream).estimates)[1])
    lines = [
        f"multipath: {bs.multipath_per_min:g} jumps per minute of 5-50 m lasting 1-10 s, white GNSS errors, "
        f"{len(bs.scenarios)} drives of {bs.duration_s:.0f} s; error of every estimate (m):"
    ]
    for name in names:
        if pooled[name]:
            mean, p95, mx = mean_p95_max(np.concatenate(pooled[name]))
            lines.append(f"    {name:15s} mean {mean:6.2f}  p95 {p95:6.2f}  max {mx:6.2f}")
    return lines


# ---- the report ----------------------------------------------------------------------------------------------------


def run_benchmark(bs: MheBenchSettings, progress: Progress | None = None) -> list[str]:
    """Run the parts ``bs.parts``; the report's lines."""
    say = progress or (lambda _msg: None)
    lines = [f"sumhe bench mhe: {environment()}"]
    s = bs.estimator
    m = s.estimator.mhe
    lines.append(
        f"MHE: solver {m.solver}, N={m.steps} N_B={m.steps_before} N_A={m.steps_after} "
        f"N_max={m.max_steps} (merge up to {m.max_merge}x), model {s.estimator.model}/{s.estimator.discretisation}, "
        f"step {s.gnss.period_s} s, GNSS speed over ground {'used' if s.gnss.use_speed else 'not used'}"
    )
    if "latency" in bs.parts:
        lines += ["", *_latency_report(bs, say)]
    if "accuracy" in bs.parts:
        lines += ["", _accuracy_report(bs, say)]
    if "multipath" in bs.parts:
        lines += ["", *multipath_report(bs, say)]
    if "replay" in bs.parts and bs.replay_s > 0:
        lines += ["", _replay_line(bs, say)]
    return lines


def _latency_report(bs: MheBenchSettings, say: Progress) -> list[str]:
    s = bs.estimator
    lines = [f"latency per GNSS epoch, window full (ms; load average {os.getloadavg()[0]:.1f}):"]
    head = ("solver", "N", "epochs", "p50", "p99", "max", "iter/solve")
    lines.append("  {:8s} {:>4s} {:>6s} {:>8s} {:>8s} {:>8s} {:>10s} banded".format(*head))
    for solver in bs.solvers:
        for n in bs.window_sizes:
            say(f"latency {solver} N={n}")
            max_epochs = bs.nlp_latency_epochs if solver != "sqp" else None
            try:
                r = latency_run(solver, n, bs.latency_s, s, max_epochs)
            except SumheError as e:
                lines.append(f"  {solver:8s} {n:4d} failed: {e}")
                continue
            lines.append(
                f"  {solver:8s} {n:4d} {r['epochs']:6.0f} {r['p50']:8.2f} {r['p99']:8.2f} {r['max']:8.2f} "
                f"{r['iterations']:10.1f} {100 * r['banded']:5.0f} %"
            )
            say(lines[-1])
    say("latency through a 30 s outage")
    r = outage_latency_run("sqp", s)
    lines.append(
        f"  sqp through a 30 s outage (N={s.estimator.mhe.steps} -> {r['window']:.0f} steps), epochs with >= "
        f"{0.9 * s.estimator.mhe.max_steps:.0f} steps: p50 {r['p50']:.2f} p99 {r['p99']:.2f} max {r['max']:.2f} ms "
        f"({r['epochs']:.0f} epochs)"
    )
    return lines


def _replay_line(bs: MheBenchSettings, say: Progress) -> str:
    say(f"replay of {bs.replay_s:.0f} s")
    r = replay_run(bs.replay_s, bs.estimator)
    return (
        f"replay: {r['span_s']:.0f} s of simulated data ({r['samples']:.0f} samples, {r['estimates']:.0f} "
        f"estimates) in {r['wall_s']:.1f} s = {r['speed']:.0f}x real time ({r['cpu_s']:.1f} s of CPU = "
        f"{r['cpu_speed']:.0f}x on a core of its own; load average {r['load']:.1f} on {os.cpu_count()} CPUs); "
        f"epoch update p50 {r['epoch_p50']:.2f} ms, p99 {r['epoch_p99']:.2f} ms; "
        f"banded solves {100 * r['banded']:.0f} %, fallbacks {r['fallbacks']:.0f}"
    )


def _accuracy_report(bs: MheBenchSettings, say: Progress) -> str:
    lines = [
        "accuracy: error of the newest state inside outages (m), all estimates (GNSS epochs and CAN rate); "
        f"{len(bs.scenarios)} scenarios x {len(bs.seeds)} seeds, {bs.duration_s:.0f} s drives, CAN delay "
        f"calibrated ({bs.estimator.can.delay_s} s) for every estimator"
    ]
    for gps_error in bs.gps_errors:
        lines.append(f" GNSS errors {gps_error!r}:")
        lines += _accuracy_lines(bs, gps_error, say)
    return "\n".join(lines)


def _accuracy_lines(bs: MheBenchSettings, gps_error: str, say: Progress) -> list[str]:
    lines: list[str] = []
    names = ["mhe", *bs.baselines]
    for length in bs.outage_lengths_s:
        pooled: dict[str, list[NDArray]] = {n: [] for n in names}
        pooled_net: dict[str, list[NDArray]] = {n: [] for n in names}
        smoothed: list[float] = []
        batch: list[float] = []
        count = 0
        for scenario in bs.scenarios:
            for seed in bs.seeds:
                say(f"accuracy {scenario} seed {seed} {gps_error} outages {length:.0f} s")
                r = accuracy_drive(scenario, seed, gps_error, length, bs, say)
                errs, net = r["errors"], r["net"]
                assert isinstance(errs, dict) and isinstance(net, dict)
                for n in names:
                    if n in errs:
                        pooled[n].append(errs[n])
                        pooled_net[n].append(net[n])
                smoothed += list(r["smoothed"])  # type: ignore[call-overload]
                batch += list(r["batch"])  # type: ignore[call-overload]
                count += len(outage_plan(bs.duration_s, length, bs.recover_s))
        lines.append(f"  outages of {length:.0f} s ({count} outages):")
        lines += _compare(pooled, bs.baselines, "")
        if gps_error in CORRELATED_GPS_ERRORS:
            lines.append(f"   net of the GNSS offset at the outage start (mean error of its last {bs.before} fixes):")
            lines += _compare(pooled_net, bs.baselines, "  ")
        if smoothed:
            ok = [(a, b) for a, b in zip(smoothed, batch, strict=False) if math.isfinite(b)]
            if ok:
                sm, bt = np.mean([a for a, _ in ok]), np.mean([b for _, b in ok])
                lines.append(
                    f"    after the outage ({bs.after} epochs back): MHE smoothed window over the outage mean "
                    f"{sm:.2f} m vs batch {bt:.2f} m ({sm / bt:.2f}x, {len(ok)} outages)"
                )
    return lines


def _compare(pooled: dict[str, list[NDArray]], baselines: Sequence[str], indent: str) -> list[str]:
    """Mean/p95/max per estimator and the MHE's ratios to each baseline."""
    lines = []
    means = {}
    for n, parts in pooled.items():
        if not parts:
            lines.append(f"    {indent}{n:15s} not available")
            continue
        mean, p95, mx = mean_p95_max(np.concatenate(parts))
        means[n] = (mean, p95)
        lines.append(f"    {indent}{n:15s} mean {mean:6.2f}  p95 {p95:6.2f}  max {mx:6.2f}")
    for ref in baselines:
        if ref in means and "mhe" in means:
            lines.append(
                f"    {indent}mhe / {ref}: mean {means['mhe'][0] / means[ref][0]:.2f}x, p95 "
                f"{means['mhe'][1] / means[ref][1]:.2f}x"
            )
    return lines
