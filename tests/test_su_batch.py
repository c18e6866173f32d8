import dataclasses
import itertools
import math

import numpy as np
import pytest

from sumhe.config import load_config
from sumhe.estimator.batch import estimate_batch
from sumhe.estimator.registry import make_estimator
from sumhe.estimator.su_batch import seam, state_noise_volume, window_bounds
from sumhe.io.fixtime import stamp_fix
from sumhe.messages import CanSample
from sumhe.service.pipeline import Pipeline
from sumhe.sim import SimSettings, simulate


def test_window_bounds_overlap_and_never_end_inside_an_outage():
    t_gps = np.r_[np.arange(0.0, 30.0, 0.1), np.arange(45.0, 100.0, 0.1)]  # an outage 30-45 s
    wins = window_bounds(t_gps, 100.0, length_s=20.0, overlap_s=4.0)
    assert wins[0][0] == 0.0 and wins[-1][1] == pytest.approx(100.0)
    for (_, e0), (s1, _) in itertools.pairwise(wins):
        assert e0 - s1 >= 4.0 - 1e-9  # consecutive windows overlap by at least overlap_s
    for s, e in wins:
        assert not 30.0 <= e < 45.0, "a window ends inside the outage"
        assert not 30.0 <= s < 45.0, "a window starts inside the outage"


def test_window_bounds_pass_an_outage_with_data_on_both_sides_of_its_end():
    t_gps = np.r_[np.arange(0.0, 49.05, 0.1), np.arange(79.1, 120.0, 0.1)]  # an outage 49-79.1 s
    wins = window_bounds(t_gps, 120.0, length_s=30.0, overlap_s=6.0)
    ends = [e for _, e in wins]
    assert all(b > a for a, b in itertools.pairwise(ends)), f"a window ends where the one before it did: {wins}"
    assert any(s < 79.1 and e >= 79.1 + 6.0 - 1e-9 for s, e in wins), f"no window holds the outage's end: {wins}"


@pytest.mark.parametrize("length", [10.0, 30.0, 60.0])
@pytest.mark.parametrize("next_tighter", [True, False])
def test_an_outage_that_fills_an_overlap_comes_whole_from_one_window(length, next_tighter):
    """1 Hz fixes, as on the real drives: the window before the outage ends at its first fix after, the next one
    starts at its last fix before; su-batch changes windows at one of those, the one that gives the outage whole to
    the window with the tighter noise bounds, not half-way through the outage."""
    t_gps = np.arange(0.0, 200.0, 1.0)
    t_gps = t_gps[(t_gps <= 40.0) | (t_gps >= 40.0 + length)]
    wins = window_bounds(t_gps, 200.0, length_s=30.0, overlap_s=6.0)
    seams = [seam(t_gps, e0, s1, 6.0, next_tighter) for (_, e0), (s1, _) in itertools.pairwise(wins)]
    assert not any(40.0 < x < 40.0 + length for x in seams), (seams, wins)
    for ((_, e0), (s1, _)), x in zip(itertools.pairwise(wins), seams, strict=True):
        if s1 <= 40.0 and e0 >= 40.0 + length:  # the overlap that holds the outage
            assert x == (s1 if next_tighter else e0)
        else:
            assert x == (s1 + e0) / 2, "elsewhere the middle of the overlap"
    assert sum(s1 <= 40.0 and e0 >= 40.0 + length for (_, e0), (s1, _) in itertools.pairwise(wins)) == 1


def test_a_failed_window_is_never_the_tighter():
    sim = simulate(SimSettings(scenario="urban", seed=3, duration_s=20.0))
    config = load_config(None, env={})
    fixes = [stamp_fix(f, config.gps) for f in sim.fixes()]
    can = [c for c in sim.can_samples() if isinstance(c, CanSample)]
    result = estimate_batch(sorted([*fixes, *can], key=lambda s: s.t), config.estimation)
    assert result.success and math.isfinite(state_noise_volume(result))
    assert state_noise_volume(dataclasses.replace(result, success=False)) == math.inf


def test_window_bounds_of_nothing():
    assert window_bounds(np.zeros(0), 10.0, 20.0, 4.0) == []


@pytest.mark.slow
def test_su_batch_smooths_a_drive_through_an_outage():
    sim = simulate(SimSettings(scenario="urban", seed=3, duration_s=50.0, outages=((20.0, 8.0),)))
    config = load_config(None, env={}, overrides={"estimator.name": "su-batch", "estimator.batch.window_s": 20.0})
    pipeline = Pipeline(config, make_estimator("su-batch", config))
    fixes = [stamp_fix(f, config.gps) for f in sim.fixes()]
    can = [c for c in sim.can_samples() if isinstance(c, CanSample)]
    out = []
    for sample in sorted([*fixes, *can], key=lambda s: s.t):
        out += pipeline.push(sample)
    assert out == [], "su-batch answers only at the end of the drive"
    out = pipeline.finish()
    t = np.array([e.t for e in out])
    assert len(out) > 400 and np.all(np.diff(t) > 0)
    assert np.max(np.diff(t)) < 0.15, "an estimate of the 10 Hz grid lost at a seam between windows"
    enu = sim.frame.to_enu(np.array([e.lat_deg for e in out]), np.array([e.lon_deg for e in out]), sim.frame.alt0_m)
    at = sim.truth.at(t)
    err = np.hypot(enu[:, 0] - at.east, enu[:, 1] - at.north)
    in_outage = np.array([sim.in_outage(x) for x in t])
    assert in_outage.sum() > 60
    assert {e.gps for e, o in zip(out, in_outage, strict=True) if o} == {"outage"}
    assert np.max(err[in_outage]) < 3.0
    assert np.mean(err[~in_outage]) < 2.0


def test_a_live_service_refuses_the_offline_smoother(tmp_path, capsys):
    from sumhe.cli import main

    cfg = tmp_path / "c.toml"
    cfg.write_text('[can]\ninterface = "virtual"\n[gps]\nport = "/nonexistent"\n')
    assert main(["run", "--config", str(cfg), "--estimator", "su-batch", "--duration", "0.1"]) == 1
    assert "sumhe replay" in capsys.readouterr().err
