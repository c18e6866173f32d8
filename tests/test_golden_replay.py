"""Golden replay regression: the bundled drive's first 80 s (a 15 s outage at 52 s) through every live estimator,
as ``sumhe replay`` runs it (:class:`~sumhe.service.pipeline.Pipeline`), against estimates checked in under
``tests/data/golden/``.

The GNSS-epoch estimates (t, east, north, azimuth, speed, yaw rate, gps, mode) must match within the tolerances
below, and the number of estimates (epochs and CAN rate) exactly: a change of behaviour, not only a large one,
shows. When a change is meant, regenerate the files and say why in the commit::

    SUMHE_WRITE_GOLDEN=1 .venv/bin/pytest tests/test_golden_replay.py
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
import pytest

from sumhe.commands.candump import reference_config
from sumhe.config import PACKAGE_DATA
from sumhe.estimator.registry import estimator_names, make_estimator
from sumhe.io.replay import log_samples
from sumhe.messages import Estimate, GnssFix
from sumhe.service.pipeline import Pipeline

GOLDEN = Path(__file__).parent / "data" / "golden"
DRIVE = PACKAGE_DATA / "drive"
SPAN_S = 80.0
TOLERANCE = {"east": 0.02, "north": 0.02, "azimuth": 0.002, "speed": 0.01, "yaw_rate": 0.002}
"""Absolute tolerances (m, rad, m/s, rad/s): far below any real change, above floating-point noise between
machines (BLAS, CasADi and OSQP builds)."""
COLUMNS = ("t", "east", "north", "azimuth", "speed", "yaw_rate", "gps", "mode")


def replay(name: str) -> tuple[list[Estimate], int]:
    """The estimates of the GNSS epochs (the estimates whose time is no CAN sample's) and the count of all."""
    config = reference_config()
    pipeline = Pipeline(config, make_estimator(name, config))
    t0 = None
    epochs, count = [], 0
    for sample in log_samples(config, DRIVE / "drive.log", DRIVE / "drive.nmea"):
        t0 = sample.t if t0 is None else t0
        if sample.t > t0 + SPAN_S:
            break
        out = pipeline.push(sample)
        count += len(out)
        epochs += [e for e in out if isinstance(sample, GnssFix) or e.t != sample.t]
    return epochs, count


def rows(estimates: list[Estimate], t0: float) -> list[dict[str, str]]:
    return [
        {
            "t": f"{e.t - t0:.3f}",
            "east": f"{e.east_m:.4f}",
            "north": f"{e.north_m:.4f}",
            "azimuth": f"{e.track_rad:.5f}",
            "speed": f"{e.speed_mps:.4f}",
            "yaw_rate": f"{e.yaw_rate_rps:.5f}",
            "gps": e.gps,
            "mode": e.mode,
        }
        for e in estimates
    ]


def first_time() -> float:
    return next(iter(log_samples(reference_config(), DRIVE / "drive.log", DRIVE / "drive.nmea"))).t


@pytest.mark.parametrize("name", estimator_names(live_only=True))
def test_replay_matches_the_golden_estimates(name: str) -> None:
    epochs, count = replay(name)
    new = rows(epochs, first_time())
    path = GOLDEN / f"{name}.csv"
    if os.environ.get("SUMHE_WRITE_GOLDEN"):
        GOLDEN.mkdir(parents=True, exist_ok=True)
        with path.open("w", newline="", encoding="utf-8") as f:
            f.write(f"# {name} on the bundled drive's first {SPAN_S:g} s: {count} estimates, these at GNSS epochs\n")
            writer = csv.DictWriter(f, COLUMNS)
            writer.writeheader()
            writer.writerows(new)
        pytest.skip(f"wrote {path}")
    assert path.is_file(), f"no golden file {path} (see the module docstring)"
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0] == f"# {name} on the bundled drive's first {SPAN_S:g} s: {count} estimates, these at GNSS epochs"
    old = list(csv.DictReader(lines[1:]))
    assert len(new) == len(old)
    for key in ("t", "gps", "mode"):
        changed = [(o["t"], o[key], n[key]) for o, n in zip(old, new, strict=True) if o[key] != n[key]]
        assert not changed, f"{key} changed at (t, golden, now): {changed[:5]}"
    for key, tol in TOLERANCE.items():
        golden = np.array([float(o[key]) for o in old])
        now = np.array([float(n[key]) for n in new])
        diff = np.abs(now - golden)
        if key == "azimuth":
            diff = np.minimum(diff, 2 * math.pi - diff)
        worst = int(np.argmax(diff))
        assert diff[worst] <= tol, f"{key} off by {diff[worst]:.4g} at t = {old[worst]['t']} s"
