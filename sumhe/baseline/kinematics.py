"""The motion and measurement models every recursive baseline shares, with their Jacobians (numpy), taken from
the SU model of :mod:`sumhe.model.su`: the peers and the SU estimators run one model.

State (the single-antenna SU model ``su5`` of paper 000 with the optional CAN sensor states of issues 7 and 12),
in its order: east, north (m), azimuth phi (rad, clockwise from north), speed v (m/s), yaw rate omega (rad/s,
anticlockwise positive), then the CAN yaw-rate bias b (rad/s), the CAN speed scale k (CAN speed = k v) and the CAN
yaw-rate gain g (CAN yaw rate = g omega + b) when the :class:`Layout` carries them.

Continuous model: ``east' = v sin phi``, ``north' = v cos phi``, ``phi' = -omega``; v, omega, b and k are random
walks. One step of ``dt`` seconds is su5's trapezoidal transition at constant speed and yaw rate,
``T(x, x, dt)``: the midpoint azimuth ``phi - omega dt / 2`` (exact on a straight line, second order on a circle);
its Jacobian is CasADi's (:func:`sumhe.model.compiled.kinematic_jacobian`); ``dt`` may be negative, which is how a
fix older than the state (receiver latency) is compared with it. Every function takes a state of shape ``(n,)``
or a stack of states ``(n, M)`` (sigma points, particles) unless it says otherwise.

Measurements: a GNSS position (east, north), azimuth (GPS course over ground or HDT heading) and speed over
ground (Doppler, the speed v) at ``lag`` seconds before the state's time, and the CAN rows ``k v`` (speed) and
``omega + b`` (yaw rate), plus the standstill row ``omega = 0`` (a car at rest does not turn).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from numpy.typing import NDArray

from sumhe.model import compiled
from sumhe.model.su import SU5_STATES, SuModel, can_outputs, su_model, wrap_angle
from sumhe.settings import EstimationSettings, NoiseSettings

FloatArray = NDArray[np.float64]

E, N, PHI, V, OMEGA = (SU5_STATES.index(s) for s in ("px", "py", "phi", "v", "omega"))
_KINEMATICS = su_model("su5", discretisation="trapezoid")
"""The transition of every step (states beyond the kinematic five are carried unchanged)."""
POSITION = "position"
AZIMUTH = "azimuth"
GPS_SPEED = "gps_speed"
FIX_ROWS = {POSITION: (E, N), AZIMUTH: (PHI,), GPS_SPEED: (V,)}
"""State rows a GNSS measurement of each kind observes."""
CAN_SPEED, CAN_YAW_RATE, STANDSTILL = "speed", "yaw_rate", "standstill"


@dataclass(frozen=True, slots=True)
class Layout:
    """Which optional states follow the five kinematic ones: CAN yaw-rate bias ``b``, CAN speed scale ``k`` and CAN
    yaw-rate gain ``g``."""

    bias: bool = True
    scale: bool = True
    gain: bool = True

    @classmethod
    def from_settings(cls, settings: EstimationSettings, noise: NoiseSettings) -> Layout:
        """The states of ``[estimator]``; the yaw-rate gain only where the filter's ``gain0`` (its prior sigma) is
        set (the Kalman filters' tables: they take the CAN yaw rate as an input, :func:`~.ekf.yaw_rate_input`;
        not the particle filters', whose gain as a particle state moved the realistic drives' outages either way)."""
        e = settings.estimator
        return cls(bias=e.yaw_rate_bias, scale=e.speed_scale, gain=e.yaw_rate_gain and noise.gain0 > 0)

    @property
    def model(self) -> SuModel:
        """The su5 model with these states."""
        return su_model("su5", self.bias, self.scale, yaw_rate_gain=self.gain)

    @property
    def n(self) -> int:
        """Number of states."""
        return self.model.n_states

    @property
    def b(self) -> int | None:
        """Row of the yaw-rate bias, or None."""
        return self.model.i_bias

    @property
    def k(self) -> int | None:
        """Row of the speed scale, or None."""
        return self.model.i_scale

    @property
    def g(self) -> int | None:
        """Row of the yaw-rate gain, or None."""
        return self.model.i_gain

    @property
    def sensor_rows(self) -> tuple[int, ...]:
        """The rows of the CAN sensor states (bias, scale, gain) it has."""
        return tuple(r for r in (self.b, self.k, self.g) if r is not None)


def chi2_threshold(prob: float, dof: int) -> float:
    """The ``prob`` quantile of the chi-square distribution with 1 or 2 degrees of freedom (inf for prob 1)."""
    if prob >= 1.0:
        return math.inf
    if dof == 1:
        return NormalDist().inv_cdf(0.5 + 0.5 * prob) ** 2
    if dof == 2:
        return -2.0 * math.log1p(-prob)
    raise ValueError(f"dof: 1 or 2, got {dof!r}")


def step(x: FloatArray, dt: float) -> FloatArray:
    """The state(s) ``dt`` seconds later: ``T(x, x, dt)`` of su5 (extra states carried unchanged)."""
    return np.array(_KINEMATICS.transition(x, x, dt), dtype=float)


def step_jacobian(x: FloatArray, dt: float) -> FloatArray:
    """d step(x, dt) / dx for one state ``x`` of shape ``(n,)``."""
    return compiled.kinematic_jacobian(len(x))(x, dt)


def process_noise(dt: float, noise: NoiseSettings, layout: Layout) -> FloatArray:
    """Q of one step of ``dt`` seconds: independent random walks of every state (n x n)."""
    dens = [noise.pos_rw, noise.pos_rw, noise.heading_rw, noise.speed_rw, noise.yaw_rate_rw]
    dens += [noise.bias_rw] * int(layout.bias) + [noise.scale_rw] * int(layout.scale)
    dens += [noise.gain_rw] * int(layout.gain)
    return np.diag(np.square(dens) * abs(dt))


def can_model(x: FloatArray, rows: tuple[str, ...], layout: Layout) -> FloatArray:
    """The CAN rows of the state(s): ``speed`` and ``yaw_rate`` as su5 measures them (k v, g omega + b,
    :func:`~sumhe.model.su.can_outputs`), ``standstill`` omega."""
    speed, yaw_rate = can_outputs(x[V], x[OMEGA], x, layout.b, layout.k, layout.g)
    values = {CAN_SPEED: speed, CAN_YAW_RATE: yaw_rate, STANDSTILL: x[OMEGA]}
    return np.array([values[r] for r in rows], dtype=float)


def can_jacobian(x: FloatArray, rows: tuple[str, ...], layout: Layout) -> FloatArray:
    """d can_model / dx for one state (len(rows) x n)."""
    J = compiled.can_jacobian(layout.bias, layout.scale, layout.gain)(x)
    unit = np.eye(len(x))[OMEGA]
    return np.array([{CAN_SPEED: J[0], CAN_YAW_RATE: J[1], STANDSTILL: unit}[r] for r in rows])


def can_sigmas(rows: tuple[str, ...], noise: NoiseSettings) -> FloatArray:
    """Measurement sigmas of the CAN rows."""
    sigma = {CAN_SPEED: noise.can_speed_mps, CAN_YAW_RATE: noise.can_yaw_rate_rps, STANDSTILL: noise.standstill_rps}
    return np.array([sigma[r] for r in rows])


def fix_model(x: FloatArray, kind: str, lag: float) -> FloatArray:
    """What a GNSS measurement of ``kind`` taken ``lag`` s before the state's time sees (rows of FIX_ROWS)."""
    xb = step(x, -lag) if lag else x
    return np.asarray(xb[list(FIX_ROWS[kind])], dtype=float)


def fix_jacobian(x: FloatArray, kind: str, lag: float) -> FloatArray:
    """d fix_model / dx for one state."""
    rows = list(FIX_ROWS[kind])
    if not lag:
        return np.eye(len(x))[rows]
    return step_jacobian(x, -lag)[rows]


def residual(kind: str, z: FloatArray, zhat: FloatArray) -> FloatArray:
    """``z - zhat`` with azimuth differences wrapped to (-pi, pi] (broadcasts over stacked ``zhat``)."""
    d = np.asarray(z, dtype=float) - zhat
    return wrap_angle(d) if kind == AZIMUTH else d


def wrap_state(x: FloatArray) -> FloatArray:
    """The state(s) with the azimuth wrapped to (-pi, pi] (in place, and returned)."""
    x[PHI] = wrap_angle(x[PHI])
    return x


def state_difference(x: FloatArray, ref: FloatArray) -> FloatArray:
    """``x - ref`` with the azimuth difference wrapped (broadcasts: ``x`` may be a stack ``(n, M)``)."""
    d = x - (ref[:, None] if x.ndim == 2 and ref.ndim == 1 else ref)
    d[PHI] = wrap_angle(d[PHI])
    return d


def weighted_mean(x: FloatArray, w: FloatArray) -> FloatArray:
    """Mean of stacked states ``(n, M)`` with weights ``w`` (sum 1); the azimuth as a circular mean."""
    m = x @ w
    m[PHI] = math.atan2(float(np.sin(x[PHI]) @ w), float(np.cos(x[PHI]) @ w))
    return m


def weighted_covariance(x: FloatArray, w: FloatArray, mean: FloatArray) -> FloatArray:
    """Covariance of stacked states ``(n, M)`` with weights ``w`` (sum 1) about ``mean`` (azimuth differences
    wrapped)."""
    d = state_difference(x, mean)
    return np.asarray((d * w) @ d.T, dtype=float)


def measurement_mean(kind: str, z: FloatArray, w: FloatArray) -> FloatArray:
    """Weighted mean of stacked measurements ``(rows, M)`` of ``kind``; an azimuth as a circular mean."""
    if kind == AZIMUTH:
        return np.array([math.atan2(float(np.sin(z[0]) @ w), float(np.cos(z[0]) @ w))])
    return np.asarray(z @ w, dtype=float)
