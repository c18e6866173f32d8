"""``mskf-em``'s EM (paper 002 eqs. 13-16) on a linear stage with known noise, and the estimator's block scheme."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest
from test_estimator_contract import run, synthetic_drive

from sumhe.baseline.mskf_em import MskfEm, Step, clamp, smooth_block
from sumhe.frontend.fixes import LocalFix
from sumhe.settings import MskfSettings


def random_walk_block(q: float, r: float, steps: int, seed: int) -> list[Step]:
    """A 1-D position random walk (density q, 0.1 s steps) measured every step with variance ``r`` (R scaled)."""
    rng = np.random.default_rng(seed)
    dt = 0.1
    x = 0.0
    out = []
    for _ in range(steps):
        x += rng.normal(0.0, np.sqrt(q * dt))
        z = np.array([x + rng.normal(0.0, np.sqrt(r))])
        step = Step(np.eye(1), np.zeros(1), np.array([[dt]]), np.zeros((1, 1)))
        step.updates.append((np.eye(1), z, np.eye(1), True))
        out.append(step)
    return out


def test_em_recovers_the_noise_of_a_random_walk() -> None:
    steps = random_walk_block(q=0.5, r=0.2, steps=1500, seed=1)
    q, r = 1.5, 0.6  # both 3x off
    for _ in range(25):
        m = smooth_block(np.zeros(1), np.eye(1), steps, q, r, ())
        q, r = m.q, m.r_sum / m.r_rows
    assert q == pytest.approx(0.5, rel=0.15) and r == pytest.approx(0.2, rel=0.1)


def test_clamp_keeps_the_scale_near_its_start() -> None:
    assert clamp(1e-9, 1.0, 100.0, 3.0) == 0.01 and clamp(1e9, 1.0, 100.0, 3.0) == 100.0
    assert clamp(float("nan"), 1.0, 100.0, 3.0) == 3.0


def test_blocks_re_estimate_the_scales() -> None:
    drive = synthetic_drive(duration_s=20.0)
    est = MskfEm(table=MskfSettings(block_s=2.0))
    run(est, drive.samples)
    stats = est.stats()
    assert stats["em_blocks"] >= 8
    start = MskfSettings().noise
    assert stats["q_position"] != start.pos_rw**2 and stats["r_gnss"] != 1.0


def noisier_fixes(samples: list, sigma_m: float, seed: int) -> list:
    """The drive's samples with its fixes' positions off by ``sigma_m`` more noise than their GST sigmas say."""
    rng = np.random.default_rng(seed)

    def worse(s):
        if not (isinstance(s, LocalFix) and s.valid):
            return s
        e, n = rng.normal(0.0, sigma_m, 2)
        return dataclasses.replace(s, east_m=s.east_m + e, north_m=s.north_m + n)

    return [worse(s) for s in samples]


@pytest.mark.parametrize(("sigma_m", "limit", "said"), [(1.0, 4.0, True), (1.0, 1.0, False), (0.0, 100.0, False)])
def test_an_em_scale_at_its_bound_is_said_naming_the_key(sigma_m, limit, said, caplog) -> None:
    """Fixes with 1 m more noise than their 0.3 m sigmas say: the GNSS scale runs to ``scale_limit`` and the filter
    says so, naming the key (counted for each block that ends there, logged at the 1st and the 10th); with the EM
    off (a limit of 1) or the fixes as noisy as they say, nothing."""
    drive = synthetic_drive(duration_s=30.0)
    est = MskfEm(table=MskfSettings(block_s=2.0, scale_limit=limit))
    with caplog.at_level(logging.WARNING, logger="sumhe.baseline.mskf_em"):
        run(est, noisier_fixes(drive.samples, sigma_m, seed=3))
    stats = est.stats()
    said_lines = [r.getMessage() for r in caplog.records if "estimator.mskf_em.scale_limit" in r.getMessage()]
    if said:
        assert stats["r_gnss"] == limit and stats["em_at_limit"] >= 10
        assert len(said_lines) == 2 and all("GNSS noise scale at its bound, 4 x its start" in m for m in said_lines)
    else:
        assert stats.get("em_at_limit", 0) == 0 and not said_lines


def test_settings_are_validated() -> None:
    with pytest.raises(ValueError, match="block_s"):
        MskfSettings(block_s=0.0)
    with pytest.raises(ValueError, match="em_iterations"):
        MskfSettings(em_iterations=0)


def test_error_estimate_carries_the_azimuth_error_through_an_outage() -> None:
    """An azimuth error at an outage's start moves the position across the track by the way moved times it: after
    20 s at 10 m/s the covariance holds at least (200 m)^2 times the azimuth's variance then (the position stage
    alone, taking it as white noise at every step, held a fifth of it)."""
    drive = synthetic_drive(duration_s=32.0, silent=[(10.0, 20.0)])
    est = MskfEm()
    t0 = drive.samples[0].t
    before = [s for s in drive.samples if s.t < t0 + 10.0]
    run(est, before, finish=False)
    azimuth_var = float(est.heading.P[0, 0])
    run(est, [s for s in drive.samples[len(before) :] if s.t < t0 + 29.9], finish=False)
    across = float(np.max(np.linalg.eigvalsh(est._covariance()[:2, :2])))
    assert across >= (10.0 * 20.0) ** 2 * azimuth_var
