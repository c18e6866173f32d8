"""GTSAM's incremental fixed-lag smoother over the CAN odometry and the GNSS fixes (``gtsam-fls``).

The factor graph, one node per GNSS epoch ``k`` (at the epoch's time on the CAN clock):

* ``X_k``: a ``Pose2`` (x east, y north, theta anticlockwise from east: ``theta = pi/2 - phi``);
* ``C_k``: the CAN calibration ``(b, k)``, yaw-rate bias (rad/s) and speed scale (CAN speed = k v), a random walk
  between nodes (``BetweenFactorVector``, densities ``bias_rw``, ``scale_rw``);
* the CAN odometry between ``X_k`` and ``X_k+1`` as a custom factor on ``(X_k, X_k+1, C_k)``: the CAN samples in
  between integrated with su5's midpoint step (the model of the other peers: ``v = CAN speed / k``,
  ``omega = CAN yaw rate - b``, 0 at standstill) into a relative pose, with its first-order correction for ``b``
  and ``k`` (the preintegration of IMU factor graphs) and its covariance from the CAN sigmas and the model error
  densities (``pos_rw``, ``heading_rw``); a CAN value missing is held, its error a random walk (``speed_rw``,
  ``yaw_rate_rw``: the EKF's model of its speed and yaw-rate states);
* ``O_k``: the offset (rad) of a receiver's heading from the azimuth of the motion (mounting, sideslip), a
  first-order Gauss-Markov process between nodes about 0 (:data:`~.heading_offset.OFFSET_CORRELATION_S`, its
  prior's variance at rest: the config's bound read as sigmas, 0.43 deg), as the Kalman filters carry it
  (:class:`~sumhe.baseline.ekf.OffsetFilter`);
* GNSS factors on ``X_k``: position (the front-end's sigmas x ``gps_scale``), azimuth (a course, sigma with
  ``course_rad`` and the antenna lever's error in turns, as the EKF's and the particle filter's:
  :class:`~sumhe.baseline.ekf.LeverCourse`; a heading on ``(X_k, O_k)``, the azimuth plus the offset); on ``C_k``:
  speed over ground against the CAN speed (``k sog = CAN speed``; the front-end's sigma x ``sog_scale``), the CAN
  speed interpolated to the fix's time, none for a fix ahead of the CAN data (the newest CAN speed held to it is the
  speed of up to a GNSS latency earlier: in a realistic offroad drive's braking at 5 m/s^2, 1.9 m/s off a speed over
  ground of 8.5 m/s, which the gate rejected for a second, then re-acquired with the speed scale widened, and ``k``
  jumped by 0.2-0.4 at each while its marginal said 0.002-0.009).

Without ``C_k`` (the odometry taken as it is) the smoother drifted to 25.7 m in the bundled drive's outages; with
it, it matched the MHE (issue 17). The figures: ``docs/baselines.md``.

Why the incremental smoother (iSAM2, ``IncrementalFixedLagSmoother``) rather than the batch one
(``BatchFixedLagSmoother``): each epoch adds one node and a few factors; iSAM2 re-eliminates only the cliques they
touch, the batch smoother re-solves the whole lag window by Levenberg-Marquardt at every update. Both marginalise the
nodes older than ``lag_s`` into a prior on the rest, which keeps the graph (and the memory) bounded.

Stream: the front-end's epochs (:mod:`sumhe.frontend`), the gate and re-acquisition of
:class:`~sumhe.baseline.stream.RecursiveEstimator`. A fix older than the newest CAN data needs no model run back:
its node sits at its own time, and the CAN steps after it go into the next node's odometry. Gating uses the newest
node's marginal covariance carried to the fix by the odometry; re-acquisition widens the odometry factor into the
fix's node. CAN-rate estimates are the newest node carried forward by the odometry since it. Until the first
course or heading gives an azimuth there is no graph: the estimate is the newest fix; from fixes without either
(a receiver that sends neither), the first chord between two of them opens it (``azimuth_from_motion``,
:mod:`.stream`).

Error estimate: the newest node's joint marginal of pose, calibration and offset carried by the odometry
(:meth:`GtsamFls._covariance`).

The offset estimated since 1 Dec 2026: before, a heading's factor took it for the velocity's azimuth, and the
smoother carried the offset (only considered in its error estimate, as the particle filters do) into its estimates:
on the shared real drive (the logger's GNSS/IMU heading, 0.7 deg off the motion by the EKF's estimate) its estimates
with GPS lay 1-4 m left of the fixes on the mean, more as the drive went on, and in the 60 s outages the error across
the track grew linearly with the distance in most of them, at 0.46 deg rms over 18 outages (13 to the left). The
EKF had gone the same way (:class:`~sumhe.baseline.ekf.OffsetFilter`). Figures: docs/baselines.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam  # the optional extra sumhe[peers]: the registry says so when it is missing
import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import LeverCourse
from sumhe.baseline.heading_offset import heading_offset_variance, offset_step
from sumhe.baseline.kinematics import AZIMUTH, GPS_SPEED, OMEGA, PHI, POSITION, E, FloatArray, N, V
from sumhe.baseline.stream import Inputs, Pending
from sumhe.config import Config
from sumhe.estimator.base import StateEstimate
from sumhe.frontend.stream import Epoch
from sumhe.model.su import wrap_angle
from sumhe.settings import EstimationSettings, GtsamSettings, NoiseSettings

MIN_VARIANCE = 1e-8
"""Added to the diagonal of every factor covariance (a node right after the previous one has a zero-length step)."""
FIXED_SIGMA = 1e-6
"""Prior sigma of a CAN state the model does not have (``estimator.yaw_rate_bias`` or ``speed_scale`` off)."""
NO_GRAPH_SIGMA_M = 1e3
"""Position sigma before the graph starts (no azimuth yet): every fix is taken."""
UNKNOWN_SPEED_MPS = 30.0
UNKNOWN_YAW_RATE_RPS = 1.0
"""Sigmas of a CAN speed / yaw rate never measured since the start (held at 0): the odometry then says little and
the nodes follow the fixes."""


def _rot(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


# ---- the CAN odometry between two nodes ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Step:
    """One CAN step: from ``t0`` for ``dt`` s at CAN ``speed`` (m/s) and ``yaw_rate`` (rad/s). Where CAN is
    missing the newest value is held: ``speed_age`` / ``yaw_rate_age`` is then the time (s) since it was measured
    at the step's start (inf: never measured, the value is 0), None for a measured value."""

    t0: float
    dt: float
    speed: float
    yaw_rate: float
    standstill: bool
    speed_age: float | None = None
    yaw_rate_age: float | None = None


def held_variance(age: float, rw: float, unknown: float) -> float:
    """Variance of a held CAN value's error ``age`` s after it was measured: a random walk of density ``rw``
    (the EKF's process model for its speed and yaw-rate states); ``unknown`` squared if it never was."""
    return unknown**2 if math.isinf(age) else rw**2 * age


@dataclass(slots=True)
class Odometry:
    """CAN steps integrated from a node, in the node's frame (x forward, y left, theta anticlockwise), at the
    calibration ``(b0, k0)``; ``J`` = d(dx, dy, dtheta)/d(b, k), ``T`` the time (s). ``cov``: the covariance of
    (dx, dy, dtheta) and of the errors of the held speed and yaw rate (zero while CAN is measured)."""

    b0: float
    k0: float
    dx: float = 0.0
    dy: float = 0.0
    dth: float = 0.0
    T: float = 0.0
    J: FloatArray = field(default_factory=lambda: np.zeros((3, 2)))
    cov: FloatArray = field(default_factory=lambda: np.zeros((5, 5)))

    def add(self, step: Step, dt: float, noise: NoiseSettings) -> None:
        """``dt`` s of ``step`` (su5's midpoint step)."""
        v = step.speed / self.k0
        dv_dk = -v / self.k0
        w, dw_db = (0.0, 0.0) if step.standstill else (step.yaw_rate - self.b0, -1.0)
        mid = self.dth + 0.5 * w * dt
        c, s = math.cos(mid), math.sin(mid)
        J = self.J
        dmid_db, dmid_dk = J[2, 0] + 0.5 * dw_db * dt, J[2, 1]
        J[0, 0] -= dt * v * s * dmid_db  # d(v dt cos mid)/db
        J[0, 1] += dt * (dv_dk * c - v * s * dmid_dk)
        J[1, 0] += dt * v * c * dmid_db  # d(v dt sin mid)/db
        J[1, 1] += dt * (dv_dk * s + v * c * dmid_dk)
        J[2, 0] += dw_db * dt
        held = (
            (3, step.speed_age, noise.speed_rw, UNKNOWN_SPEED_MPS),
            (4, step.yaw_rate_age, noise.yaw_rate_rw, UNKNOWN_YAW_RATE_RPS),
        )
        cov = self.cov
        for i, age, rw, unknown in held:
            if age is not None and cov[i, i] == 0.0:  # a gap starts: the held value's error so far
                cov[i, i] = held_variance(age, rw, unknown)
        dv = dt * np.array([c, s, 0.0])  # d(dx, dy, dtheta)/dv
        dw = dt * np.array([-0.5 * v * dt * s, 0.5 * v * dt * c, 1.0])  # d(dx, dy, dtheta)/domega
        A = np.eye(5)
        A[0, 2], A[1, 2] = -v * dt * s, v * dt * c
        A[:3, 3], A[:3, 4] = dv / self.k0, dw
        cov = self.cov = A @ cov @ A.T
        cov[:3, :3] += np.outer(dv, dv) * (noise.can_speed_mps / self.k0) ** 2
        cov[:3, :3] += np.outer(dw, dw) * noise.can_yaw_rate_rps**2
        cov[:3, :3] += np.diag(np.array([noise.pos_rw, noise.pos_rw, noise.heading_rw]) ** 2 * dt)
        for i, age, rw, _ in held:
            if age is None:  # measured: no held error
                cov[i, :] = cov[:, i] = 0.0
            elif math.isfinite(age):
                cov[i, i] += rw**2 * dt  # the held value's error walks on
        self.dx += v * dt * c
        self.dy += v * dt * s
        self.dth += w * dt
        self.T += dt

    def delta(self, b: float, k: float) -> FloatArray:
        """(dx, dy, dtheta) at the calibration ``(b, k)`` (first order about ``(b0, k0)``)."""
        return np.array([self.dx, self.dy, self.dth]) + self.J @ np.array([b - self.b0, k - self.k0])


def integrate(steps: list[Step], b0: float, k0: float, noise: NoiseSettings, until: float = math.inf) -> Odometry:
    """The steps up to time ``until`` integrated at ``(b0, k0)`` (a step that straddles it, in part)."""
    odo = Odometry(b0, k0)
    for s in steps:
        dt = min(s.dt, until - s.t0)
        if dt <= 0.0:
            break
        odo.add(s, dt, noise)
    return odo


def after(steps: list[Step], t: float) -> list[Step]:
    """The part of ``steps`` after time ``t``."""
    out = []
    for s in steps:
        if s.t0 + s.dt <= t:
            continue
        cut = max(t - s.t0, 0.0)
        out.append(dataclasses.replace(s, t0=s.t0 + cut, dt=s.dt - cut) if cut else s)
    return out


# ---- the factors (GTSAM's CustomFactor: error and Jacobians on the tangent spaces) -----------------------------

ErrorFunction = Callable[[Any, Any, Any], FloatArray]


def odometry_error(odo: Odometry) -> ErrorFunction:
    """Keys ``(X_i, X_j, C_i)``: ``[R_i' (t_j - t_i) - (dx, dy), theta_j - theta_i - dtheta]`` at ``C_i``."""

    def error(this: Any, values: Any, H: Any) -> FloatArray:
        ki, kj, kc = this.keys()
        xi, xj, c = values.atPose2(ki), values.atPose2(kj), values.atVector(kc)
        p = np.array([xj.x() - xi.x(), xj.y() - xi.y()])
        q = _rot(xi.theta()).T @ p
        d = odo.delta(float(c[0]), float(c[1]))
        e = np.array([q[0] - d[0], q[1] - d[1], wrap_angle(xj.theta() - xi.theta() - d[2])])
        if H is not None:
            H[0] = np.array([[-1.0, 0.0, q[1]], [0.0, -1.0, -q[0]], [0.0, 0.0, -1.0]])
            Hj = np.eye(3)
            Hj[:2, :2] = _rot(xj.theta() - xi.theta())
            H[1] = Hj
            H[2] = -odo.J
        return e

    return error


def position_error(z: FloatArray) -> ErrorFunction:
    """Key ``X``: its position minus the fix (east, north)."""

    def error(this: Any, values: Any, H: Any) -> FloatArray:
        x = values.atPose2(this.keys()[0])
        if H is not None:
            Hx = np.zeros((2, 3))
            Hx[:, :2] = _rot(x.theta())
            H[0] = Hx
        return np.array([x.x() - z[0], x.y() - z[1]])

    return error


def azimuth_error(phi: float) -> ErrorFunction:
    """Key ``X``: its theta minus the measured azimuth's (``pi/2 - phi``)."""

    def error(this: Any, values: Any, H: Any) -> FloatArray:
        x = values.atPose2(this.keys()[0])
        if H is not None:
            H[0] = np.array([[0.0, 0.0, 1.0]])
        return np.array([wrap_angle(x.theta() - (0.5 * math.pi - phi))])

    return error


def heading_error(phi: float) -> ErrorFunction:
    """Keys ``(X, O)``: its theta minus the azimuth a heading ``phi`` measures, the offset ``o`` taken off (a
    heading measures the azimuth plus the offset: ``pi/2 - theta + o``)."""

    def error(this: Any, values: Any, H: Any) -> FloatArray:
        kx, ko = this.keys()
        x, o = values.atPose2(kx), float(values.atVector(ko)[0])
        if H is not None:
            H[0] = np.array([[0.0, 0.0, 1.0]])
            H[1] = np.array([[-1.0]])
        return np.array([wrap_angle(x.theta() - (0.5 * math.pi - phi) - o)])

    return error


def offset_step_error(decay: float) -> ErrorFunction:
    """Keys ``(O_i, O_j)``: ``o_j - decay o_i``, the heading offset's first-order Gauss-Markov step."""

    def error(this: Any, values: Any, H: Any) -> FloatArray:
        ki, kj = this.keys()
        oi, oj = float(values.atVector(ki)[0]), float(values.atVector(kj)[0])
        if H is not None:
            H[0] = np.array([[-decay]])
            H[1] = np.array([[1.0]])
        return np.array([oj - decay * oi])

    return error


def speed_error(sog: float, can_speed: float) -> ErrorFunction:
    """Key ``C``: ``k sog - CAN speed`` (the CAN speed at the fix's time, its speed over ground ``sog``)."""

    def error(this: Any, values: Any, H: Any) -> FloatArray:
        c = values.atVector(this.keys()[0])
        if H is not None:
            H[0] = np.array([[0.0, sog]])
        return np.array([float(c[1]) * sog - can_speed])

    return error


def bias_error(yaw_rate: float) -> ErrorFunction:
    """Key ``C``: its bias minus the CAN yaw rate at a standstill (the EKF's pseudo-measurement ``omega = 0``)."""

    def error(this: Any, values: Any, H: Any) -> FloatArray:
        c = values.atVector(this.keys()[0])
        if H is not None:
            H[0] = np.array([[1.0, 0.0]])
        return np.array([float(c[0]) - yaw_rate])

    return error


def gaussian(cov: FloatArray) -> Any:
    return gtsam.noiseModel.Gaussian.Covariance(cov + MIN_VARIANCE * np.eye(len(cov)))


# ---- the estimator -----------------------------------------------------------------------------------------------


@dataclass(slots=True)
class Node:
    """The newest node: index, time (s), its estimate (east, north, theta; b, k; the heading's offset o, rad) and,
    once asked for, the joint marginal covariance of its pose, calibration and offset (east, north, theta in the
    world frame; b, k; o)."""

    index: int
    t: float
    pose: FloatArray
    calib: FloatArray
    offset: float
    cov: FloatArray | None = None


@dataclass(slots=True)
class Opened:
    """The node of the epoch being processed: its time, odometry from the newest node (computed when first
    needed), the factors committed to it and the widening a re-acquisition asked for (world frame)."""

    t: float
    odo: Odometry | None = None
    factors: list[tuple[ErrorFunction, FloatArray, str]] = field(default_factory=list)
    widen: FloatArray = field(default_factory=lambda: np.zeros((6, 6)))
    priors: tuple[FloatArray, FloatArray] | None = None


def joint_marginal(smoother: Any, node: Node) -> FloatArray:
    """The joint marginal covariance of ``node``'s pose (east, north, theta in the world frame), calibration (b, k)
    and heading offset (o) in iSAM2's Bayes tree.

    Joint, not the two marginals apart: the fixes see the calibration only through the poses, so after a fix the
    pose's error and the calibration's are correlated (a heading pulled by the bias, a position along the track
    pulled by the speed scale), and the prediction from the node carries both through the odometry's Jacobian
    ``J_c``; the two marginals apart dropped the cross term ``2 J_x Sigma_xc J_c'``."""
    keys = [gtsam.symbol(name, node.index) for name in "xco"]
    full = np.asarray(smoother.getISAM2().jointMarginalCovariance(keys).fullMatrix())
    T = np.eye(6)
    T[:2, :2] = _rot(node.pose[2])  # the pose's body tangent -> world
    return T @ full @ T.T


class GtsamFls(LeverCourse):
    """GTSAM's iSAM2 fixed-lag smoother over the CAN odometry and GNSS (``gtsam-fls``; the module docstring)."""

    name = "gtsam-fls"
    azimuth_from_motion = "start"

    def __init__(self, settings: EstimationSettings | None = None, table: GtsamSettings | None = None) -> None:
        settings = settings or EstimationSettings()
        self.table = table or settings.estimator.gtsam_fls
        super().__init__(settings, self.table.noise)
        variance = heading_offset_variance(self.settings)
        self._offset_sigma = max(math.sqrt(variance), FIXED_SIGMA)
        """The heading offset's prior sigma (rad): the config's bound read as sigmas, as the Kalman filters'."""
        self._offset_estimated = variance > 0.0
        """Whether a heading measures the azimuth plus the offset (else the azimuth: ``estimator.azimuth_offset``
        off; the offset then stays at its prior, 0)."""

    @classmethod
    def from_config(cls, config: Config) -> GtsamFls:
        return cls(config.estimation)

    def stats(self) -> dict[str, float | int | str]:
        """The counters, the graph's size and the heading's offset estimated (``heading_offset_deg``, the heading
        less the azimuth)."""
        out = dict(super().stats())
        if self._smoother is not None:
            out["graph_values"] = int(self._smoother.getLinearizationPoint().size())
        out["heading_offset_deg"] = math.degrees(self._node.offset) if self._node is not None else 0.0
        return out

    # ---- the smoother ---------------------------------------------------------------------------------------

    def _reset_filter(self) -> None:
        self._smoother: Any = None
        self._node: Node | None = None
        self._opened: Opened | None = None
        self._steps: list[Step] = []
        self._now: Odometry | None = None
        self._fix_pos = np.zeros(2)  # the newest position fix used (east, north; m) and its sigmas
        self._fix_sigma = np.full(2, NO_GRAPH_SIGMA_M)
        self._calib0 = np.array([0.0, 1.0])
        self._calib_sigma0 = np.array([FIXED_SIGMA, FIXED_SIGMA])
        self._speed, self._yaw_rate, self._standstill = 0.0, 0.0, False
        self._speed_t = self._yaw_rate_t = -math.inf
        self._still: list[float] = []

    def _new_smoother(self) -> Any:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.table.relinearize_threshold)
        params.relinearizeSkip = self.table.relinearize_skip
        params.setFactorization("QR")  # the calibration's random walk over 0.1 s is stiff: QR, the safer one
        return gtsam.IncrementalFixedLagSmoother(self.table.lag_s, params)

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        lay = self.layout
        self._fix_pos = x0[[E, N]].copy()
        self._fix_sigma = np.sqrt(np.diag(P0)[[E, N]])
        self._calib0 = np.array([0.0, 1.0])
        self._calib_sigma0 = np.array(
            [math.sqrt(P0[r, r]) if r is not None else FIXED_SIGMA for r in (lay.b, lay.k)],
        )
        self._opened = Opened(self._t_state)
        if self._heading_known:
            self._open_graph(x0[PHI], math.sqrt(P0[PHI, PHI]))

    def _open_graph(self, phi: float, sigma_phi: float) -> None:
        """Start the graph at the opened node: priors on its position (the newest fix), azimuth and calibration."""
        assert self._opened is not None
        self._smoother = self._new_smoother()
        self._opened.priors = (
            np.array([*self._fix_pos, 0.5 * math.pi - phi]),
            np.array([*self._fix_sigma, sigma_phi]),
        )
        self._steps = after(self._steps, self._opened.t)

    def _flush(self) -> None:
        """Add the opened node and its factors to the smoother and take the new estimate."""
        node, opened = self._node, self._opened
        assert opened is not None and self._smoother is not None
        odo = self._node_odometry() if opened.priors is None else None
        self._opened = None
        i = 0 if node is None else node.index + 1
        X, C, Ho = (gtsam.symbol(name, i) for name in "xco")
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if opened.priors is not None:
            mean, sigma = opened.priors
            graph.add(gtsam.CustomFactor(gaussian(np.diag(sigma[:2] ** 2)), [X], position_error(mean[:2])))
            graph.add(
                gtsam.CustomFactor(gaussian(np.diag(sigma[2:] ** 2)), [X], azimuth_error(0.5 * math.pi - mean[2]))
            )
            graph.add(gtsam.PriorFactorVector(C, self._calib0, gtsam.noiseModel.Diagonal.Sigmas(self._calib_sigma0)))
            offset_sigma = np.array([self._offset_sigma])
            graph.add(gtsam.PriorFactorVector(Ho, np.zeros(1), gtsam.noiseModel.Diagonal.Sigmas(offset_sigma)))
            pose, calib, offset = mean, self._calib0, 0.0
        else:
            assert node is not None and odo is not None
            pose, _ = self._predict_node(node, odo)
            calib, offset = node.calib, node.offset
            cov = odo.cov[:3, :3].copy()
            R = np.eye(3)
            R[:2, :2] = _rot(node.pose[2])
            cov += R.T @ opened.widen[:3, :3] @ R  # a re-acquisition's widening, in the node's frame
            Xp, Cp = gtsam.symbol("x", node.index), gtsam.symbol("c", node.index)
            graph.add(gtsam.CustomFactor(gaussian(cov), [Xp, X, Cp], odometry_error(odo)))
            rw = np.array([self.noise.bias_rw, self.noise.scale_rw]) ** 2 * max(odo.T, 1e-3)
            rw = np.where(self._calib_sigma0 <= FIXED_SIGMA, FIXED_SIGMA**2, rw) + np.diag(opened.widen)[3:5]
            graph.add(gtsam.BetweenFactorVector(Cp, C, np.zeros(2), gtsam.noiseModel.Diagonal.Variances(rw)))
            decay, var = self._offset_step(odo.T)
            step = offset_step_error(decay)
            graph.add(gtsam.CustomFactor(gaussian(np.array([[var]])), [gtsam.symbol("o", node.index), Ho], step))
        if self._still and self.layout.b is not None and self.noise.standstill_rps > 0.0:
            var = (self.noise.can_yaw_rate_rps**2 + self.noise.standstill_rps**2) / len(self._still)
            still = bias_error(float(np.mean(self._still)))
            graph.add(gtsam.CustomFactor(gaussian(np.array([[var]])), [C if node is None else Cp], still))
        self._still = []
        keys = {"x": [X], "c": [C], "xo": [X, Ho]}
        for error, cov, key in opened.factors:
            graph.add(gtsam.CustomFactor(gaussian(cov), keys[key], error))
        values.insert(X, gtsam.Pose2(*pose))
        values.insert(C, np.asarray(calib, dtype=float))
        values.insert(Ho, np.array([offset]))
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        for key in (X, C, Ho):
            stamps.insert((key, opened.t))
        try:
            self._smoother.update(graph, values, stamps)
            est = self._smoother.calculateEstimatePose2(X)
            calib = self._smoother.calculateEstimateVector(C)
            offset = float(self._smoother.calculateEstimateVector(Ho)[0])
        except RuntimeError as e:  # GTSAM's indeterminant system and the like
            raise np.linalg.LinAlgError(f"GTSAM: {e}") from e
        pose = np.array([est.x(), est.y(), est.theta()])
        self._node = Node(i, opened.t, pose, np.asarray(calib, dtype=float), offset)
        self._steps = after(self._steps, opened.t)
        self._now = integrate(self._steps, *self._node.calib, self.noise)

    def _node_odometry(self) -> Odometry:
        """The odometry from the newest node to the opened node (computed once per node)."""
        assert self._opened is not None and self._node is not None
        if self._opened.odo is None:
            self._opened.odo = integrate(self._steps, *self._node.calib, self.noise, until=self._opened.t)
        return self._opened.odo

    def _offset_step(self, T: float) -> tuple[float, float]:
        """The heading offset's first-order Gauss-Markov step over ``T`` s (:data:`OFFSET_CORRELATION_S`, about 0,
        its prior's variance at rest, as the Kalman filters'): its decay and the variance it adds."""
        return offset_step(T, self._offset_sigma**2)

    def _predict_node(self, node: Node, odo: Odometry) -> tuple[FloatArray, FloatArray]:
        """The pose (east, north, theta) at the end of ``odo`` from ``node``, and the covariance of
        (east, north, theta, b, k, o) there: the node's joint marginal (:func:`joint_marginal`) carried by the
        odometry, ``J Sigma J' + odo`` with ``J = [d pose / d node pose, d pose / d calibration, 0; 0, I, 0; 0, 0,
        decay]`` (the offset's Gauss-Markov step, :meth:`_offset_step`)."""
        if node.cov is None:
            node.cov = joint_marginal(self._smoother, node)
        R = _rot(node.pose[2])
        d = np.array([odo.dx, odo.dy])
        pose = np.array([*(node.pose[:2] + R @ d), node.pose[2] + odo.dth])
        decay, var = self._offset_step(odo.T)
        J = np.eye(6)
        J[:2, 2] = _rot(node.pose[2] + 0.5 * math.pi) @ d  # d(R d)/dtheta
        J[:3, 3:5] = np.vstack([R @ odo.J[:2], odo.J[2:]])
        J[5, 5] = decay
        Rb = np.eye(3)
        Rb[:2, :2] = R
        P = J @ node.cov @ J.T
        P[:3, :3] += Rb @ odo.cov[:3, :3] @ Rb.T
        P[5, 5] += var
        return pose, P

    # ---- the RecursiveEstimator's hooks ---------------------------------------------------------------------

    def on_epoch(self, epoch: Epoch) -> StateEstimate:
        """The epoch's node (after the start); its estimate is the node's, at the epoch's time."""
        if not epoch.start and self._smoother is None:  # no azimuth yet: only the steps after the epoch matter
            self._opened = Opened(epoch.t)
            self._steps = after(self._steps, epoch.t)
        elif not epoch.start and self._opened is None and epoch.t > self._node_time():
            self._opened = Opened(epoch.t)
        estimate = super().on_epoch(epoch)
        node = self._node
        if node is not None and node.t == epoch.t:
            estimate = dataclasses.replace(
                estimate,
                east_m=float(node.pose[0]),
                north_m=float(node.pose[1]),
                azimuth_rad=float((0.5 * math.pi - node.pose[2]) % (2.0 * math.pi)),
            )
        return estimate

    def _turning(self) -> tuple[float, float]:
        """The newest CAN yaw rate less the bias and CAN speed over the scale (its mean would add the opened node)."""
        b, k = self._node.calib if self._node is not None else self._calib0
        return (0.0 if self._standstill else self._yaw_rate - b), self._speed / k

    def _node_time(self) -> float:
        return self._node.t if self._node is not None else -math.inf

    def _predict(self, dt: float, inputs: Inputs) -> None:
        self._hold(inputs, self._t_state + dt)
        t0 = self._t_state
        speed_age = None if inputs.speed is not None else t0 - self._speed_t
        yaw_rate_age = None if inputs.yaw_rate is not None else t0 - self._yaw_rate_t
        step = Step(t0, dt, self._speed, self._yaw_rate, self._standstill, speed_age, yaw_rate_age)
        self._steps.append(step)
        if self._now is not None:
            self._now.add(step, dt, self.noise)

    def _can_update(self, inputs: Inputs) -> None:
        self._hold(inputs, self._t_state)
        if inputs.standstill and inputs.yaw_rate is not None:  # at a standstill the CAN yaw rate is the bias
            self._still.append(inputs.yaw_rate)

    def _hold(self, inputs: Inputs, t: float) -> None:
        """Keep the CAN values of ``inputs`` measured (at ``t``): a missing one stays as it was."""
        if inputs.speed is not None:
            self._speed, self._speed_t, self._standstill = inputs.speed, t, inputs.standstill
        if inputs.yaw_rate is not None:
            self._yaw_rate, self._yaw_rate_t = inputs.yaw_rate, t

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        opened = self._opened
        assert opened is not None
        if self._smoother is None:  # no azimuth yet: the newest fix is the estimate
            pose = np.array([*self._fix_pos, 0.0])
            P = np.diag([NO_GRAPH_SIGMA_M**2] * 2 + [math.pi**2, 1.0, 1.0, self._offset_sigma**2])
        elif self._node is None:
            assert opened.priors is not None
            pose, sigma = opened.priors
            P = np.diag([*sigma**2, *self._calib_sigma0**2, self._offset_sigma**2])
        else:
            pose, P = self._predict_node(self._node, self._node_odometry())
        P = P + opened.widen
        calib = self._node.calib if self._node is not None else self._calib0
        offset = self._node.offset if self._node is not None else 0.0
        if kind == POSITION:
            nu, S, H = z - pose[:2], P[:2, :2] + R, None
            factor: tuple[ErrorFunction, FloatArray, str] | None = (position_error(z.copy()), R, "x")
        elif kind == AZIMUTH and self._heading and self._offset_estimated:  # the azimuth plus the offset
            nu = np.array([wrap_angle(z[0] - (0.5 * math.pi - pose[2]) - offset)])
            h = np.array([-1.0, 1.0])
            S, factor = h @ P[np.ix_([2, 5], [2, 5])] @ h + R, (heading_error(float(z[0])), R, "xo")
        elif kind == AZIMUTH:
            nu = np.array([wrap_angle(z[0] - (0.5 * math.pi - pose[2]))])
            S, factor = P[2:3, 2:3] + R, (azimuth_error(float(z[0])), R, "x")
        else:
            R = R * self.table.sog_scale**2  # the speed over ground's sigma, scaled as the search tuned it
            measured = self.frontend.can["speed"].interpolate(opened.t, self.settings.can.max_gap_s)
            # no CAN on both sides of the fix (ahead of the CAN data, or a gap): no factor below
            can = float(z[0]) * float(calib[1]) if measured is None else measured
            H = np.array([[0.0, 0.0, 0.0, 0.0, -can / calib[1] ** 2, 0.0]])
            nu = np.array([z[0] - can / calib[1]])
            # one CAN sample: its noise and its resolution (uniform rounding error)
            var_can = self.noise.can_speed_mps**2 + self.settings.can.speed_quantum_mps**2 / 12.0
            S = H @ P @ H.T + R + var_can / calib[1] ** 2
            factor = (speed_error(float(z[0]), can), np.asarray(R * calib[1] ** 2 + var_can), "c")
            if measured is None:
                factor = None

        def commit() -> None:
            if kind == POSITION:
                self._fix_pos, self._fix_sigma = z.copy(), np.sqrt(np.diag(R))
            if self._smoother is None:
                return
            if factor is not None:
                opened.factors.append(factor)

        return Pending(nu, np.atleast_2d(S), commit)

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        assert self._opened is not None
        rows = {POSITION: [0, 1], AZIMUTH: [2], GPS_SPEED: [4]}[kind]
        extra = np.outer(nu, nu) + R
        if kind == GPS_SPEED:
            calib = self._node.calib if self._node is not None else self._calib0
            extra = extra * calib[1] ** 4 / max(self._speed, 1.0) ** 2  # in k: d(can / k)/dk
        self._opened.widen[np.ix_(rows, rows)] += extra

    def _init_heading(self, phi: float, sigma: float) -> None:
        if self._smoother is None and self._opened is not None:
            self._open_graph(phi, sigma)

    def _covariance(self) -> FloatArray:
        """The newest node's marginal covariance (iSAM2's) carried by the odometry since to the state's time (the
        heading's offset estimated beside the pose: its uncertainty is in the pose's); the newest fix's sigmas before
        the graph opens; speed and yaw rate the CAN sensors' noise."""
        P = np.diag(np.square([self.noise.can_speed_mps, self.noise.can_yaw_rate_rps]))
        out = np.eye(self.layout.n)
        out[np.ix_([V, OMEGA], [V, OMEGA])] = P
        node = self._node
        if node is None or self._now is None or self._smoother is None:
            out[[E, N], [E, N]] = np.square(self._fix_sigma)
            out[PHI, PHI] = math.pi**2
            return out
        _, pose_cov = self._predict_node(node, self._now)
        rows = [E, N, PHI]
        out[np.ix_(rows, rows)] = pose_cov[:3, :3]
        out[PHI, [E, N]] = out[[E, N], PHI] = -pose_cov[:2, 2]  # phi = pi/2 - theta
        return out

    def _mean(self) -> FloatArray:
        if self._opened is not None and self._smoother is not None and self._opened.t <= self._t_state:
            self._flush()
        x = np.zeros(self.layout.n)
        if self.layout.g is not None:
            x[self.layout.g] = 1.0
        node = self._node
        b, k = node.calib if node is not None else self._calib0
        x[V] = self._speed / k
        x[OMEGA] = 0.0 if self._standstill else self._yaw_rate - b
        if node is None or self._now is None:
            x[E], x[N] = self._fix_pos
            return x
        R = _rot(node.pose[2])
        x[[E, N]] = node.pose[:2] + R @ np.array([self._now.dx, self._now.dy])
        x[PHI] = wrap_angle(0.5 * math.pi - node.pose[2] - self._now.dth)
        if self.layout.b is not None:
            x[self.layout.b] = b
        if self.layout.k is not None:
            x[self.layout.k] = k
        return kin.wrap_state(x)
