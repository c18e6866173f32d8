"""Unscented Kalman filter on the shared model (``ukf``), written here rather than taken from filterpy.

filterpy (1.4.5, 2018) would have been the well-kept choice, but its install pulls scipy and matplotlib into
sumhe's core dependencies, and its ``UnscentedKalmanFilter`` calls the model once per sigma point in Python;
the model of :mod:`.kinematics` takes all sigma points at once, and the filter is 60 lines. Sigma points are
van der Merwe's scaled set with ``alpha = 1, beta = 2, kappa = 0``: the weights are all non-negative, so the
covariance stays positive semi-definite; the azimuth is averaged on the circle and its differences wrapped.
Every update (CAN rows, GNSS position, course) draws fresh sigma points from the current mean and covariance.

It estimates the offset of a receiver's heading as the EKF does (:class:`~sumhe.baseline.ekf.OffsetFilter`), its
sigma points drawn from the state grown by the offset once a heading has tied the two (:class:`Ukf`).

Where the fixes carry neither a course nor a heading, its azimuth starts at the chord between the first two fixes
far enough apart (``azimuth_from_motion = "start"``, as ``gtsam-fls``), not unknown: an unknown azimuth's sigma
(``pi / sqrt(3)``, a uniform one's) puts the sigma points ``sqrt(n)`` of it away, round the circle and back (5.1
rad with the 8 states), and their spread is no longer the covariance's. Started so, with the CAN yaw rate's gain a
state, it took the azimuth's correction for the yaw rate's bias (0.05 rad/s) and was 44 m off 10 s into an outage
(2.9 m without the gain).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import OffsetFilter, can_rows, considered, sees_offset
from sumhe.baseline.heading_offset import offset_step
from sumhe.baseline.kinematics import FloatArray
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


class Ukf(OffsetFilter):
    """Unscented Kalman filter (``ukf``), the offset of a receiver's heading estimated (:class:`~sumhe.baseline.ekf.
    OffsetFilter`).

    Once a heading has tied the offset to the state (their covariance in ``Pt`` not nil), the sigma points are drawn
    from the state grown by the offset, which a step decays and a heading measures beside the azimuth; before (and
    for good where the fixes carry courses only) from the state alone, the offset's variance carried beside it.
    Grown from the start, the sigma points spread wider (the spread factor grows with the dimension) and a UKF whose
    azimuth no fix had set yet (fixes with neither course nor heading) no longer found it from the positions: 45 m off
    after 40 s, 10 m as it is. Taken as a Schmidt consider parameter instead (carried through the filter's own
    recursion by the first-order sensitivity of its state to the offset, the estimates without it), the UKF followed
    the shared real drive's headings as the EKF did: 3.85 / 4.99 / 6.39 m off the removed fixes of its 10 / 30 / 60
    s outages."""

    name = "ukf"
    azimuth_from_motion = "start"

    def __init__(self, settings: EstimationSettings | None = None, noise: NoiseSettings | None = None) -> None:
        super().__init__(settings, noise)
        n = self.layout.n
        self._weights = {dim: merwe_weights(dim) for dim in (n, n + 1)}

    @staticmethod
    def tuned(settings: EstimationSettings) -> NoiseSettings:
        """The noise of its table, ``[estimator.ukf]``."""
        return settings.estimator.ukf

    def _block(self, grown: bool) -> tuple[FloatArray, FloatArray]:
        """The mean and covariance the sigma points are drawn from: the state's grown by the offset (``grown``, or
        where a heading has tied them), else the state's."""
        if grown or self.Pt[-1, :-1].any():
            return np.append(self.x, self.offset_rad), self.Pt
        return self.x, self.P

    def _sigma_points(self, mean: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The sigma points of ``(mean, cov)`` and their mean and covariance weights."""
        wm, wc, spread = self._weights[len(mean)]
        return sigma_points(mean, cov, spread), wm, wc

    def _set(self, mean: FloatArray, cov: FloatArray, offset_var: float) -> None:
        """The state (wrapped) and, where ``mean`` is grown, the offset from ``mean``, their covariance ``cov``;
        else the offset's variance ``offset_var`` beside the state's (unused where grown)."""
        mean, cov = kin.wrap_state(mean), 0.5 * (cov + cov.T)
        if len(mean) > len(self.x):
            self.x, self.offset_rad, self.Pt = mean[:-1], float(mean[-1]), cov
        else:
            self.x, self.Pt = mean, considered(cov, offset_var)
        self._marginal()

    def _step(self, dt: float) -> None:
        keep, walk = offset_step(dt, self._offset_var)
        mean, cov = self._block(False)
        grown = len(mean) > len(self.x)
        X, wm, wc = self._sigma_points(mean, cov)
        X = np.vstack([kin.step(X[:-1], dt), keep * X[-1]]) if grown else kin.step(X, dt)
        mean, cov, _ = unscented_transform(X, wm, wc)
        Q = kin.process_noise(dt, self.noise, self.layout)
        if grown:
            self._set(mean, cov + considered(Q, walk), 0.0)
        else:  # the offset decays beside the state
            self.offset_rad *= keep
            self._set(mean, cov + Q, keep * keep * self.Pt[-1, -1] + walk)

    def _update_can(self, inputs: Inputs) -> None:
        rows, z = can_rows(self._take_yaw_rate(inputs))
        if rows:
            R = np.diag(np.square(kin.can_sigmas(rows, self.noise)))
            n = len(self.x)
            self._measurement(lambda X: kin.can_model(X[:n], rows, self.layout), "can", z, R, False).commit()

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        seen, n = sees_offset(kind, self._heading), len(self.x)

        def h(X: FloatArray) -> FloatArray:
            return kin.fix_model(X[:n], kind, lag) + (seen * X[n] if len(X) > n else 0.0)

        return self._measurement(h, kind, z, R, bool(seen))

    def _measurement(
        self, h: Callable[[FloatArray], FloatArray], kind: str, z: FloatArray, R: FloatArray, grown: bool
    ) -> Pending:
        """The unscented update with measurement function ``h`` (on stacked states, grown by the offset where
        ``grown`` or a heading has tied them: :meth:`_block`), pending commit."""
        mean, cov = self._block(grown)
        X, wm, wc = self._sigma_points(mean, cov)
        Z = h(X)
        zhat = kin.measurement_mean(kind, Z, wm)
        Dz = kin.residual(kind, Z, zhat[:, None])
        Dx = kin.state_difference(X, mean)
        S = (Dz * wc) @ Dz.T + R
        Pxz = (Dx * wc) @ Dz.T
        nu = kin.residual(kind, z, zhat)

        def commit() -> None:
            K = np.linalg.solve(S, Pxz.T).T  # K = Pxz S^-1
            self._set(mean + K @ nu, cov - K @ S @ K.T, self.Pt[-1, -1])

        return Pending(nu, S, commit)
