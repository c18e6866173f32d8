"""``sumhe fleet DRIVE... --out DIR``: reprocess recorded drives on Ray, each through one or more estimators.

DRIVE is a drive folder or a manifest (see :mod:`sumhe.bench.fleet`). A local Ray instance with ``--workers``
processes (default: every core) starts unless ``--address`` names a running cluster (``auto``, or
``ray://HEAD:10001`` for Ray Client). Each worker is an actor that keeps the estimators it has built and reuses
them drive after drive; one task per drive and estimator, the biggest drives first. A failing drive is reported
(its reason in the table) and never stops the fleet; a worker that dies is replaced and its task reported failed.
Tasks finished before (their record in ``OUT`` says ok) are skipped: run the same command again to finish a fleet.
Out: ``OUT/<drive>/<estimator>.jsonl`` (estimates) and ``.json`` (the drive's summary), ``OUT/summary.csv`` and
the table on stdout, a progress bar and the fleet's throughput on stderr.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any

from tqdm import tqdm

from sumhe.bench.fleet import (
    FleetWorker,
    Task,
    failure_record,
    find_drives,
    format_table,
    make_tasks,
    read_record,
    table_row,
    write_record,
    write_table,
)
from sumhe.commands.options import add_outage_option
from sumhe.errors import ConfigError
from sumhe.estimator.registry import estimator_names

FLEET_EXTRA = "pip install 'sumhe[fleet]'"
WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""One BLAS thread per worker: the workers are the parallelism."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("drives", nargs="+", metavar="DRIVE", help="drive folders or manifests (one drive a line)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (finished drives are skipped)")
    parser.add_argument("--address", metavar="ADDRESS", help="a running Ray cluster (auto, ray://HOST:10001)")
    parser.add_argument("--workers", type=int, metavar="N", help="worker actors (default: the cluster's CPUs)")
    parser.add_argument(
        "--estimators", metavar="NAMES", help="comma-separated estimator names (default: estimator.name)"
    )
    add_outage_option(parser, "--outages", "each drive's first frame")
    parser.add_argument("--config", metavar="FILE", help="TOML config of the fleet (each drive's config.toml over it)")


def run(args: argparse.Namespace) -> int:
    try:
        import ray
    except ImportError as e:
        raise ConfigError(f"sumhe fleet runs on Ray: {FLEET_EXTRA}") from e
    if args.workers is not None and args.workers < 1:
        raise ConfigError("--workers: must be at least 1")
    estimators = _estimators(args)
    drives = find_drives(args.drives)
    if not drives:
        raise ConfigError("no drives given")
    config = os.path.abspath(args.config) if args.config else None
    tasks = make_tasks(drives, estimators, config, args.outages, os.path.abspath(args.out))
    todo = [t for t in tasks if (read_record(t) or {}).get("status") != "ok"]
    print(
        f"fleet: {len(drives)} drives x {len(estimators)} estimators; {len(tasks) - len(todo)} finished before, "
        f"{len(todo)} to run",
        file=sys.stderr,
    )
    if todo:
        started = time.perf_counter()
        _init_ray(ray, args)
        workers = args.workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        up = time.perf_counter() - started
        wall0 = time.perf_counter()
        records = _dispatch(ray, todo, workers)
        wall = time.perf_counter() - wall0
        ray.shutdown()
        data_s = sum(r.get("span_s") or 0.0 for r in records)
        print(
            f"fleet: {sum(r['status'] == 'ok' for r in records)} of {len(records)} tasks ok on {workers} workers; "
            f"{data_s / 3600:.2f} h of data in {wall:.1f} s ({data_s / max(wall, 1e-9):.0f}x real time; "
            f"Ray start-up {up:.1f} s)",
            file=sys.stderr,
        )
    rows = [table_row(read_record(t) or failure_record(t, "no record")) for t in tasks]
    write_table(rows, Path(args.out) / "summary.csv")
    print(format_table(rows))
    return 0 if all(r["status"] == "ok" for r in rows) else 1


def _estimators(args: argparse.Namespace) -> list[str]:
    if args.estimators:
        names = [n.strip() for n in args.estimators.split(",") if n.strip()]
    else:
        from sumhe.config import load_config

        names = [load_config(args.config).estimator.name]
    known = estimator_names()
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise ConfigError(f"--estimators: unknown {', '.join(unknown) or '(none)'} (known: {', '.join(known)})")
    return names


def _init_ray(ray: Any, args: argparse.Namespace) -> None:
    env = {"env_vars": WORKER_ENV}
    if args.address:
        ray.init(address=args.address, runtime_env=env, log_to_driver=False)
    else:
        cpus = args.workers or os.cpu_count() or 1
        ray.init(num_cpus=cpus, include_dashboard=False, runtime_env=env, log_to_driver=False)


def _dispatch(ray: Any, tasks: list[Task], workers: int) -> list[dict[str, Any]]:
    """Hand the tasks to ``workers`` actors, one at a time each; replace an actor that dies."""
    actor = ray.remote(num_cpus=1)(FleetWorker)
    idle = [actor.remote() for _ in range(min(workers, len(tasks)))]
    queue, running, records = deque(tasks), {}, []
    with tqdm(total=len(tasks), unit="drive", file=sys.stderr, disable=None) as bar:
        while queue or running:
            while idle and queue:
                a, task = idle.pop(), queue.popleft()
                running[a.run.remote(task)] = (a, task)
            [ref], _ = ray.wait(list(running), num_returns=1)
            a, task = running.pop(ref)
            try:
                record = ray.get(ref)
            except ray.exceptions.RayError as e:  # the worker process died (crash, out of memory, node lost)
                record = failure_record(task, f"worker died: {type(e).__name__}")
                write_record(task, record)
                a = actor.remote()
            idle.append(a)
            records.append(record)
            data_h = sum(r.get("span_s") or 0.0 for r in records) / 3600
            bar.set_postfix_str(f"{data_h:.2f} h of data, {sum(r['status'] != 'ok' for r in records)} failed")
            bar.update(1)
    return records
