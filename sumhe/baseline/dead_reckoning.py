"""Dead reckoning (``dead-reckoning``): the floor every estimator must beat.

At a fix: the position is the fix's (moved to the state's time along the model when the fix is older), the
azimuth the fix's HDT heading or course over ground (above the minimum speed), else the direction of the
motion since the previous fix with an azimuth, once that is ``MOTION_HEADING_M`` long (within
``MOTION_HEADING_MAX_S``). Between fixes and through
outages: the raw CAN speed and yaw rate integrated from there (midpoint rule; no bias or scale correction, no
turning at standstill). No gate: every fix is taken as it is. Until the first azimuth the position holds.
"""

from __future__ import annotations

import math

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.kinematics import OMEGA, PHI, FloatArray, V
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
    """CAN odometry from the last fix (``dead-reckoning``)."""

    name = "dead-reckoning"
    gated = False
    uses_gps_speed = False

    def __init__(self, settings: EstimationSettings | None = None, noise: NoiseSettings | None = None) -> None:
        super().__init__(settings or EstimationSettings(), noise or NoiseSettings())

    @classmethod
    def from_config(cls, config: Config) -> DeadReckoning:
        return cls(config.estimation)

    def _reset_filter(self) -> None:
        self.x = np.zeros(self.layout.n)
        self._anchor: FloatArray | None = None
        self._anchor_t = -math.inf

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        self.x = x0.copy()
        self._anchor = x0[[kin.E, kin.N]].copy()
        self._anchor_t = self._t_state

    def _set_inputs(self, inputs: Inputs) -> None:
        self.x[V] = inputs.speed if inputs.speed is not None else 0.0
        moving = not inputs.standstill and inputs.yaw_rate is not None
        self.x[OMEGA] = inputs.yaw_rate if moving else 0.0

    def _predict(self, dt: float, inputs: Inputs) -> None:
        self._set_inputs(inputs)
        if self._heading_known:
            self.x = kin.wrap_state(kin.step(self.x, dt))

    def _can_update(self, inputs: Inputs) -> None:
        self._set_inputs(inputs)

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        nu = kin.residual(kind, z, kin.fix_model(self.x, kind, lag))

        def commit() -> None:
            self._inflate(kind, nu, R)

        return Pending(nu, R, commit)

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        """Move the state by the innovation (taking the measurement as it is)."""
        self.x[list(kin.FIX_ROWS[kind])] += nu
        kin.wrap_state(self.x)

    def _init_heading(self, phi: float, sigma: float) -> None:
        self.x[PHI] = phi
        kin.wrap_state(self.x)

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
