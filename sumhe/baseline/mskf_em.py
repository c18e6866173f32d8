"""Multi-stage Kalman filter with on-line EM re-estimation of the noise covariances on blocks (``mskf-em``), paper 002.

Paper 002 splits the fusion into stages instead of one large filter: a gyroscope filter for the orientation
(its UKF1), an estimator combination (EC) of that orientation with the GNSS one (eq. 10, fed back into the
gyroscope filter), and a position filter (its UKF2) that takes the combined orientation as a control input. The
noise covariances of the stages are re-estimated by EM on blocks of data: an RTS smoother over the block (eqs.
13-14, the E-step), then the process noise (eq. 15) and the observation noise (eq. 16) from the smoothed states
(the M-step), iterated on the cached block and handed to the next block (its section IV, "TV-MS").

On sumhe's sensors (GNSS + CAN speed and yaw rate, no accelerometer) the stages are:

* heading stage (002's gyroscope UKF1), state ``(phi, b)``: ``phi_k+1 = phi_k - (omega_CAN - b) dt`` with the
  CAN yaw rate as input (0 at a standstill, where the CAN yaw rate measures ``b``), ``b`` a random walk;
  process noise ``Q = q_h diag(dt, 0) + diag(sigma_CAN^2 dt^2, bias_rw^2 dt)``;
* estimator combination (002 eq. 10, ``(P_EC)^-1 mu_EC = (P_gyro)^-1 mu_gyro + (P_GPS)^-1 mu_GPS``): the GNSS
  course (or heading) fused with the heading stage's azimuth by their covariances, written as the heading stage's
  Kalman update with the course as measurement (the same ``mu_EC`` and ``P_EC``; the bias follows through its
  covariance with the azimuth), which is also the feedback of the EC result into the gyroscope filter;
* position stage (002's UKF2), state ``(east, north, s)`` with ``v = s * CAN speed``: ``east_k+1 = east_k + s u
  dt sin phi``, ``north_k+1 = north_k + s u dt cos phi`` with the combined azimuth ``phi`` (midpoint of the step)
  and the CAN speed ``u`` as control inputs (002: ``u = mu_EC``); process noise ``Q = q_p diag(dt, dt, 0) + P_phi g
  g' + diag(0, 0, scale_rw^2 dt)``, ``g = s u dt (cos phi, -sin phi, 0)`` (the combined azimuth's uncertainty);
  GNSS position (``R = r R_fix``, ``R_fix`` the front-end's) and speed over ground (``s u``).

EM on blocks of ``block_s`` seconds (002's 2-6 s for the process noises): when a block ends, it is filtered again
from its first state with the current ``q_h``, ``q_p`` and ``r``, smoothed (RTS, eqs. 13-14, lag-one covariance
``P_k+1,k|N = P_k+1|N C_k'``), and the scales re-estimated, up to ``em_iterations`` times or until they change by
less than 1 %: for ``Q = q Q_1 + Q_0`` (Q_1 diagonal) the M-step of eq. 15 projected on the scale, ``q = mean over
steps and rows of (E[w w']_ii - Q_0,ii) / Q_1,ii``, with ``E[w w'] = d d' + P_k+1|N + F P_k|N F' - P_k+1,k|N F' - F
P_k+1,k|N'``, ``d = x_k+1|N - F x_k|N - c``; the GNSS noise scale from eq. 16, ``r = mean of tr(R_fix^-1 (e e' + H
P_k|N H')) / 2`` over the fixes of the last ``r_window_s`` seconds (002's 30-40 s for the GNSS covariance), ``e = z -
H x_k|N``. The scales are kept within ``[1/scale_limit, scale_limit]`` times their tuned start values; a block whose
EM ends with a scale at its upper bound is counted and said (``em_at_limit``, :data:`EM_AT_LIMIT`: on the shared real
drive the position and GNSS scales ran to their upper bounds, at 10 as at 100, and the filter came to lag the fixes
by 10-14 m; docs/baselines.md). The live filter is not re-run: the new values apply from the next block on (002's
step 6). A block ends with the first fix ``block_s`` after it began (without one, in an outage, ``BLOCK_WAIT_S``
later), so that a late fix's re-run (:mod:`.stream`) never crosses a block's end: ended at a CAN tick, a block's EM
ran again in the re-run of every fix older than that tick (on the 60 s contract drive with fixes 0.25 s late, 4x the
CPU time).

Where it deviates from 002 and why:

* no GNSS-only stage (002's KF1, a constant-acceleration filter of the fixes whose velocity gives the GNSS
  orientation): receivers report the course over ground from Doppler, a better orientation than the direction of
  a position filter's velocity; the GNSS noise it re-estimated is re-estimated in the position stage, which
  observes the same fixes (002 computes the shared entries "only once" too). A receiver that sends neither a
  course nor a heading gives the chord between consecutive fixes instead (``azimuth_from_motion``,
  :mod:`.stream`): without it the heading stage ran on the CAN yaw rate alone from an azimuth of 0, and the
  shared real drive without its headings was 113-557 m off the removed fixes;
* linear Kalman filters, not UKFs: with the CAN yaw rate and speed as inputs and the combined azimuth as the
  position stage's control input (as 002 does), both stages are linear, and an unscented transform of a linear
  model is the Kalman filter;
* the EM estimates scales of the tuned covariances, not full matrices: blocks of 5 s are too short for full
  matrices (002 saw its IMM degrade for too many covariance parameters), and the CAN, bias and scale noises stay
  as tuned;
* no CAN yaw-rate gain state, as ``gtsam-fls`` (``gain0`` is ignored).

Its error estimate is the stages' joint covariance (:func:`joint_step`, the estimates do not change) with the offset of
a receiver's heading considered (Schmidt's consider covariance, where the Kalman filters estimate it,
:class:`~sumhe.baseline.ekf.OffsetFilter`; the offset's variance :func:`~.heading_offset.heading_offset_variance`): the
combination takes a heading for the azimuth the position stage moves along, so the joint covariance carries the offset
as a sixth row (:data:`OFFSET_ROW`), constant through the steps, seen by the heading stage's updates with a heading and
never updated (the estimates, the stages' and the EM's, do not change). Before, it added the offset's part from the way
moved since the newest position fix alone (the position at the fix taken as right, the azimuth off by the whole offset),
while between fixes the combined azimuth follows the headings and the fixes pull the position back only in part
(`docs/error-estimates.md`, `cons18`). The position stage's own covariance takes the azimuth's error as white noise,
``P_phi g g'`` afresh at every step, while it is one slowly drifting error: over an outage of ``t`` seconds an azimuth
error at its start moves the position by the way moved times it (variance ``t^2``, the stage alone: ``dt t``, ``dt`` the
CAN period), the CAN yaw rate's bias integrated twice (``t^4``, the stage alone: ``dt t^3``). The joint covariance of
``(east, north, s, phi, b, offset)`` carries the cross-covariance between the stages, moved by the same steps and
updated with the stages' own gains (Joseph form: the covariance of the errors the filter makes, a Schmidt consider
covariance of the stages' neglected coupling).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import considered
from sumhe.baseline.heading_offset import FollowsHeadings, heading_offset_variance
from sumhe.baseline.kinematics import OMEGA, PHI, E, FloatArray, N, V
from sumhe.baseline.stream import Inputs, Pending
from sumhe.config import Config
from sumhe.frontend.stream import FixMeasurement
from sumhe.messages import GpsStatus
from sumhe.model.su import wrap_angle
from sumhe.settings import EstimationSettings, MskfSettings

EM_TOLERANCE = 0.01
"""EM stops iterating on a block when no scale changes by more than this share."""
EM_AT_LIMIT = (
    "the EM's %s noise scale at its bound, %g x its start value (estimator.mskf_em.scale_limit): the data disagree "
    "with the stages' model, its fixed noises included, by more than the scale can take up (slowly wandering GNSS "
    "errors, a CAN calibration or a course noise beyond the fixed noises); held there, the filter can lag the fixes "
    "by metres"
)
"""Said (``em_at_limit``, each block the EM ends with a scale at its upper bound) where the EM runs to its bound."""
BLOCK_WAIT_S = 1.0
"""A block ends with the first fix ``block_s`` after it began; without a fix (an outage), this much later."""


@dataclass(slots=True)
class Step:
    """One predict step of a linear stage (``x' = F x + c``, ``Q = q Q1 + Q0``) and the updates after it: each
    ``(H, z, R, scaled)`` (``z`` less any known offset; ``R`` times the GNSS scale ``r`` when ``scaled``)."""

    F: FloatArray
    c: FloatArray
    Q1: FloatArray
    Q0: FloatArray
    updates: list[tuple[FloatArray, FloatArray, FloatArray, bool]] = field(default_factory=list)


@dataclass(frozen=True, slots=True)
class Moments:
    """What a smoothed block says about the noise: the process-noise scale and the GNSS sums (sum of
    ``tr(R^-1 E[e e'])`` and of the measured rows)."""

    q: float
    r_sum: float
    r_rows: int


@dataclass(frozen=True, slots=True)
class StageState:
    """A :class:`LinearStage` at one time: mean, covariance, noise scale, its block's start and steps, and how far
    the steps had come (steps and their updates are only appended; a new block takes a new list)."""

    x: FloatArray
    P: FloatArray
    q: float
    x0: FloatArray
    P0: FloatArray
    steps: list[Step]
    n_steps: int
    n_updates: int


def residual(z: FloatArray, zhat: FloatArray, wrap: bool) -> FloatArray:
    """``z - zhat``, wrapped to (-pi, pi] for an angle."""
    d = z - zhat
    return np.asarray(wrap_angle(d), dtype=float) if wrap else d


def kalman_gain(P: FloatArray, H: FloatArray, R: FloatArray) -> FloatArray:
    """``K = P H' (H P H' + R)^-1``."""
    return np.asarray(np.linalg.solve(H @ P @ H.T + R, H @ P).T, dtype=float)


def kf_update(
    x: FloatArray, P: FloatArray, H: FloatArray, z: FloatArray, R: FloatArray, wrap: bool
) -> tuple[FloatArray, FloatArray]:
    """One Kalman update (Joseph form); the residual wrapped when ``wrap`` (an angle)."""
    K = kalman_gain(P, H, R)
    x = x + K @ residual(z, H @ x, wrap)
    IKH = np.eye(len(x)) - K @ H
    P = IKH @ P @ IKH.T + K @ R @ K.T
    return x, 0.5 * (P + P.T)


def kf_step(
    x: FloatArray, P: FloatArray, step: Step, q: float, r: float, wrap: bool
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """A step of a linear stage: prior (``x, P`` moved by ``F``, ``c``, ``q Q1 + Q0``) and posterior after its
    updates, ``(x_prior, P_prior, x_post, P_post)``."""
    xp = step.F @ x + step.c  # x^- = F x + c
    Pp = step.F @ P @ step.F.T + q * step.Q1 + step.Q0  # P^- = F P F' + Q
    x, P = xp, Pp
    for H, z, R, scaled in step.updates:
        x, P = kf_update(x, P, H, z, r * R if scaled else R, wrap)
    return xp, Pp, x, P


POSITION_ROWS = (0, 1, 2)
"""The position stage's rows in the joint covariance (``east, north, s``); the heading stage's follow (``phi, b``)."""
HEADING_ROWS = (3, 4)
OFFSET_ROW = 5
"""The considered heading offset's row in the joint covariance, after the stages'."""


def joint_step(J: FloatArray, F: FloatArray, g: FloatArray, Q: FloatArray) -> FloatArray:
    """The joint covariance (6 x 6, ``east, north, s, phi, b, offset``; heading rows already moved by their step)
    after the position stage's step ``F`` with the azimuth's error moving the position by ``g`` (m/rad) and its
    noise ``Q`` (3 x 3, without the azimuth's share, which the cross-covariance carries)."""
    A = np.eye(len(J))
    A[:3, :3] = F
    A[:3, 3] = g
    J = A @ J @ A.T
    J[:3, :3] += Q
    return 0.5 * (J + J.T)


def joint_heading_step(J: FloatArray, F: FloatArray, Q: FloatArray) -> FloatArray:
    """The joint covariance after the heading stage's step ``F`` (2 x 2) and noise ``Q`` (2 x 2)."""
    rows = np.ix_(HEADING_ROWS, HEADING_ROWS)
    A = np.eye(len(J))
    A[rows] = F
    J = A @ J @ A.T
    J[rows] += Q
    return 0.5 * (J + J.T)


def joint_update(
    J: FloatArray, rows: tuple[int, ...], H: FloatArray, K: FloatArray, R: FloatArray, offset: float
) -> FloatArray:
    """The joint covariance after a stage's update with its own gain ``K`` on its ``rows`` (Joseph form, exact
    for any gain: the other stage is not corrected, its cross-covariance is; nor is the heading's offset, which the
    measurement sees ``offset`` times)."""
    n = len(J)
    Kj = np.zeros((n, len(R)))
    Kj[list(rows)] = K
    Hj = np.zeros((len(R), n))
    Hj[:, list(rows)] = H
    Hj[:, OFFSET_ROW] = offset
    IKH = np.eye(n) - Kj @ Hj
    J = IKH @ J @ IKH.T + Kj @ R @ Kj.T
    return 0.5 * (J + J.T)


def smooth_block(
    x0: FloatArray, P0: FloatArray, steps: list[Step], q: float, r: float, wrap_rows: tuple[int, ...]
) -> Moments:
    """E-step (filter, RTS eqs. 13-14) and M-step (eqs. 15-16) of a block of steps from ``(x0, P0)``."""
    wrap = bool(wrap_rows)
    xf, Pf, xp, Pp = [x0], [P0], [x0], [P0]
    for s in steps:
        a, A, b, B = kf_step(xf[-1], Pf[-1], s, q, r, wrap)
        xp.append(a)
        Pp.append(A)
        xf.append(b)
        Pf.append(B)
    xs, Ps = [xf[-1]], [Pf[-1]]
    gains: list[FloatArray] = []
    for k in range(len(steps) - 1, -1, -1):
        C = Pf[k] @ steps[k].F.T @ np.linalg.pinv(Pp[k + 1])  # smoother gain Lambda_k
        d = xs[0] - xp[k + 1]
        d[list(wrap_rows)] = wrap_angle(d[list(wrap_rows)])
        xs.insert(0, xf[k] + C @ d)  # eq. 13
        Ps.insert(0, Pf[k] + C @ (Ps[0] - Pp[k + 1]) @ C.T)  # eq. 14
        gains.insert(0, C)
    q_sum, q_rows, r_sum, r_rows = 0.0, 0, 0.0, 0
    for k, s in enumerate(steps):
        F = s.F
        d = xs[k + 1] - F @ xs[k] - s.c
        d[list(wrap_rows)] = wrap_angle(d[list(wrap_rows)])
        cross = Ps[k + 1] @ gains[k].T  # P_k+1,k|N
        Eww = np.outer(d, d) + Ps[k + 1] + F @ Ps[k] @ F.T - cross @ F.T - F @ cross.T  # eq. 15's summand
        rows = np.flatnonzero(np.diag(s.Q1) > 0)
        q_sum += float(np.sum((np.diag(Eww)[rows] - np.diag(s.Q0)[rows]) / np.diag(s.Q1)[rows]))
        q_rows += len(rows)
        for H, z, R, scaled in s.updates:
            if scaled:
                e = residual(z, H @ xs[k + 1], False)
                Ee = np.outer(e, e) + H @ Ps[k + 1] @ H.T  # eq. 16's summand
                r_sum += float(np.trace(np.linalg.solve(R, Ee)))
                r_rows += len(z)
    return Moments(q_sum / q_rows if q_rows else math.nan, r_sum, r_rows)


class LinearStage:
    """A linear Kalman filter that records its steps since the block began (for the EM)."""

    def __init__(self, n: int, q: float, wrap_rows: tuple[int, ...] = ()) -> None:
        self.x = np.zeros(n)
        self.P = np.eye(n)
        self.q = q
        self.wrap_rows = wrap_rows
        self.begin_block()

    def begin_block(self) -> None:
        self.x0, self.P0 = self.x.copy(), self.P.copy()
        self.steps: list[Step] = []

    def snapshot(self) -> StageState:
        """The stage now, for :meth:`restore`."""
        updates = len(self.steps[-1].updates) if self.steps else 0
        return StageState(self.x.copy(), self.P.copy(), self.q, self.x0, self.P0, self.steps, len(self.steps), updates)

    def restore(self, state: StageState) -> None:
        """Set the stage back to a :meth:`snapshot` (the block's steps and updates after it are dropped)."""
        self.x, self.P, self.q = state.x.copy(), state.P.copy(), state.q
        self.x0, self.P0, self.steps = state.x0, state.P0, state.steps
        del self.steps[state.n_steps :]
        if self.steps:
            del self.steps[-1].updates[state.n_updates :]

    def predict(self, step: Step, r: float) -> None:
        _, _, self.x, self.P = kf_step(self.x, self.P, step, self.q, r, bool(self.wrap_rows))
        self.steps.append(step)

    def innovation(self, H: FloatArray, z: FloatArray, R: FloatArray, wrap: bool) -> tuple[FloatArray, FloatArray]:
        return residual(z, H @ self.x, wrap), H @ self.P @ H.T + R

    def update(self, H: FloatArray, z: FloatArray, R: FloatArray, scaled: bool, r: float) -> None:
        """Kalman update, recorded on the newest step (R times ``r`` when ``scaled``)."""
        if not self.steps:
            n = len(self.x)
            self.steps.append(Step(np.eye(n), np.zeros(n), np.zeros((n, n)), np.zeros((n, n))))
        self.steps[-1].updates.append((H, z, R, scaled))
        self.x, self.P = kf_update(self.x, self.P, H, z, r * R if scaled else R, bool(self.wrap_rows))


class MskfEm(FollowsHeadings):
    """Multi-stage Kalman filter with on-line block EM of the noise scales (``mskf-em``)."""

    name = "mskf-em"
    azimuth_from_motion = "always"
    """Without a receiver's course or heading the chord between fixes is the GNSS orientation (002's KF1's role):
    the position stage does not turn the heading stage, whose azimuth only the combination corrects."""
    snapshot_attrs = ("r", "_r_blocks", "_u", "_omega", "_t_block", "_joint")
    """... and the two stages (:meth:`LinearStage.snapshot`)."""

    def __init__(self, settings: EstimationSettings | None = None, table: MskfSettings | None = None) -> None:
        settings = settings or EstimationSettings()
        self.table = table or settings.estimator.mskf_em
        super().__init__(settings, self.table.noise)
        self._offset_var = heading_offset_variance(self.settings)

    @classmethod
    def from_config(cls, config: Config) -> MskfEm:
        return cls(config.estimation)

    def stats(self) -> Mapping[str, float | int | str]:
        return {**super().stats(), "q_heading": self.heading.q, "q_position": self.position.q, "r_gnss": self.r}

    # ---- the stages ---------------------------------------------------------------------------------------------

    def _reset_filter(self) -> None:
        self.heading = LinearStage(2, self.noise.heading_rw**2, wrap_rows=(0,))
        self.position = LinearStage(3, self.noise.pos_rw**2)
        self.r = 1.0
        self._r_blocks: deque[tuple[float, int]] = deque(
            maxlen=max(1, round(self.table.r_window_s / self.table.block_s))
        )
        self._u = 0.0
        self._omega = 0.0
        self._t_block = math.nan
        self._joint = considered(np.eye(5), 0.0)

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        b, k = self.layout.b, self.layout.k
        self.heading.x = np.array([x0[PHI], x0[b] if b is not None else 0.0])
        self.heading.P = np.diag([P0[PHI, PHI], P0[b, b] if b is not None else 0.0])
        self.position.x = np.array([x0[E], x0[N], 1.0])
        self.position.P = np.diag([P0[E, E], P0[N, N], P0[k, k] if k is not None else 0.0])
        self._u = float(x0[V])
        self._joint = considered(np.zeros((5, 5)), self._offset_var)
        self._joint[:3, :3], self._joint[3:OFFSET_ROW, 3:OFFSET_ROW] = self.position.P, self.heading.P
        self._begin_blocks()

    def _snapshot(self) -> object:
        return super()._snapshot(), self.heading.snapshot(), self.position.snapshot()

    def _restore(self, state: object) -> None:
        assert isinstance(state, tuple)
        own, heading, position = state
        super()._restore(own)
        self.heading.restore(heading)
        self.position.restore(position)

    def _begin_blocks(self) -> None:
        self.heading.begin_block()
        self.position.begin_block()
        self._t_block = self._t_state

    def _predict(self, dt: float, inputs: Inputs) -> None:
        if inputs.speed is not None:
            self._u = inputs.speed
        moving = not inputs.standstill and inputs.yaw_rate is not None
        yaw = inputs.yaw_rate if moving and inputs.yaw_rate is not None else 0.0
        n = self.noise
        bias_q = n.bias_rw**2 * dt if self.layout.b is not None else 0.0
        F = np.array([[1.0, dt if moving else 0.0], [0.0, 1.0]])  # phi' = -(omega_CAN - b)
        phi_before = float(self.heading.x[0])
        step = Step(
            F, np.array([-yaw * dt, 0.0]), np.diag([dt, 0.0]), np.diag([(n.can_yaw_rate_rps * dt) ** 2, bias_q])
        )
        self.heading.predict(step, self.r)
        self._joint = joint_heading_step(self._joint, F, self.heading.q * step.Q1 + step.Q0)
        phi = phi_before + 0.5 * float(wrap_angle(self.heading.x[0] - phi_before))
        s, u = float(self.position.x[2]), self._u
        sin, cos = math.sin(phi), math.cos(phi)
        F = np.eye(3)
        F[0, 2], F[1, 2] = u * dt * sin, u * dt * cos
        g = s * u * dt * np.array([cos, -sin, 0.0])
        scale_q = n.scale_rw**2 * dt if self.layout.k is not None else 0.0
        Q0 = np.diag([0.0, 0.0, scale_q])
        self.position.predict(
            Step(F, np.zeros(3), np.diag([dt, dt, 0.0]), float(self.heading.P[0, 0]) * np.outer(g, g) + Q0), self.r
        )
        self._joint = joint_step(self._joint, F, g, self.position.q * np.diag([dt, dt, 0.0]) + Q0)
        self._omega = yaw - float(self.heading.x[1]) if moving else 0.0
        if self._t_state + dt - self._t_block >= self.table.block_s + BLOCK_WAIT_S:
            self._em()  # no fix ended the block (an outage)

    def _fix_updates(self, fix: FixMeasurement, lag: float) -> GpsStatus:
        """The fix's updates; a block of ``block_s`` ends with them."""
        status = super()._fix_updates(fix, lag)
        if self._t_state - self._t_block >= self.table.block_s:
            self._em()
        return status

    def _can_update(self, inputs: Inputs) -> None:
        if inputs.speed is not None:
            self._u = inputs.speed
        if inputs.standstill and inputs.yaw_rate is not None and self.layout.b is not None:
            # at rest the CAN yaw rate measures the bias
            R = np.array([[self.noise.can_yaw_rate_rps**2 + self.noise.standstill_rps**2]])
            self._stage_update(self.heading, np.array([[0.0, 1.0]]), np.array([inputs.yaw_rate]), R, False, 0.0)

    def _fix_rows(self, kind: str, lag: float) -> tuple[LinearStage, FloatArray, FloatArray, bool]:
        """The stage a GNSS measurement of ``kind`` updates, its H, its offset, and whether its R is scaled."""
        if kind == kin.AZIMUTH:  # phi(t - lag) = phi + (omega_CAN - b) lag
            return self.heading, np.array([[1.0, -lag]]), np.array([(self._omega + self.heading.x[1]) * lag]), False
        if kind == kin.GPS_SPEED:
            return self.position, np.array([[0.0, 0.0, self._u]]), np.zeros(1), False
        phi = float(self.heading.x[0])
        H = np.array([[1.0, 0.0, -self._u * lag * math.sin(phi)], [0.0, 1.0, -self._u * lag * math.cos(phi)]])
        return self.position, H, np.zeros(2), True

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        stage, H, offset, scaled = self._fix_rows(kind, lag)
        z = z - offset
        Rk = self.r * R if scaled else R
        nu, S = stage.innovation(H, z, Rk, kind == kin.AZIMUTH)
        offset = 1.0 if kind == kin.AZIMUTH and self._heading else 0.0  # a heading measures azimuth + offset

        def commit() -> None:
            self._stage_update(stage, H, z, R, scaled, offset)

        return Pending(nu, S, commit)

    def _stage_update(
        self, stage: LinearStage, H: FloatArray, z: FloatArray, R: FloatArray, scaled: bool, offset: float
    ) -> None:
        """``stage``'s Kalman update, and the joint covariance's with the stage's gain (:func:`joint_update`; the
        heading's offset seen ``offset`` times)."""
        Rk = self.r * R if scaled else R
        K = kalman_gain(stage.P, H, Rk)
        rows = HEADING_ROWS if stage is self.heading else POSITION_ROWS
        self._joint = joint_update(self._joint, rows, H, K, Rk, offset)
        stage.update(H, z, R, scaled, self.r)

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        wide = np.outer(nu, nu) + R
        if kind == kin.AZIMUTH:
            self.heading.P[0, 0] += wide[0, 0]
            self._joint[3, 3] += wide[0, 0]
        elif kind == kin.GPS_SPEED:
            self.position.P[2, 2] += wide[0, 0] / max(self._u, 1.0) ** 2
            self._joint[2, 2] += wide[0, 0] / max(self._u, 1.0) ** 2
        else:
            self.position.P[:2, :2] += wide
            self._joint[:2, :2] += wide
        self._begin_blocks()  # the widened prior is no process noise: the EM starts a new block

    def _init_heading(self, phi: float, sigma: float) -> None:
        P = self.heading.P
        P[0, :] = 0.0
        P[:, 0] = 0.0
        P[0, 0] = sigma**2
        self._joint[3, :] = 0.0
        self._joint[:, 3] = 0.0
        self._joint[3, 3] = sigma**2
        self.heading.x[0] = phi
        self._begin_blocks()

    def _mean(self) -> FloatArray:
        x = np.zeros(self.layout.n)
        x[E], x[N] = self.position.x[:2]
        x[PHI] = wrap_angle(self.heading.x[0])
        x[V] = self.position.x[2] * self._u
        x[OMEGA] = self._omega
        if self.layout.b is not None:
            x[self.layout.b] = self.heading.x[1]
        if self.layout.k is not None:
            x[self.layout.k] = 1.0 / self.position.x[2]
        return x

    def _covariance(self) -> FloatArray:
        """The stages' joint covariance (:func:`joint_step`, a heading's offset considered) in the shared layout
        (the speed's from the scale's, times the CAN speed)."""
        T = np.zeros((self.layout.n, OFFSET_ROW))
        T[E, 0], T[N, 1], T[V, 2], T[PHI, 3] = 1.0, 1.0, self._u, 1.0
        if self.layout.b is not None:
            T[self.layout.b, 4] = 1.0
        return T @ self._joint[:OFFSET_ROW, :OFFSET_ROW] @ T.T

    def considered_m2(self) -> float:
        """What the considered offset adds to the position's variance (trace, m^2)
        (:meth:`~sumhe.estimator.base.StreamEstimator.considered_m2`): the offset never updated, its part is ``c c' /
        sigma^2``, ``c`` the position's covariance with it."""
        if not self._offset_var:
            return 0.0
        cross = self._joint[[0, 1], OFFSET_ROW]
        return float(cross @ cross) / self._offset_var

    # ---- EM on the block that ended ------------------------------------------------------------------------------

    def _em(self) -> None:
        """Re-estimate ``q_h``, ``q_p`` and ``r`` on the block just ended (E- and M-steps, iterated), start the next."""
        limit = self.table.scale_limit
        start = (self.noise.heading_rw**2, self.noise.pos_rw**2)
        q_h, q_p, r = self.heading.q, self.position.q, self.r
        done = list(self._r_blocks)
        for _ in range(self.table.em_iterations):
            mh = smooth_block(self.heading.x0, self.heading.P0, self.heading.steps, q_h, r, (0,))
            mp = smooth_block(self.position.x0, self.position.P0, self.position.steps, q_p, r, ())
            r_sum = sum(s for s, _ in done) + mp.r_sum
            r_rows = sum(n for _, n in done) + mp.r_rows
            new = (
                clamp(mh.q, start[0], limit, q_h),
                clamp(mp.q, start[1], limit, q_p),
                clamp(r_sum / r_rows if r_rows else math.nan, 1.0, limit, r),
            )
            change = max(abs(a - b) / b for a, b in zip(new, (q_h, q_p, r), strict=True))
            q_h, q_p, r = new
            if change < EM_TOLERANCE:
                break
        self._r_blocks.append((mp.r_sum, mp.r_rows))
        self.heading.q, self.position.q, self.r = q_h, q_p, r
        self.tally.counts["em_blocks"] += 1
        names = ("heading process", "position process", "GNSS")
        capped = [
            n for n, q, s in zip(names, (q_h, q_p, r), (*start, 1.0), strict=True) if limit > 1.0 and q >= s * limit
        ]
        if capped:
            self.tally.count("em_at_limit", EM_AT_LIMIT, " and ".join(capped), limit)
        self._begin_blocks()


def clamp(value: float, start: float, limit: float, fallback: float) -> float:
    """``value`` within ``[start / limit, start * limit]``; ``fallback`` when it is not a number (no data)."""
    if not math.isfinite(value):
        return fallback
    return min(max(value, start / limit), start * limit)
