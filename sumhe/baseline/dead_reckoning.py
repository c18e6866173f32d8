"""Dead reckoning (``dead-reckoning``): the floor every estimator must beat.

At a fix: the position is the fix's (moved to the state's time along the model when the fix is older), the
azimuth the fix's HDT heading or course over ground (above the minimum speed), else the direction of the
motion since the previous fix with an azimuth, once that is ``MOTION_HEADING_M`` long (within
``MOTION_HEADING_MAX_S``). Between fixes and through
outages: the raw CAN speed and yaw rate integrated from there (midpoint rule; no bias or scale correction, no
turning at standstill). No gate: every fix is taken as it is. Until the first azimuth the position holds.

Error growth model (its error estimates): a covariance carried by the linearised model as the EKF's, with the
speed and yaw rate the raw CAN values' errors. Dead reckoning corrects neither the CAN speed scale ``k`` nor the
yaw-rate bias ``b``, so their errors are rows of the covariance (:class:`~sumhe.baseline.kinematics.Layout`'s ``b``
and ``k``), with the filters' priors: half their configured maxima as one sigma, from the first fix on, never
reset by a fix (they are the sensors', and a fix does not tell dead reckoning of them); at every CAN sample the
speed's error is the speed times the scale's plus the sensor's noise, the yaw rate's the bias's plus its noise
(none at standstill, where no turning is integrated). So the same bias turns the azimuth all through an outage:
its variance grows as the outage's length squared, the position's across the track as its fourth power, and the
scale's along it as its square. Taken afresh at every sample instead (white noise), they grew as the length and
its cube: at 50 Hz, after 60 s, the bias's part of the azimuth's variance 3000 times too small, after 10 s 500
times, and the one growth scale the fixes after gaps give (:class:`~sumhe.estimator.uncertainty.InnovationScale`)
could fit one outage length only: on the shared real drive it was 4-6 before the 10 s outages, 15-22 before the
30 s and up to 34 before the 60 s ones, and is 0.45 before all of them now, the square of the drive's bias (0.38
deg/s) over its prior sigma (0.57 deg/s). A fix sets the position (and an azimuth the azimuth) to the
measurement's covariance.

Nor does it correct the CAN yaw rate's gain ``g`` (CAN yaw rate = g omega + b), a row too, with half
``sensors.can.yaw_rate_gain_max`` as one sigma (the Kalman filters estimate it, the particle filters leave it out of
their states, :meth:`~sumhe.baseline.kinematics.Layout.from_settings`; dead reckoning estimates neither): in a turn
the yaw rate is also off by the yaw rate times the gain's error, and a 90 degree turn leaves the azimuth off by 0.12
rad (one sigma). On the realistic profile's sharp-turn outages the growth scale had taken it for growth (6.3 and 4.0
after two drives' sharp outages, 1.3 and 0.56 with it; most drives' 0.1-1.2 as they were).
"""

from __future__ import annotations

import math

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import kf_predict, pin, set_heading
from sumhe.baseline.kinematics import OMEGA, FloatArray, V
from sumhe.baseline.stream import Inputs, Pending, RecursiveEstimator
from sumhe.config import Config
from sumhe.frontend.stream import FixMeasurement
from sumhe.settings import EstimationSettings, NoiseSettings

MOTION_HEADING_M = 5.0
"""Distance (m) between fixes that gives an azimuth when the receiver sends neither course nor heading."""
MOTION_HEADING_MAX_S = 5.0
"""... covered within this time (a longer chord is no longer the direction of travel)."""
MOTION_HEADING_SIGMA_RAD = 0.2


class DeadReckoning(RecursiveEstimator):
    """CAN odometry from the last fix (``dead-reckoning``). Its layout has the CAN yaw-rate bias, speed scale and
    yaw-rate gain whatever ``[estimator]`` says the filters estimate: dead reckoning estimates none of them, and
    their errors are in its covariance (the module docstring)."""

    name = "dead-reckoning"
    gated = False
    uses_gps_speed = False
    averages_fixes = False
    snapshot_attrs = ("x", "P", "_anchor", "_anchor_t")

    def __init__(self, settings: EstimationSettings | None = None, noise: NoiseSettings | None = None) -> None:
        super().__init__(settings or EstimationSettings(), noise or NoiseSettings())
        self.layout = kin.Layout(bias=True, scale=True, gain=True)
        self._reset_filter()

    @classmethod
    def from_config(cls, config: Config) -> DeadReckoning:
        return cls(config.estimation)

    def _reset_filter(self) -> None:
        self.x = np.zeros(self.layout.n)
        self.P = np.eye(self.layout.n)
        self._anchor: FloatArray | None = None
        self._anchor_t = -math.inf

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        self.x, self.P = x0.copy(), P0.copy()
        g = self.layout.g
        assert g is not None
        self.P[g, g] = (0.5 * self.settings.can.yaw_rate_gain_max) ** 2
        self._anchor = x0[[kin.E, kin.N]].copy()
        self._anchor_t = self._t_state

    def _set_inputs(self, inputs: Inputs) -> None:
        self.x[V] = inputs.speed if inputs.speed is not None else 0.0
        moving = not inputs.standstill and inputs.yaw_rate is not None
        self.x[OMEGA] = inputs.yaw_rate if moving else 0.0
        self.P = raw_input_errors(self.P, self.x, moving, self.layout, self.noise)

    def _predict(self, dt: float, inputs: Inputs) -> None:
        self._set_inputs(inputs)
        Q = kin.process_noise(dt, self.noise, self.layout)
        if self._heading_known:
            F = kin.step_jacobian(self.x, dt)
            self.x, self.P = kin.wrap_state(kin.step(self.x, dt)), kf_predict(self.P, F, Q)
        else:
            self.P = self.P + Q

    def _can_update(self, inputs: Inputs) -> None:
        self._set_inputs(inputs)

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        nu = kin.residual(kind, z, kin.fix_model(self.x, kind, lag))

        def commit() -> None:
            self._inflate(kind, nu, R)

        return Pending(nu, R, commit)

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        """Move the state by the innovation (taking the measurement as it is)."""
        rows = list(kin.FIX_ROWS[kind])
        self.x[rows] += nu
        kin.wrap_state(self.x)
        self.P = pin(self.P, rows, R)

    def _init_heading(self, phi: float, sigma: float) -> None:
        self.x, self.P = set_heading(self.x, self.P, phi, sigma)

    def _fix_angle(self, fix: FixMeasurement) -> tuple[float, float] | None:
        angle = super()._fix_angle(fix)
        here, t = np.array([fix.east_m, fix.north_m]), fix.t
        if angle is not None or self._anchor is None or t - self._anchor_t > MOTION_HEADING_MAX_S:
            self._anchor, self._anchor_t = here, t
            return angle
        d = here - self._anchor
        if math.hypot(*d) < MOTION_HEADING_M:
            return None
        self._anchor, self._anchor_t = here, t
        return math.atan2(d[0], d[1]), MOTION_HEADING_SIGMA_RAD

    def _mean(self) -> FloatArray:
        return self.x

    def _covariance(self) -> FloatArray:
        return self.P


def raw_input_errors(
    P: FloatArray, x: FloatArray, turning: bool, layout: kin.Layout, noise: NoiseSettings
) -> FloatArray:
    """``P`` with the speed and yaw-rate rows set to the errors of the raw CAN values ``x[V]`` (m/s) and
    ``x[OMEGA]`` (rad/s) taken as they are: the speed, ``k v``, is off by itself times the scale's error (the
    estimate 1 less ``k``; row ``layout.k``); the yaw rate, ``g omega + b``, by the bias (the estimate 0 less
    ``b``; row ``layout.b``) while ``turning`` (else it is taken as 0, and the bias is not integrated) and by itself
    times the gain's error (row ``layout.g``); each plus its sensor's independent noise (``noise.can_speed_mps``,
    ``noise.can_yaw_rate_rps``). Their correlation with the sensor rows carries the errors the state's rows
    integrate from them, sample after sample."""
    b, k, g = layout.b, layout.k, layout.g
    assert b is not None and k is not None and g is not None
    A = np.eye(len(P))
    A[[V, OMEGA]] = 0.0
    A[V, k] = -x[V]
    A[OMEGA, b] = -1.0 if turning else 0.0
    A[OMEGA, g] = -x[OMEGA]
    P = A @ P @ A.T
    P[V, V] += noise.can_speed_mps**2
    P[OMEGA, OMEGA] += noise.can_yaw_rate_rps**2
    return P
