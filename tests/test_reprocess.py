"""The shared replay loop: bounded histograms, counter deltas, and the CAN quantities a replay decodes."""

from __future__ import annotations

import gc
import io
import json
import math

import numpy as np
import pytest

from sumhe.bench.metrics import percentiles
from sumhe.bench.reprocess import counter_deltas, replay_drive
from sumhe.estimator.registry import estimator_names, make_estimator
from sumhe.frontend.can import CAN_USED
from sumhe.io.can import reference_config
from sumhe.io.replay import RecordedDrive
from sumhe.service.histogram import Histogram
from sumhe.sim import SimSettings, simulate, write_drive


def test_histogram_percentiles_mean_and_max_in_fixed_memory():
    rng = np.random.default_rng(0)
    values = rng.lognormal(0.0, 1.0, 20_000)
    h = Histogram()
    for v in values:
        h.add(float(v))
    h.add(math.nan)  # not counted
    assert h.n == values.size and h.counts.size == 900
    assert h.mean == pytest.approx(values.mean()) and h.max == values.max()
    for q, exact in zip((50.0, 99.0), percentiles(values, (50.0, 99.0)), strict=True):
        assert h.percentile(q) == pytest.approx(exact, rel=0.025)
    assert math.isnan(Histogram().percentile(50.0)) and math.isnan(Histogram().mean)


def test_counter_deltas_subtract_counters_only():
    before = {"estimator": "mhe", "window": 40, "period_s": 0.1, "epochs": 100, "solves": 90}
    after = {"estimator": "mhe", "window": 50, "period_s": 0.2, "epochs": 150, "solves": 130, "widened": 3}
    assert counter_deltas(before, after) == {
        "estimator": "mhe",
        "window": 50,
        "period_s": 0.2,
        "epochs": 50,
        "solves": 40,
        "widened": 3,
    }


@pytest.mark.slow
@pytest.mark.parametrize("name", estimator_names())
def test_every_estimator_reads_only_the_can_inputs(tmp_path, name):
    """A replay decodes only CAN_USED: every estimator must give the same estimates without the other
    quantities (an estimator that starts reading another one must have it added to CAN_USED)."""
    write_drive(simulate(SimSettings(seed=4, duration_s=20.0)), tmp_path)
    config = reference_config()
    assert set(config.can.signals) > set(CAN_USED)
    runs = []
    for quantities in (None, CAN_USED):
        drive = RecordedDrive(config, tmp_path / "drive.log", tmp_path / "drive.nmea", quantities=quantities)
        out = io.StringIO()
        summary = replay_drive(drive, make_estimator(name, drive.config), out=out)
        estimates = [
            {k: v for k, v in json.loads(line).items() if k != "solve_ms"} for line in out.getvalue().splitlines()
        ]
        runs.append((estimates, summary.can_samples))
    (every, every_samples), (inputs, input_samples) = runs
    assert every == inputs and len(every) > 10
    assert input_samples < every_samples


def test_an_interrupted_replay_keeps_what_it_estimated(tmp_path):
    """The lines are written in batches; a replay stopped part way (here by its progress callback, at 60 s of
    data) still writes every estimate let through before it stopped."""
    write_drive(simulate(SimSettings(seed=4, duration_s=90.0)), tmp_path)
    config = reference_config()
    out = io.StringIO()

    def stop_at_a_minute(done_s: float) -> None:
        if done_s >= 60.0:
            raise KeyboardInterrupt

    drive = RecordedDrive(config, tmp_path / "drive.log", tmp_path / "drive.nmea")
    with pytest.raises(KeyboardInterrupt):
        replay_drive(drive, make_estimator("ekf", config), out=out, progress=stop_at_a_minute)
    times = [json.loads(line)["t"] for line in out.getvalue().splitlines()]
    assert len(times) > 2000  # ~50 a second for a minute: more than one batch's worth of samples read ahead
    assert times[-1] - times[0] > 55.0
    assert gc.get_freeze_count() == 0  # what the loop froze is handed back to the collector, interrupted too


def test_a_replay_leaves_the_callers_frozen_objects_frozen(tmp_path):
    """The loop freezes what was made before it only where nothing is frozen yet, and unfreezes only that."""
    write_drive(simulate(SimSettings(seed=4, duration_s=5.0)), tmp_path)
    config = reference_config()
    drive = RecordedDrive(config, tmp_path / "drive.log", tmp_path / "drive.nmea")
    gc.freeze()
    try:
        replay_drive(drive, make_estimator("ekf", config))
        assert gc.get_freeze_count() > 0  # (objects freed since leave the count)
    finally:
        gc.unfreeze()
