"""Unscented Kalman filter on the shared model (``ukf``), written here rather than taken from filterpy.

filterpy (1.4.5, 2018) would have been the well-kept choice, but its install pulls scipy and matplotlib into
sumhe's core dependencies, and its ``UnscentedKalmanFilter`` calls the model once per sigma point in Python;
the model of :mod:`.kinematics` takes all sigma points at once, and the filter is 60 lines. Sigma points are
van der Merwe's scaled set with ``alpha = 1, beta = 2, kappa = 0``: the weights are all non-negative, so the
covariance stays positive semi-definite; the azimuth is averaged on the circle and its differences wrapped.
Every update (CAN rows, GNSS position, course) draws fresh sigma points from the current mean and covariance.

Its error estimate is its covariance with the offset of a receiver's heading considered (:class:`Ukf`: a Schmidt
consider parameter carried through the filter's own recursion; the estimates do not change), where the EKF and the
IMM estimate the offset (:class:`~sumhe.baseline.ekf.OffsetFilter`): drawn from the state grown by the offset, the
sigma points spread wider (the spread factor grows with the dimension), and a UKF whose azimuth no fix had set yet
(fixes without course or heading) no longer found it in the positions (45 m off after 40 s, 10 m before).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import GaussianFilter, can_rows
from sumhe.baseline.heading_offset import heading_offset_variance
from sumhe.baseline.kinematics import AZIMUTH, PHI, E, FloatArray, N
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


class Ukf(GaussianFilter):
    """Unscented Kalman filter (``ukf``).

    Its error estimate is ``P + s s' sigma^2``: its own covariance ``P`` and the offset of a receiver's heading
    (variance ``sigma^2``, :func:`~.heading_offset.heading_offset_variance`) considered (Schmidt's consider
    covariance, as the EKF had it before it estimated the offset), through ``s`` (``_sensitivity``, per rad),
    the first-order change of the state's error with the offset: moved by each step's Jacobian, ``s <- F s``, and
    by each update with the filter's own gain ``K``, ``s <- s - K (H s + c)``, ``H`` the measurement's Jacobian at
    the mean and ``c`` 1 for a heading (which measures the azimuth plus the offset), else 0. Before, it added the
    offset's part from the way moved since the newest position fix alone
    (:func:`~.heading_offset.considered_heading_offset`): an azimuth off by the whole offset from that fix on, a
    position right at it. Between fixes, though, the filter follows the headings: on the shared real drive (1 Hz
    fixes, headings) the EKF's ``s`` at the starts of the 60 s outages put the position 60-490 m/rad to the left
    of the track (0.4-3.9 m across, 2.6 m at the median, for a 1-sigma offset; the azimuth 0.86-1.07 of the
    offset), the estimates of the first 10 s of 16 of the 19 outages were on the mean left of the removed fixes
    (by up to 9 m), and the UKF's own position variance at the newest fix said 0.2-0.5 m^2 (trace; but before the
    first outage, 2.5 min into the drive: 45 m^2). That part (6.8 m^2 at the median) and its correlation with the
    azimuth's (46 m^2 50-60 s into the outages) were missing from the UKF's error estimate, whose ``P`` was the
    EKF's within 0.1 %: its own growth 21-24 % below the EKF's 40-60 s into the outages, 85.7 against 98.4 % of
    the removed fixes within ``eph`` in their first 10 s. Where the filter takes courses over ground only, ``s``
    stays nil."""

    name = "ukf"
    snapshot_attrs = ("x", "P", "_sensitivity", "_t_yaw")

    def __init__(self, settings: EstimationSettings | None = None, noise: NoiseSettings | None = None) -> None:
        super().__init__(settings, noise)
        self._wm, self._wc, self._spread = merwe_weights(self.layout.n)
        self._offset_var = heading_offset_variance(self.settings)

    @staticmethod
    def tuned(settings: EstimationSettings) -> NoiseSettings:
        """The noise of its table, ``[estimator.ukf]``."""
        return settings.estimator.ukf

    def _reset_filter(self) -> None:
        super()._reset_filter()
        self._sensitivity = np.zeros(self.layout.n)

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        super()._start(x0, P0)
        self._sensitivity = np.zeros(self.layout.n)

    def _init_heading(self, phi: float, sigma: float) -> None:
        super()._init_heading(phi, sigma)
        self._sensitivity[PHI] = 0.0

    def _step(self, dt: float) -> None:
        if self._sensitivity.any():
            self._sensitivity = kin.step_jacobian(self.x, dt) @ self._sensitivity
        X = kin.step(sigma_points(self.x, self.P, self._spread), dt)
        self.x, P, _ = unscented_transform(X, self._wm, self._wc)
        self.P = P + kin.process_noise(dt, self.noise, self.layout)

    def _update_can(self, inputs: Inputs) -> None:
        rows, z = can_rows(inputs)
        if rows:
            R = np.diag(np.square(kin.can_sigmas(rows, self.noise)))
            jacobian = partial(kin.can_jacobian, self.x, rows, self.layout)
            self._measurement(lambda X: kin.can_model(X, rows, self.layout), "can", z, R, jacobian, 0.0).commit()

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        offset = 1.0 if kind == AZIMUTH and self._heading else 0.0  # a heading measures azimuth + offset
        jacobian = partial(kin.fix_jacobian, self.x, kind, lag)
        return self._measurement(lambda X: kin.fix_model(X, kind, lag), kind, z, R, jacobian, offset)

    def _measurement(
        self,
        h: Callable[[FloatArray], FloatArray],
        kind: str,
        z: FloatArray,
        R: FloatArray,
        jacobian: Callable[[], FloatArray],
        offset: float,
    ) -> Pending:
        """The unscented update with measurement function ``h`` (on stacked states), pending commit; the
        sensitivity to the heading's offset moved with the gain, the measurement's Jacobian at the mean before it
        (``jacobian``, called only where there is a sensitivity to move) and how many times it sees the offset
        (``offset``)."""
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
            if offset or self._sensitivity.any():
                self._sensitivity = self._sensitivity - K @ (jacobian() @ self._sensitivity + offset)
            self.x = kin.wrap_state(self.x + K @ nu)
            P = self.P - K @ S @ K.T
            self.P = 0.5 * (P + P.T)

        return Pending(nu, S, commit)

    def _covariance(self) -> FloatArray:
        return self.P + self._offset_var * np.outer(self._sensitivity, self._sensitivity)

    def considered_m2(self) -> float:
        """What the considered offset adds to the position's variance (trace, m^2)
        (:meth:`~sumhe.estimator.base.StreamEstimator.considered_m2`)."""
        return self._offset_var * float(self._sensitivity[E] ** 2 + self._sensitivity[N] ** 2)
