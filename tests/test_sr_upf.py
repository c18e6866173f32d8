"""``sr-upf``: paper 004's sparse kernel density (eqs. 2-8), the square-root factors, seeding, settings."""

from __future__ import annotations

import numpy as np
import pytest
from test_estimator_contract import run, synthetic_drive

from sumhe.baseline.sr_upf import (
    SrUpf,
    log_normal,
    mixture_loglik,
    mixture_moments,
    nonnegative_lasso,
    sparse_kde,
    tria,
)
from sumhe.settings import UpfSettings


def test_tria_is_a_square_root() -> None:
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 3, 7))
    S = tria(A)
    np.testing.assert_allclose(S @ np.swapaxes(S, 1, 2), A @ np.swapaxes(A, 1, 2), atol=1e-12)
    assert np.allclose(np.triu(S[0], 1), 0.0) and np.all(np.diagonal(S, axis1=1, axis2=2) >= 0)


def test_log_normal_matches_the_density() -> None:
    rng = np.random.default_rng(1)
    S = tria(rng.normal(size=(2, 2, 4)))
    x, mean = rng.normal(size=(2, 2)), rng.normal(size=(2, 2))
    for i in range(2):
        P = S[i] @ S[i].T
        d = x[i] - mean[i]
        expected = -0.5 * d @ np.linalg.solve(P, d) - 0.5 * np.log(np.linalg.det(2 * np.pi * P))
        assert log_normal(x, mean, S)[i] == pytest.approx(expected)


def test_lasso_is_sparse_and_nonnegative() -> None:
    rng = np.random.default_rng(2)
    K = rng.random((40, 20))
    truth = np.zeros(20)
    truth[[3, 11]] = (1.0, 2.0)
    beta = nonnegative_lasso(K, K @ truth, lam=0.01)
    assert np.all(beta >= 0) and np.count_nonzero(beta > 0.05) <= 4
    assert beta[3] > 0.5 and beta[11] > 1.5


def test_sparse_kde_follows_a_two_mode_noise() -> None:
    """A receiver that jumps between two offsets (multipath): the mixture finds both, a Gaussian cannot."""
    rng = np.random.default_rng(3)
    samples = np.concatenate([rng.normal((-2.0, 0.0), 0.3, (100, 2)), rng.normal((2.0, 0.0), 0.3, (100, 2))])
    centres, weights, bandwidth = sparse_kde(samples, lasso=0.1, threshold=0.2)
    assert len(centres) < len(samples) and weights.sum() == pytest.approx(1.0) and np.all(weights > 0)
    at = mixture_loglik(np.array([[-2.0, 0.0], [2.0, 0.0], [0.0, 0.0]]), centres, weights, bandwidth)
    assert at[0] > at[2] + 2.0 and at[1] > at[2] + 2.0  # the modes are likelier than the mean between them
    mean, cov = mixture_moments(centres, weights, bandwidth)
    assert abs(mean[0]) < 0.5 and cov[0, 0] == pytest.approx(4.0, rel=0.25)


def test_same_seed_same_estimates_and_noise_learned() -> None:
    drive = synthetic_drive(duration_s=12.0)
    table = UpfSettings(particles=20, kde_min_samples=30, kde_refit=30)
    a, b = SrUpf(table=table), SrUpf(table=table)
    ea, eb = run(a, drive.samples).estimates, run(b, drive.samples).estimates
    assert [(e.east_m, e.north_m) for e in ea] == [(e.east_m, e.north_m) for e in eb]
    assert a._kde is not None  # 110 fixes: the kernel density replaced the Gaussian


def test_settings_are_validated() -> None:
    with pytest.raises(ValueError, match="particles"):
        UpfSettings(particles=3)
    with pytest.raises(ValueError, match="kde_samples"):
        UpfSettings(kde_samples=10, kde_min_samples=20)
    with pytest.raises(ValueError, match="kde_threshold"):
        UpfSettings(kde_threshold=1.0)
