"""The output envelope (:mod:`sumhe.estimator.mhe.envelope`): the factor is the largest residual ratio of the
recent blocks and the current one, times the margin, within [1, max]."""

from __future__ import annotations

import numpy as np

from sumhe.estimator.mhe.envelope import BLOCK, OutputEnvelope


def test_the_factor_is_the_margin_times_the_largest_recent_ratio() -> None:
    rng = np.random.default_rng(3)
    history, margin, max_factor = 4 * BLOCK, 1.1, 20.0
    envelope = OutputEnvelope(2, history, margin, max_factor)
    seen: list[list[float]] = [[], []]
    for _ in range(400):
        ratios = rng.exponential(1.0, (int(rng.integers(1, 4)), 2)) * rng.choice([0.5, 3.0])
        ratios[rng.random(ratios.shape) < 0.2] = np.nan
        envelope.observe(ratios)
        for j in range(2):
            seen[j] += [v for v in ratios[:, j].tolist() if np.isfinite(v)]
            done = len(seen[j]) // BLOCK * BLOCK
            kept = seen[j][max(done - history, 0) :]  # the blocks kept and the one being filled
            peak = max(kept, default=0.0)
            assert envelope.factor[j] == min(max(peak * margin, 1.0), max_factor)
