"""Interacting multiple models (``imm``): two EKF cells on the shared model, "straight" and "turning".

As in papers 002-003, the vehicle switches between a non-manoeuvring and a manoeuvring motion model. With CAN
yaw rate measured at 100 Hz, the two models differ in their process noise: the straight model keeps speed,
yaw rate and azimuth nearly constant (small random walks), the turning model lets yaw rate and azimuth change
fast and the position slip sideways (large ones). A two-state Markov chain with mean sojourn times
``sojourn_s`` switches them; each predict step mixes the cells (interaction), each update (CAN rows, GNSS)
weighs the models by the likelihood of its innovation, and the output is the probability-weighted mean.
Measurement noise, gate and priors come from the straight model's :class:`~sumhe.baseline.kinematics.NoiseSettings`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import (
    ekf_can_update,
    ekf_innovation,
    ekf_predict,
    gaussian_loglik,
    inflate,
    kf_update,
    set_heading,
)
from sumhe.baseline.kinematics import FloatArray
from sumhe.baseline.stream import Inputs, Pending, RecursiveEstimator
from sumhe.config import Config
from sumhe.settings import EstimationSettings, NoiseSettings

MU_MIN = 1e-4
"""Floor of a model's probability, so that it can come back."""


def transition_matrix(dt: float, sojourn_s: tuple[float, float]) -> FloatArray:
    """Markov switching probabilities over ``dt`` seconds: ``Pi[i, j]`` = P(model j after | model i before)."""
    leave = [1.0 - math.exp(-dt / s) for s in sojourn_s]
    return np.array([[1.0 - leave[0], leave[0]], [leave[1], 1.0 - leave[1]]])


def mix(
    xs: list[FloatArray], Ps: list[FloatArray], mu: FloatArray, Pi: FloatArray
) -> tuple[list[FloatArray], list[FloatArray], FloatArray]:
    """The IMM interaction step: mixed initial states and covariances of each cell and the predicted probabilities."""
    c = mu @ Pi  # c_j = sum_i mu_i Pi_ij
    W = mu[:, None] * Pi / c[None, :]  # mixing weights mu_i|j
    out_x, out_P = [], []
    for j, ref in enumerate(xs):
        D = [kin.state_difference(x, ref) for x in xs]
        dbar = sum(W[i, j] * D[i] for i in range(len(xs)))
        out_x.append(kin.wrap_state(ref + dbar))
        out_P.append(sum(W[i, j] * (Ps[i] + np.outer(D[i] - dbar, D[i] - dbar)) for i in range(len(xs))))
    return out_x, out_P, c


class Imm(RecursiveEstimator):
    """IMM of a straight and a turning EKF cell (``imm``)."""

    name = "imm"

    def __init__(
        self,
        settings: EstimationSettings | None = None,
        models: tuple[NoiseSettings, NoiseSettings] | None = None,
        sojourn_s: tuple[float, float] | None = None,
    ) -> None:
        settings = settings or EstimationSettings()
        table = settings.estimator.imm
        self.models = models or (table.straight, table.turn)
        sojourn_s = table.sojourn_s if sojourn_s is None else sojourn_s
        if len(sojourn_s) != 2 or not all(math.isfinite(s) and s > 0 for s in sojourn_s):
            raise ValueError(f"sojourn_s: two positive times (s), got {sojourn_s!r}")
        self.sojourn_s = sojourn_s
        super().__init__(settings, self.models[0])

    @classmethod
    def from_config(cls, config: Config) -> Imm:
        return cls(config.estimation)

    def stats(self) -> Mapping[str, float | int | str]:
        return {**super().stats(), "p_turn": float(self.mu[1])}

    def _reset_filter(self) -> None:
        self.xs = [np.zeros(self.layout.n) for _ in self.models]
        self.Ps = [np.eye(self.layout.n) for _ in self.models]
        self.mu = np.array(self.sojourn_s) / sum(self.sojourn_s)

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        self.xs = [x0.copy() for _ in self.models]
        self.Ps = [P0.copy() for _ in self.models]

    def _weigh(self, loglik: list[float]) -> None:
        """Bayes' rule on the model probabilities with each cell's log-likelihood."""
        logp = np.log(self.mu) + np.array(loglik)
        p = np.exp(logp - logp.max())
        p = np.maximum(p / p.sum(), MU_MIN)
        self.mu = p / p.sum()

    def _predict(self, dt: float, inputs: Inputs) -> None:
        self.xs, self.Ps, self.mu = mix(self.xs, self.Ps, self.mu, transition_matrix(dt, self.sojourn_s))
        for j, noise in enumerate(self.models):
            self.xs[j], self.Ps[j] = ekf_predict(self.xs[j], self.Ps[j], dt, noise, self.layout)

    def _can_update(self, inputs: Inputs) -> None:
        loglik = []
        for j in range(len(self.models)):
            self.xs[j], self.Ps[j], ll = ekf_can_update(self.xs[j], self.Ps[j], inputs, self.noise, self.layout)
            loglik.append(ll)
        self._weigh(loglik)

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        cells = [ekf_innovation(x, P, kind, z, R, lag) for x, P in zip(self.xs, self.Ps, strict=True)]
        zhats = np.column_stack([kin.fix_model(x, kind, lag) for x in self.xs])
        zhat = kin.measurement_mean(kind, zhats, self.mu)
        dev = kin.residual(kind, zhats, zhat[:, None])
        S = sum(m * (S_j + np.outer(d, d)) for m, (_, S_j, _), d in zip(self.mu, cells, dev.T, strict=True))
        nu = kin.residual(kind, z, zhat)

        def commit() -> None:
            loglik = []
            for j, (nu_j, S_j, H_j) in enumerate(cells):
                loglik.append(gaussian_loglik(nu_j, S_j))
                x, self.Ps[j] = kf_update(self.xs[j], self.Ps[j], nu_j, H_j, R)
                self.xs[j] = kin.wrap_state(x)
            self._weigh(loglik)

        return Pending(nu, np.asarray(S), commit)

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        self.Ps = [inflate(P, kind, nu, R) for P in self.Ps]

    def _init_heading(self, phi: float, sigma: float) -> None:
        cells = [set_heading(x, P, phi, sigma) for x, P in zip(self.xs, self.Ps, strict=True)]
        self.xs, self.Ps = [x for x, _ in cells], [P for _, P in cells]

    def _mean(self) -> FloatArray:
        return kin.weighted_mean(np.column_stack(self.xs), self.mu)

    def _covariance(self) -> FloatArray:
        """The mixture's covariance: the cells' covariances and the spread of their means, weighted."""
        spread = kin.weighted_covariance(np.column_stack(self.xs), self.mu, self._mean())
        return np.asarray(sum(m * P for m, P in zip(self.mu, self.Ps, strict=True)) + spread)
