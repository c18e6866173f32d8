"""Unscented Kalman filter on the shared model (``ukf``), written here rather than taken from filterpy.

filterpy (1.4.5, 2018) would have been the well-kept choice, but its install pulls scipy and matplotlib into
sumhe's core dependencies, and its ``UnscentedKalmanFilter`` calls the model once per sigma point in Python;
the model of :mod:`.kinematics` takes all sigma points at once, and the filter is 60 lines. Sigma points are
van der Merwe's scaled set with ``alpha = 1, beta = 2, kappa = 0``: the weights are all non-negative, so the
covariance stays positive semi-definite; the azimuth is averaged on the circle and its differences wrapped.
Every update (CAN rows, GNSS position, course) draws fresh sigma points from the current mean and covariance.

Its error estimate is its covariance with the offset of a receiver's heading considered where it follows headings
(:class:`~.heading_offset.ConsideredHeadingOffset`, the EKF's bound and reading; the estimates do not change).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import GaussianFilter, can_rows
from sumhe.baseline.heading_offset import ConsideredHeadingOffset
from sumhe.baseline.kinematics import E, FloatArray, N
from sumhe.baseline.stream import Inputs, Pending
from sumhe.settings import EstimationSettings, NoiseSettings

ALPHA, BETA, KAPPA = 1.0, 2.0, 0.0
JITTER = 1e-12
"""Added to the diagonal when a covariance fails its Cholesky factorisation."""


def merwe_weights(n: int) -> tuple[FloatArray, FloatArray, float]:
    """Mean and covariance weights of the ``2n + 1`` scaled sigma points, and the spread factor ``n + lambda``."""
    lam = ALPHA**2 * (n + KAPPA) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + 1.0 - ALPHA**2 + BETA
    return wm, wc, n + lam


def sigma_points(x: FloatArray, P: FloatArray, spread: float) -> FloatArray:
    """The sigma points of (x, P) as columns ``(n, 2n + 1)``: x, x + columns of L, x - columns of L."""
    try:
        L = np.linalg.cholesky(spread * P)
    except np.linalg.LinAlgError:
        L = np.linalg.cholesky(spread * (P + JITTER * np.trace(P) * np.eye(len(x))))
    return np.column_stack([x, x[:, None] + L, x[:, None] - L])


def unscented_transform(X: FloatArray, wm: FloatArray, wc: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mean, covariance and deviations of propagated sigma points (states; the azimuth on the circle)."""
    mean = kin.weighted_mean(X, wm)
    D = kin.state_difference(X, mean)
    return mean, (D * wc) @ D.T, D


class Ukf(ConsideredHeadingOffset, GaussianFilter):
    """Unscented Kalman filter (``ukf``)."""

    name = "ukf"
    snapshot_attrs = ("x", "P", "_anchor", "_t_yaw")

    def __init__(self, settings: EstimationSettings | None = None, noise: NoiseSettings | None = None) -> None:
        super().__init__(settings, noise)
        self._wm, self._wc, self._spread = merwe_weights(self.layout.n)

    @staticmethod
    def tuned(settings: EstimationSettings) -> NoiseSettings:
        """The noise of its table, ``[estimator.ukf]``."""
        return settings.estimator.ukf

    def _step(self, dt: float) -> None:
        X = kin.step(sigma_points(self.x, self.P, self._spread), dt)
        self.x, P, _ = unscented_transform(X, self._wm, self._wc)
        self.P = P + kin.process_noise(dt, self.noise, self.layout)

    def _update_can(self, inputs: Inputs) -> None:
        rows, z = can_rows(inputs)
        if rows:
            R = np.diag(np.square(kin.can_sigmas(rows, self.noise)))
            self._measurement(lambda X: kin.can_model(X, rows, self.layout), "can", z, R).commit()

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        return self._measurement(lambda X: kin.fix_model(X, kind, lag), kind, z, R)

    def _measurement(self, h: Callable[[FloatArray], FloatArray], kind: str, z: FloatArray, R: FloatArray) -> Pending:
        """The unscented update with measurement function ``h`` (on stacked states), pending commit."""
        X = sigma_points(self.x, self.P, self._spread)
        Z = h(X)
        zhat = kin.measurement_mean(kind, Z, self._wm)
        Dz = kin.residual(kind, Z, zhat[:, None])
        Dx = kin.state_difference(X, self.x)
        S = (Dz * self._wc) @ Dz.T + R
        Pxz = (Dx * self._wc) @ Dz.T
        nu = kin.residual(kind, z, zhat)

        def commit() -> None:
            K = np.linalg.solve(S, Pxz.T).T  # K = Pxz S^-1
            self.x = kin.wrap_state(self.x + K @ nu)
            P = self.P - K @ S @ K.T
            self.P = 0.5 * (P + P.T)

        return Pending(nu, S, commit)

    def _covariance(self) -> FloatArray:
        return self._considered(self.P, self.x[[E, N]])
