"""The daemon's whole-run latency percentiles in fixed memory (sumhe/service/histogram.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sumhe.service.histogram import BINS_PER_DECADE, LogHistogram


@pytest.mark.parametrize("q", [1, 50, 90, 99, 99.9, 100])
def test_percentile_is_the_exact_one_within_a_bin_and_never_below(q: float) -> None:
    values = np.random.default_rng(3).lognormal(mean=-0.5, sigma=1.2, size=20_000)
    h = LogHistogram(1e-3, 1e5)
    for v in values:
        h.add(float(v))
    exact = float(np.percentile(values, q, method="inverted_cdf"))
    assert exact <= h.percentile(q) <= exact * 10.0 ** (1.0 / BINS_PER_DECADE)
    assert h.count == values.size


def test_out_of_range_values_and_nan() -> None:
    h = LogHistogram(0.01, 100.0)
    assert math.isnan(h.percentile(50))
    for v in (0.0, -1.0, 0.005, math.nan, 250.0, 1000.0):
        h.add(v)
    assert h.count == 5
    assert h.percentile(50) == 0.01
    assert h.percentile(100) == 1000.0
    assert h.percentile(80) == 1000.0


def test_bad_range_is_refused() -> None:
    with pytest.raises(ValueError, match="lo, hi"):
        LogHistogram(0.0, 1.0)
