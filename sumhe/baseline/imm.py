"""Interacting multiple models (``imm``): two EKF cells on the shared state, a straight and a curved model.

Paper 003's IMM switches between a non-manoeuvring ("straight") and a manoeuvring ("curved") kinematic model of
the vehicle. Both of 003's models carry the vehicle's orientation and its rate (``theta``, ``theta'``, the rate a
random walk of ``theta''``): the orientation turns by the yaw rate in both, and they differ in the angle of the
velocity to the vehicle, to first order in the straight model (so that "both straight and mild trajectories fulfill
the kinematical definition of the model") and to second order in the curved one. The shared state has no such
angle (its azimuth is the velocity's), so both cells are the shared su5 step, the azimuth turning with the yaw rate
(``phi' = -omega``, ``omega`` the CAN yaw rate less its bias, over its gain), and they differ in how fast the
turning may change: the yaw rate's random walk ``yaw_rate_rw`` of the straight model's noise (the EKF's) and the
curved model's, 4x louder (both scale with the step, so which model predicts a steady yaw rate better does not
depend on the CAN rate).

The CAN yaw rate is what tells them apart: where the yaw rate changes fast (into and out of a turn) the straight
cell's prediction of it (the previous sample's rate, held through the step) leaves its predicted spread, its
likelihood (003 eq. 20, ``exp(-d^2/2) / sqrt((2 pi)^M |S|)`` with ``d^2 = nu' S^-1 nu``, eq. 19) collapses and the
curved model takes over; at a steady yaw rate, straight or a gentle bend, the straight cell predicts the CAN data
more tightly and is kept. Before, the straight cell held its azimuth and drew its yaw rate about zero at every step
(white, sigma 0.01 rad/s): a minute-long gentle bend (26 deg at 0.0075 rad/s) stayed within that sigma, the straight
cell kept the probability (``p_turn`` 0.03-0.07) and an azimuth 10-26 deg off with a sigma of 0.3-0.5 deg, half the
fixes after it failed the gate and the outages starting there ended hundreds of metres off: on the shared real drive
without the receiver's heading 9.0 / 23.6 / 49.6 m mean in its 10 / 30 / 60 s outages (the EKF 3.2 / 4.6 / 5.9 m),
with ``eph`` 8-14 times the median error; a cell whose yaw rate is about zero explains a bend's steady CAN yaw rate
as the CAN's bias, too.

Model probabilities follow Bayes' rule (eq. 21) after the interaction (mixing) of the cells; the switching is a
two-state Markov chain, ``Pi[i, j] = P(model j after dt | model i before)``, with mean sojourn times whose 1 s
transition matrix is paper 002's, trained on real driving data (its Sigma = [[0.9168, 0.0832], [0.2328,
0.7672]] per 1 s GPS epoch: 11.5 s straight, 3.8 s manoeuvring). Measurement noise, gate and priors come from the
straight model's :class:`~sumhe.settings.NoiseSettings`; the output is the probability-weighted mean. Each cell
estimates the offset of a receiver's heading as the EKF does (:class:`Imm`). Its error estimate is the mixture's
covariance.

Like the EKF, it takes each CAN yaw-rate sample before the step through its time
(:class:`~sumhe.baseline.ekf.YawRateBeforeStep`). Taken at the CAN speed tick after the step, the azimuth turned
through each step at the rate of the interval before it, one CAN speed period late (0.5 s on the shared real drive),
on past each turn's end: that drive's 60 s outage after a 21 deg turn (at 1470 s) ended 56.0 m off, 13.7 m now, and
its 10 / 30 / 60 s outages 4.06 / 6.31 / 9.05 -> 3.84 / 4.96 / 6.37 m mean (the EKF's figures); on the realistic
profile, whose seed-2 drives' CAN yaw rate reads 8.5 % high (a gain the filter does not model), the outages 6.87 ->
7.01 m, with GPS 3.69 -> 3.74 m, as the EKF's moved with the same change.

Its cells weigh the GNSS data as the other Kalman filters do: a course with the lever arm's error at the mixture's
yaw rate and speed (:class:`~sumhe.baseline.ekf.LeverCourse`: the model has no antenna offset) and a speed over
ground with the error of its uncertain time (:class:`~sumhe.baseline.ekf.TimedSpeed`). Without them, on the
realistic drives, a course bent by 17 deg in a turn of 1.1 rad/s at 6.3 m/s failed the gate, re-acquired after
a second of such courses it snapped both cells' azimuth to them (16 deg off, held into the outage after it: 23 m
off after 5 s), and the speed scale took the first acceleration's speed over ground (13 % off at 8 s, 2.5 % at
30 s: 7-8 m behind with GPS on a highway, 13 m at the end of a 10 s outage).

The CAN yaw rate weighs the cells first (the likelihood of what each predicted), then each takes it as an input
(:func:`~sumhe.baseline.ekf.yaw_rate_input`: its yaw rate is the CAN's, less the bias, over the gain), so both turn
alike. While the CAN yaw rate was a measurement of each cell's yaw-rate state, the straight cell's lagged the curved
one's at a turn's start and end, and the mixture, its cells drawn together by the interaction at every step, dropped
``mu_straight x (curved turn - straight turn)`` of the turn at each step; the error estimate carried that dropped
turn as a considered error from one position fix to the next (on the shared real drive, when the straight cell had
held its azimuth, it reached 0.31-0.34 rad over a 60 s outage, 196 and 246 m across, where the fixes after found 188
and 421 m). With the yaw rate an input there is none left to carry (1e-13 m^2 after 20 s of a gentle curve with a
course a second).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import (
    LeverCourse,
    TimedSpeed,
    YawRateBeforeStep,
    azimuth_from_heading,
    can_measurement,
    considered,
    gaussian_loglik,
    grown_jacobian,
    inflate,
    offset_innovation,
    offset_predict,
    offset_update,
    set_heading,
    yaw_rate_input,
)
from sumhe.baseline.heading_offset import heading_offset_variance
from sumhe.baseline.kinematics import FloatArray
from sumhe.baseline.stream import Inputs, Pending
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
    """The IMM interaction step: the mixed initial state and covariance of each cell and the predicted
    probabilities."""
    c = mu @ Pi  # c_j = sum_i mu_i Pi_ij
    W = mu[:, None] * Pi / c[None, :]  # mixing weights mu_i|j
    out_x: list[FloatArray] = []
    out_P: list[FloatArray] = []
    for j, ref in enumerate(xs):
        D = [kin.state_difference(x, ref) for x in xs]
        dbar = sum(W[i, j] * D[i] for i in range(len(xs)))
        out_x.append(kin.wrap_state(ref + dbar))
        out_P.append(sum(W[i, j] * (Ps[i] + np.outer(D[i] - dbar, D[i] - dbar)) for i in range(len(xs))))
    return out_x, out_P, c


class Imm(LeverCourse, TimedSpeed, YawRateBeforeStep):
    """IMM of a straight and a curved EKF cell (``imm``).

    Each cell estimates the offset of a receiver's heading as the EKF does (:class:`~sumhe.baseline.ekf.Ekf`):
    ``offsets[j]`` beside its state ``xs[j]``, their covariance ``Pts[j]``, a heading measuring the azimuth plus it;
    the interaction mixes the offsets with the states. Taken as a Schmidt consider parameter instead (the gains
    without it), the cells followed the headings of the shared real drive as the EKF did, 3.84 / 4.96 / 6.37 m off
    the removed fixes of its 10 / 30 / 60 s outages (README, "Where it stands")."""

    name = "imm"
    snapshot_attrs = ("xs", "offsets", "Pts", "mu", "_t_yaw")

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
        self._offset_var = heading_offset_variance(self.settings)

    @classmethod
    def from_config(cls, config: Config) -> Imm:
        return cls(config.estimation)

    def stats(self) -> Mapping[str, float | int | str]:
        return {
            **super().stats(),
            "p_turn": float(self.mu[1]),
            "heading_offset_deg": math.degrees(self.offset_rad),  # as the EKF's (OffsetFilter.stats)
        }

    def _reset_filter(self) -> None:
        self.xs = [np.zeros(self.layout.n) for _ in self.models]
        self.offsets = [0.0 for _ in self.models]
        self.Pts = [considered(np.eye(self.layout.n), 0.0) for _ in self.models]
        self.mu = np.array(self.sojourn_s) / sum(self.sojourn_s)

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        self.xs = [x0.copy() for _ in self.models]
        self.offsets = [0.0 for _ in self.models]
        self.Pts = [considered(P0, self._offset_var) for _ in self.models]
        if self._heading_known and self._heading:
            self._from_heading()

    def _from_heading(self) -> None:
        """Each cell's azimuth just set from a heading (:func:`~sumhe.baseline.ekf.azimuth_from_heading`)."""
        cells = [azimuth_from_heading(*cell) for cell in zip(self.xs, self.offsets, self.Pts, strict=True)]
        self.xs, self.Pts = [x for x, _ in cells], [Pt for _, Pt in cells]

    def _weigh(self, loglik: list[float]) -> None:
        """Bayes' rule on the model probabilities with each cell's log-likelihood."""
        logp = np.log(self.mu) + np.array(loglik)
        p = np.exp(logp - logp.max())
        p = np.maximum(p / p.sum(), MU_MIN)
        self.mu = p / p.sum()

    def _step(self, dt: float) -> None:
        grown, self.Pts, self.mu = mix(
            [np.append(x, o) for x, o in zip(self.xs, self.offsets, strict=True)],
            self.Pts,
            self.mu,
            transition_matrix(dt, self.sojourn_s),
        )
        self.xs, self.offsets = [g[:-1] for g in grown], [float(g[-1]) for g in grown]
        for j, model in enumerate(self.models):
            self.xs[j], self.offsets[j], self.Pts[j] = offset_predict(
                self.xs[j], self.offsets[j], self.Pts[j], dt, model, self.layout, self._offset_var
            )

    def _update_can(self, inputs: Inputs) -> None:
        """Each cell's CAN rows: the yaw rate weighs the cells (the likelihood of what each predicted) and is then
        taken as an input (:func:`~sumhe.baseline.ekf.yaw_rate_input`); the speed and standstill rows update."""
        yaw_rate = Inputs(None, inputs.yaw_rate, False)
        others = Inputs(inputs.speed, None, inputs.standstill)
        loglik = []
        for j in range(len(self.models)):
            total = 0.0
            measured = can_measurement(self.xs[j], yaw_rate, self.noise, self.layout)
            if measured is not None:
                nu, H, R = measured
                H = grown_jacobian(H, 0.0)
                total += gaussian_loglik(nu, H @ self.Pts[j] @ H.T + R)
                self.xs[j], self.Pts[j] = yaw_rate_input(self.xs[j], self.Pts[j], inputs, self.noise, self.layout)
            measured = can_measurement(self.xs[j], others, self.noise, self.layout)
            if measured is not None:
                nu, H, R = measured
                total += self._cell_update(j, nu, grown_jacobian(H, 0.0), R)
            loglik.append(total)
        self._weigh(loglik)

    def _cell_update(self, j: int, nu: FloatArray, H: FloatArray, R: FloatArray) -> float:
        """Cell ``j``'s EKF update of its state and offset (``H``: :func:`~sumhe.baseline.ekf.grown_jacobian`);
        returns the update's log-likelihood."""
        loglik = gaussian_loglik(nu, H @ self.Pts[j] @ H.T + R)
        self.xs[j], self.offsets[j], self.Pts[j] = offset_update(self.xs[j], self.offsets[j], self.Pts[j], nu, H, R)
        return loglik

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        cells = [
            offset_innovation(x, o, Pt, kind, z, R, lag, self._heading)
            for x, o, Pt in zip(self.xs, self.offsets, self.Pts, strict=True)
        ]
        zhats = np.column_stack([kin.residual(kind, z, nu_j) for nu_j, _, _ in cells])  # z - nu: the cells' own
        zhat = kin.measurement_mean(kind, zhats, self.mu)
        dev = kin.residual(kind, zhats, zhat[:, None])
        S = sum(m * (S_j + np.outer(d, d)) for m, (_, S_j, _), d in zip(self.mu, cells, dev.T, strict=True))
        nu = kin.residual(kind, z, zhat)

        def commit() -> None:
            self._weigh([self._cell_update(j, nu_j, H_j, R) for j, (nu_j, _, H_j) in enumerate(cells)])

        return Pending(nu, np.asarray(S), commit)

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        self.Pts = [inflate(Pt, kind, nu, R) for Pt in self.Pts]

    def _init_heading(self, phi: float, sigma: float) -> None:
        cells = [set_heading(x, Pt, phi, sigma) for x, Pt in zip(self.xs, self.Pts, strict=True)]
        self.xs, self.Pts = [x for x, _ in cells], [Pt for _, Pt in cells]
        if self._heading:
            self._from_heading()

    def _mean(self) -> FloatArray:
        return kin.weighted_mean(np.column_stack(self.xs), self.mu)

    @property
    def offset_rad(self) -> float:
        """The receiver heading's offset (rad) the cells estimate, weighted."""
        return float(np.dot(self.mu, self.offsets))

    def _covariance(self) -> FloatArray:
        """The mixture's covariance: the cells' covariances (their states' blocks of ``Pts``) and the spread of their
        means, weighted."""
        mean = self._mean()
        spread = kin.weighted_covariance(np.column_stack(self.xs), self.mu, mean)
        cells = sum(m * Pt[:-1, :-1] for m, Pt in zip(self.mu, self.Pts, strict=True))
        return np.asarray(cells + spread)
