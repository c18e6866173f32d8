import dataclasses
import itertools
import math

import numpy as np
import pytest

from sumhe.config import load_config
from sumhe.estimator.batch import estimate_batch
from sumhe.estimator.registry import make_estimator
from sumhe.estimator.su_batch import (
    blend_outage,
    filled_overlap,
    fix_allowance,
    later_weight,
    state_noise_volume,
    window_bounds,
    window_estimates,
)
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
def test_an_outage_that_fills_an_overlap_is_found_there_alone(length):
    """1 Hz fixes, as on the real drives: the window before the outage ends at its first fix after, the next one
    starts at its last fix before; that pair's overlap holds the outage whole, no other pair's holds one."""
    t_gps = np.arange(0.0, 200.0, 1.0)
    t_gps = t_gps[(t_gps <= 40.0) | (t_gps >= 40.0 + length)]
    wins = window_bounds(t_gps, 200.0, length_s=30.0, overlap_s=6.0)
    found = [filled_overlap(t_gps, e0, s1, 6.0) for (_, e0), (s1, _) in itertools.pairwise(wins)]
    assert [g for g in found if g is not None] == [(40.0, 40.0 + length)], (found, wins)


def test_the_later_window_weighs_by_where_in_the_outage_or_wholly_by_its_noise_bounds():
    for x in (0.05, 0.5, 0.95):
        assert later_weight(x, -2.0, agree=True) == x, "agreeing tracks: each window by the data on its side"
        assert later_weight(x, -2.0, agree=False) == 1.0, "the later window's box the smaller: the later whole"
        assert later_weight(x, 0.7, agree=False) == 0.0
        assert later_weight(x, math.inf, agree=False) == 0.0, "a failed later window counts nil"
        assert later_weight(x, -math.inf, agree=False) == 1.0
        assert later_weight(x, math.nan, agree=False) == x, "both failed: by where in the outage"


def test_a_failed_window_is_never_the_tighter():
    sim = simulate(SimSettings(scenario="urban", seed=3, duration_s=20.0))
    config = load_config(None, env={})
    fixes = [stamp_fix(f, config.gps) for f in sim.fixes()]
    can = [c for c in sim.can_samples() if isinstance(c, CanSample)]
    result = estimate_batch(sorted([*fixes, *can], key=lambda s: s.t), config.estimation)
    assert result.success and math.isfinite(state_noise_volume(result))
    assert state_noise_volume(dataclasses.replace(result, success=False)) == math.inf


@pytest.mark.slow
def test_su_batch_blends_an_outage_filling_an_overlap_from_both_windows():
    """1 Hz fixes and a 12 s outage filling the overlap of two 20 s windows: the estimates inside it are the two
    windows' blend by where in the outage, their tracks within a fix's allowance of each other; at the fixes on
    either side, each window's own. Tracks further apart than the allowance: the whole outage from the window with
    the tighter noise bounds."""
    sim = simulate(SimSettings(scenario="urban", seed=3, duration_s=60.0, gps_rate_hz=1.0, outages=((25.0, 12.0),)))
    overrides = {"estimator.name": "su-batch", "estimator.batch.window_s": 20.0}
    config = load_config(None, env={}, overrides=overrides)
    samples = sorted(
        [*(stamp_fix(f, config.gps) for f in sim.fixes()), *(c for c in sim.can_samples() if isinstance(c, CanSample))],
        key=lambda s: s.t,
    )
    pipeline = Pipeline(config, make_estimator("su-batch", config))
    for sample in samples:
        pipeline.push(sample)
    out = {round(e.t, 6): e for e in pipeline.finish()}
    solved = pipeline.estimator._samples  # as the front-end gave them: fixes on the CAN clock, speeds centred
    fixes = [f for f in solved if not isinstance(f, CanSample) and f.valid]
    t_gps = np.array([f.t for f in fixes])
    wins = window_bounds(t_gps, solved[-1].t, 20.0, 6.0)
    pair = [(w0, w1) for w0, w1 in itertools.pairwise(wins) if filled_overlap(t_gps, w0[1], w1[0], 6.0)]
    assert len(pair) == 1, wins
    (s0, e0), (s1, e1) = pair[0]
    a, b = filled_overlap(t_gps, e0, s1, 6.0)
    early, late = (
        estimate_batch([x for x in solved if lo <= x.t <= hi], config.estimation, frame=pipeline.estimator._frame)
        for lo, hi in ((s0, e0), (s1, e1))
    )
    inside = [(k, t) for k, t in enumerate(early.t) if a < t < b]
    assert len(inside) >= 10
    east_late = np.interp([t for _, t in inside], late.t, late.east)
    north_late = np.interp([t for _, t in inside], late.t, late.north)
    apart = np.hypot(east_late - [early.east[k] for k, _ in inside], north_late - [early.north[k] for k, _ in inside])
    allowance = max(fix_allowance(f, config.estimation) for f in fixes if f.t in (a, b))
    assert 0.05 < apart.max() < allowance, "the two windows' tracks differ, within a fix's allowance"
    for (k, t), there in zip(inside, east_late, strict=True):
        want = early.east[k] + (t - a) / (b - a) * (there - early.east[k])
        assert out[round(t, 6)].east_m == pytest.approx(want, abs=1e-9)
    assert out[round(a, 6)].east_m == early.east[list(early.t).index(a)], "the fix before: the earlier window's"
    assert out[round(b, 6)].east_m == late.east[list(late.t).index(b)], "the fix after: the later window's"
    tighter = late if state_noise_volume(late) < state_noise_volume(early) else early
    whole = blend_outage(window_estimates(early), early, late, (a, b), allowance_m=0.01)
    assert [e.east_m for e in whole] == pytest.approx(np.interp([t for _, t in inside], tighter.t, tighter.east))


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
