"""Extended Kalman filter on the shared model: predict at CAN rate, update with CAN speed / yaw rate and GNSS.

The maths is in two procedural functions (``kf_predict``, ``kf_update``, after filterpy's
``kalman_filter.py``), reused by the RTS smoother and the IMM cells; :class:`GaussianFilter` holds a mean and
covariance and implements the hooks every Gaussian filter shares (start, re-acquisition, heading set-up);
:class:`Ekf` adds the linearised prediction and updates. Stream handling, gating and re-acquisition are in
:mod:`sumhe.baseline.stream`.
"""

from __future__ import annotations

import math

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.kinematics import PHI, FloatArray
from sumhe.baseline.stream import Inputs, Pending, RecursiveEstimator
from sumhe.config import Config
from sumhe.settings import EstimationSettings, NoiseSettings


def kf_predict(P: FloatArray, F: FloatArray, Q: FloatArray) -> FloatArray:
    """The predicted covariance ``F P F' + Q`` (the mean is moved by the caller's nonlinear model)."""
    return F @ P @ F.T + Q  # P^- = F P F' + Q


def kf_update(
    x: FloatArray, P: FloatArray, nu: FloatArray, H: FloatArray, R: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """One Kalman update with innovation ``nu``; Joseph form, so P stays symmetric positive semi-definite."""
    PHt = P @ H.T
    S = H @ PHt + R  # innovation covariance
    K = np.linalg.solve(S, PHt.T).T  # K = P H' S^-1
    x = x + K @ nu  # x^+ = x^- + K nu
    IKH = np.eye(len(x)) - K @ H
    P = IKH @ P @ IKH.T + K @ R @ K.T  # P^+ = (I - K H) P (I - K H)' + K R K'
    return x, 0.5 * (P + P.T)


def inflate(P: FloatArray, kind: str, nu: FloatArray, R: FloatArray) -> FloatArray:
    """P widened along the rows a GNSS measurement of ``kind`` sees by ``nu nu' + R`` (stays PSD)."""
    rows = list(kin.FIX_ROWS[kind])
    P = P.copy()
    P[np.ix_(rows, rows)] += np.outer(nu, nu) + R
    return P


def set_heading(x: FloatArray, P: FloatArray, phi: float, sigma: float) -> tuple[FloatArray, FloatArray]:
    """The state with the azimuth set to ``phi`` (rad), uncorrelated, with variance ``sigma^2``."""
    x = x.copy()
    x[PHI] = phi
    return kin.wrap_state(x), pin(P, [PHI], np.array([[sigma**2]]))


def pin(P: FloatArray, rows: list[int], R: FloatArray) -> FloatArray:
    """P with the state ``rows`` set outright to a measurement of covariance ``R`` (uncorrelated with the rest)."""
    P = P.copy()
    P[rows, :] = 0.0
    P[:, rows] = 0.0
    P[np.ix_(rows, rows)] = R
    return P


def ekf_predict(
    x: FloatArray, P: FloatArray, dt: float, noise: NoiseSettings, layout: kin.Layout
) -> tuple[FloatArray, FloatArray]:
    """The EKF time update over ``dt`` seconds."""
    F = kin.step_jacobian(x, dt)
    return kin.wrap_state(kin.step(x, dt)), kf_predict(P, F, kin.process_noise(dt, noise, layout))


def can_rows(inputs: Inputs) -> tuple[tuple[str, ...], FloatArray]:
    """Which CAN rows a CAN speed sample brings, and their values."""
    rows: list[str] = []
    z: list[float] = []
    if inputs.speed is not None:
        rows.append(kin.CAN_SPEED)
        z.append(inputs.speed)
    if inputs.yaw_rate is not None:
        rows.append(kin.CAN_YAW_RATE)
        z.append(inputs.yaw_rate)
    if inputs.standstill:
        rows.append(kin.STANDSTILL)
        z.append(0.0)
    return tuple(rows), np.array(z)


def ekf_can_update(
    x: FloatArray, P: FloatArray, inputs: Inputs, noise: NoiseSettings, layout: kin.Layout
) -> tuple[FloatArray, FloatArray, float]:
    """The EKF update with the CAN rows of ``inputs``; also returns the update's log-likelihood."""
    rows, z = can_rows(inputs)
    if not rows:
        return x, P, 0.0
    H = kin.can_jacobian(x, rows, layout)
    R = np.diag(np.square(kin.can_sigmas(rows, noise)))
    nu = z - kin.can_model(x, rows, layout)
    loglik = gaussian_loglik(nu, H @ P @ H.T + R)
    x, P = kf_update(x, P, nu, H, R)
    return kin.wrap_state(x), P, loglik


def ekf_innovation(
    x: FloatArray, P: FloatArray, kind: str, z: FloatArray, R: FloatArray, lag: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Innovation, its covariance and the Jacobian of a GNSS measurement of ``kind``."""
    H = kin.fix_jacobian(x, kind, lag)
    nu = kin.residual(kind, z, kin.fix_model(x, kind, lag))
    return nu, H @ P @ H.T + R, H


def gaussian_loglik(nu: FloatArray, S: FloatArray) -> float:
    """log N(nu; 0, S)."""
    _, logdet = np.linalg.slogdet(S)
    return -0.5 * float(nu @ np.linalg.solve(S, nu) + logdet + len(nu) * math.log(2.0 * math.pi))


class GaussianFilter(RecursiveEstimator):
    """A filter whose belief is a mean ``x`` and a covariance ``P`` (the layout of :mod:`.kinematics`); its noise
    is its own table's (:meth:`tuned`) unless given."""

    x: FloatArray
    P: FloatArray
    snapshot_attrs = ("x", "P")

    def __init__(self, settings: EstimationSettings | None = None, noise: NoiseSettings | None = None) -> None:
        settings = settings or EstimationSettings()
        super().__init__(settings, noise or self.tuned(settings))

    @classmethod
    def from_config(cls, config: Config) -> GaussianFilter:
        return cls(config.estimation)

    @staticmethod
    def tuned(settings: EstimationSettings) -> NoiseSettings:
        """The noise of its table, ``[estimator.ekf]``."""
        return settings.estimator.ekf

    def _reset_filter(self) -> None:
        self.x = np.zeros(self.layout.n)
        self.P = np.eye(self.layout.n)

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        self.x, self.P = x0.copy(), P0.copy()

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        self.P = inflate(self.P, kind, nu, R)

    def _init_heading(self, phi: float, sigma: float) -> None:
        self.x, self.P = set_heading(self.x, self.P, phi, sigma)

    def _mean(self) -> FloatArray:
        return self.x

    def _covariance(self) -> FloatArray:
        return self.P


class Ekf(GaussianFilter):
    """Extended Kalman filter (``ekf``): the shared model linearised at the estimate."""

    name = "ekf"

    def _predict(self, dt: float, inputs: Inputs) -> None:
        self.x, self.P = ekf_predict(self.x, self.P, dt, self.noise, self.layout)

    def _can_update(self, inputs: Inputs) -> None:
        self.x, self.P, _ = ekf_can_update(self.x, self.P, inputs, self.noise, self.layout)

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        nu, S, H = ekf_innovation(self.x, self.P, kind, z, R, lag)

        def commit() -> None:
            x, self.P = kf_update(self.x, self.P, nu, H, R)
            self.x = kin.wrap_state(x)

        return Pending(nu, S, commit)
