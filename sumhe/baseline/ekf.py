"""Extended Kalman filter on the shared model: predict at CAN rate, update with CAN speed / yaw rate and GNSS.

The maths is in procedural functions (``kf_predict``, ``offset_update``, after filterpy's
``kalman_filter.py``), reused by the RTS smoother and the IMM cells; :class:`GaussianFilter` holds a mean and
covariance and implements the hooks every Gaussian filter shares (start, re-acquisition, heading set-up);
:class:`Ekf` adds the linearised prediction and updates. Stream handling, gating and re-acquisition are in
:mod:`sumhe.baseline.stream`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.heading_offset import FollowsHeadings, heading_offset_variance, offset_step
from sumhe.baseline.kinematics import AZIMUTH, OMEGA, PHI, FloatArray, V
from sumhe.baseline.stream import Inputs, Pending, RecursiveEstimator
from sumhe.config import Config
from sumhe.frontend.stream import FixMeasurement
from sumhe.settings import EstimationSettings, NoiseSettings


def kf_predict(P: FloatArray, F: FloatArray, Q: FloatArray) -> FloatArray:
    """The predicted covariance ``F P F' + Q`` (the mean is moved by the caller's nonlinear model)."""
    return F @ P @ F.T + Q  # P^- = F P F' + Q


def kalman_gain(P: FloatArray, H: FloatArray, R: FloatArray) -> FloatArray:
    """``K = P H' S^-1``, ``S = H P H' + R`` the innovation covariance."""
    PHt = P @ H.T
    return np.linalg.solve(H @ PHt + R, PHt.T).T


def joseph(P: FloatArray, K: FloatArray, H: FloatArray, R: FloatArray) -> FloatArray:
    """``(I - K H) P (I - K H)' + K R K'``: the covariance after an update with the gain ``K``, the optimal one's
    or any other (a considered parameter's row of ``K`` is zero)."""
    IKH = np.eye(len(P)) - K @ H
    P = IKH @ P @ IKH.T + K @ R @ K.T
    return 0.5 * (P + P.T)


def considered(A: FloatArray, corner: float) -> FloatArray:
    """A square matrix of the state grown by a parameter's row and column (a receiver heading's offset), zero but the
    corner."""
    n = len(A)
    out = np.zeros((n + 1, n + 1))
    out[:n, :n], out[n, n] = A, corner
    return out


def grown_jacobian(H: FloatArray, sensitivity: float) -> FloatArray:
    """A measurement's Jacobian ``H`` grown by the column of a parameter it sees ``sensitivity`` times."""
    return np.hstack([H, np.full((len(H), 1), sensitivity)])


def offset_predict(
    x: FloatArray, offset: float, Pt: FloatArray, dt: float, noise: NoiseSettings, layout: kin.Layout, variance: float
) -> tuple[FloatArray, float, FloatArray]:
    """The time update over ``dt`` seconds of a state ``x`` and a receiver heading's ``offset`` (rad) of
    covariance ``Pt`` (:func:`considered`): the offset a first-order Gauss-Markov process about 0 of stationary
    ``variance`` (rad^2) and correlation time :data:`~.heading_offset.OFFSET_CORRELATION_S`."""
    x, F, Q = ekf_step(x, dt, noise, layout)
    keep, walk = offset_step(dt, variance)
    return x, offset * keep, kf_predict(Pt, considered(F, keep), considered(Q, walk))


def sees_offset(kind: str, heading: bool) -> float:
    """How many times a GNSS measurement of ``kind`` sees a receiver heading's offset: a ``heading`` measures the
    azimuth plus the offset, a course over ground (the velocity's azimuth) and a position none of it."""
    return 1.0 if kind == AZIMUTH and heading else 0.0


def offset_innovation(
    x: FloatArray, offset: float, Pt: FloatArray, kind: str, z: FloatArray, R: FloatArray, lag: float, heading: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Innovation, its covariance and the Jacobian (:func:`grown_jacobian`) of a GNSS measurement of ``kind`` at
    the state ``x`` and a receiver heading's ``offset`` of covariance ``Pt`` (:func:`sees_offset`)."""
    seen = sees_offset(kind, heading)
    H = grown_jacobian(kin.fix_jacobian(x, kind, lag), seen)
    nu = kin.residual(kind, z, kin.fix_model(x, kind, lag) + seen * offset)
    return nu, H @ Pt @ H.T + R, H


def offset_update(
    x: FloatArray, offset: float, Pt: FloatArray, nu: FloatArray, H: FloatArray, R: FloatArray
) -> tuple[FloatArray, float, FloatArray]:
    """One Kalman update of the state ``x`` (wrapped) and the offset, of covariance ``Pt``, with innovation ``nu``
    (``H``: :func:`grown_jacobian`), Joseph form."""
    K = kalman_gain(Pt, H, R)
    dx = K @ nu
    return kin.wrap_state(x + dx[:-1]), offset + float(dx[-1]), joseph(Pt, K, H, R)


def azimuth_from_heading(x: FloatArray, offset: float, Pt: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``x`` and ``Pt`` with the azimuth just set, uncorrelated, from a heading: the heading less the offset, whose
    error it takes."""
    x, Pt, v = x.copy(), Pt.copy(), Pt[-1, -1]
    x[PHI] = kin.wrap_angle(x[PHI] - offset)
    Pt[PHI, PHI] += v
    Pt[PHI, -1] = Pt[-1, PHI] = -v
    return x, Pt


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
    x, F, Q = ekf_step(x, dt, noise, layout)
    return x, kf_predict(P, F, Q)


def ekf_step(
    x: FloatArray, dt: float, noise: NoiseSettings, layout: kin.Layout
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The state ``dt`` seconds on, the step's Jacobian at ``x`` and its process noise."""
    return kin.wrap_state(kin.step(x, dt)), kin.step_jacobian(x, dt), kin.process_noise(dt, noise, layout)


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


def can_measurement(
    x: FloatArray, inputs: Inputs, noise: NoiseSettings, layout: kin.Layout
) -> tuple[FloatArray, FloatArray, FloatArray] | None:
    """The innovation, Jacobian and noise covariance of the CAN rows of ``inputs`` at ``x`` (None: no rows)."""
    rows, z = can_rows(inputs)
    if not rows:
        return None
    H = kin.can_jacobian(x, rows, layout)
    R = np.diag(np.square(kin.can_sigmas(rows, noise)))
    return z - kin.can_model(x, rows, layout), H, R


def yaw_rate_input(
    x: FloatArray, P: FloatArray, inputs: Inputs, noise: NoiseSettings, layout: kin.Layout
) -> tuple[FloatArray, FloatArray]:
    """The state ``x`` and its covariance ``P`` (``P`` may be grown by further rows: a heading's offset) with the yaw
    rate taken from the CAN yaw rate of ``inputs`` as an input: ``omega = (yaw_rate - b) / g`` at the CAN states of
    ``x``, its prior forgotten; its covariance is the CAN states' carried through that map plus the sample's noise
    (``noise.can_yaw_rate_rps / g``). The bias and the gain are then learned where they turn the azimuth (against
    the GNSS courses and positions) and at stops (the standstill row, ``omega = 0``), never from the yaw rate alone.
    At a standstill the true rate is 0, and the map's derivative by the gain is taken there (0).

    Why not as a measurement of ``g omega + b``, as the CAN speed is of ``k v``: with the gain a state, that row
    is a product of two states, and its linearised update read the yaw rate's noise as the gain's evidence (the
    yaw-rate state holds the earlier samples' noise, so each new innovation tends to have the opposite sign: the
    gain shrank steadily, 1.00 -> 0.42 in 90 s of straight road, and the filter was 14.5 m off in the outages
    of a drive it had been 1.6 m off without the gain). The same happens with the noise of ``(yaw_rate - b)`` at
    rest, where the true rate is known to be 0 (taken there, the gain grew 1.0 -> 1.5 in 6 s of standing)."""
    assert inputs.yaw_rate is not None
    b = float(x[layout.b]) if layout.b is not None else 0.0
    g = float(x[layout.g]) if layout.g is not None else 1.0
    x = x.copy()
    x[OMEGA] = (inputs.yaw_rate - b) / g
    A = np.eye(len(P))
    A[OMEGA, OMEGA] = 0.0
    if layout.b is not None:
        A[OMEGA, layout.b] = -1.0 / g
    if layout.g is not None and not inputs.standstill:
        A[OMEGA, layout.g] = -x[OMEGA] / g
    P = A @ P @ A.T
    P[OMEGA, OMEGA] += (noise.can_yaw_rate_rps / g) ** 2
    return x, 0.5 * (P + P.T)


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


def lever_course_sigma(yaw_rate_rps: float, speed_mps: float, lever_m: float, min_speed_mps: float) -> float:
    """The error (rad, 1-sigma) of taking the course over ground of an antenna ``lever_m`` ahead of the reference
    point for the reference point's: in a turn the antenna's velocity has ``yaw rate x lever`` across the track,
    so its course turns by ``|omega| lever / v`` (the speed at least ``min_speed_mps``, below which the front-end
    takes no course)."""
    return abs(yaw_rate_rps) * lever_m / max(abs(speed_mps), min_speed_mps)


class LeverCourse(FollowsHeadings):
    """A recursive estimator whose model has no antenna offset and that weighs a GNSS course with the lever arm's
    error at its own mean yaw rate and speed (the Kalman family and the particle filter)."""

    def _fix_angle(self, fix: FixMeasurement) -> tuple[float, float] | None:
        """A course's sigma with the lever arm's error added (:func:`lever_course_sigma`, the lever the antenna's
        forward offset and its range, ``vehicle.antenna_forward_m`` and ``antenna_forward_range_m``, in quadrature):
        the filter models no antenna offset. Without it, a course bent by 4-7 deg in a turn failed the gate of a
        filter whose azimuth sigma said 0.1 deg, and the azimuth followed the CAN yaw rate, its gain error
        unchecked: azimuth errors of 3-30 deg rms over the realistic drives with GPS. The particle filter's
        (at the cloud's mean): a course bent in a turn pulled the particles' azimuth off by 10-16 deg with a spread
        of 0.1-0.2 deg at the starts of outages on the realistic drives; with it, seeds 0 and 1, mean / p95 errors
        in outages 18.9 / 64.8 and 11.1 / 43.9 m (before 23.5 / 104.6 and 19.6 / 68.8), with GPS 5.19 / 11.5 and
        4.40 / 9.5 m (before 5.67 / 12.0 and 5.15 / 11.9)."""
        angle = super()._fix_angle(fix)
        if angle is None or fix.heading:
            return angle
        vehicle = self.settings.vehicle
        lever = math.hypot(vehicle.antenna_forward_m, vehicle.antenna_forward_range_m)
        floor = self.settings.gnss.course_min_speed_mps
        return angle[0], math.hypot(angle[1], lever_course_sigma(*self._turning(), lever, floor))

    def _turning(self) -> tuple[float, float]:
        """The yaw rate (rad/s) and speed (m/s) a course's lever error is taken at: its mean's."""
        mean = self._mean()
        return float(mean[OMEGA]), float(mean[V])


class TimedSpeed(RecursiveEstimator):
    """A recursive estimator that weighs a fix's speed over ground with the error of its uncertain time (the Kalman
    family: ``ekf``, ``ukf``, ``rts`` and ``imm``)."""

    def _speed_sigma(self, fix: FixMeasurement) -> float:
        """The speed over ground's sigma with the error of its uncertain time
        (:meth:`~sumhe.frontend.stream.FrontEnd.timed_speed_sigma_mps`: the error of the GNSS time offset the
        front-end applies, the part of the learned offset its slew has not applied yet included; none where the
        offset is configured, a calibration). Until 30 Nov 2026 the clock learner's error alone: for the second or
        two the slew takes to apply each new fit, the speed over ground weighed as if its time were known.

        Without it, the speed scale state took the speed over ground of the first acceleration from standstill,
        0.25 s off the CAN speed, for a scale error of up to 13 % with a sigma of 0.3 %, and kept it for minutes
        (its random walk is slow): the speed 0.5 m/s off and the estimate metres behind at the first outages of
        the realistic drives (its scale's error 49 times its sigma, rms over the outages' starts; 18 with it)."""
        return self.frontend.timed_speed_sigma_mps(fix)


class YawRateBeforeStep(RecursiveEstimator):
    """A recursive estimator that takes each CAN yaw-rate sample once (``_t_yaw``: the time up to which the samples
    are taken), before the step through its time where the sample is there when the step is taken
    (:meth:`_untaken_yaw_rate`; the Kalman family: ``ekf``, ``ukf``, ``rts`` and ``imm``); a subclass supplies the
    time update (:meth:`_step`) and the update with CAN rows (:meth:`_update_can`)."""

    _t_yaw: float

    def _begin(self, fix: FixMeasurement) -> None:
        """Start at ``fix``: the yaw-rate samples before it are not taken."""
        super()._begin(fix)
        self._t_yaw = self._t_state

    def _predict(self, dt: float, inputs: Inputs) -> None:
        """The CAN yaw rate of the step's own interval first (:meth:`_untaken_yaw_rate` up to its end), and the
        standstill row where the tick that ends it says the car stands (a car at rest does not turn through the
        step), then the step."""
        self._update_can(Inputs(None, self._untaken_yaw_rate(self._t_state + dt), inputs.standstill))
        self._step(dt)

    def _can_update(self, inputs: Inputs) -> None:
        """The CAN speed row at a tick, and the yaw-rate samples up to the state's time that came after the step to
        it (:meth:`_untaken_yaw_rate`; none unless the state was ahead of the CAN data)."""
        self._update_can(Inputs(inputs.speed, self._untaken_yaw_rate(self._t_state), False))

    def _update_can(self, inputs: Inputs) -> None:
        """The update with the CAN rows of ``inputs``."""
        raise NotImplementedError

    def _step(self, dt: float) -> None:
        """The time update over ``dt`` seconds."""
        raise NotImplementedError

    def _untaken_yaw_rate(self, t: float) -> float | None:
        """The mean CAN yaw rate (rad/s) of the samples up to ``t`` (s) not taken yet, which it takes (None: none).

        The model turns the azimuth through a step at the yaw rate of the step's start, constant over it
        (:func:`~.kinematics.step`); what it turns by is the mean yaw rate of that interval, which the CAN samples
        in it measure, so they update the yaw rate before the step. Weighed at the tick that ends the interval
        (after the step), as the mean since the previous tick, the yaw rate turned the azimuth through each step
        at the rate of the interval before it: one CAN speed period late (0.5 s on the shared real drive, whose
        OBD speed comes at 2 Hz, and on the realistic profile's OBD speed at 1-4 Hz; on the real drive the yaw-rate
        state trailed the gyro by 0.4 s, the lag of least rms difference, 0.3 s now, half a period, as the
        interval's mean should), and an azimuth that went on turning after each turn's end (0.8 deg at the start of
        the drive's outage at 1470 s, after a 21 deg turn, 55.8 m off at 60 s).

        A step to a fix whose time is ahead of the newest CAN data (a GNSS clock behind the CAN clock) finds the
        samples of its interval not there yet, and the ticks that come after it, older than the state, do not
        step: their samples are taken at those ticks, after the step (as before), not lost. Taking only the
        samples inside each step's interval, a state that lived at its fixes ahead of the CAN data took no yaw rate
        at all while it had GPS: on the realistic drives of seed 3 (10 Hz fixes 0.34 s ahead of the CAN data) the
        yaw-rate state stayed at 0 through 60 deg/s turns, and the azimuth followed the courses alone (off-road:
        heading error with GPS 7.3 -> 13.7 deg mean, up to 85 deg in turns). Against taking the yaw rate at the tick
        after the step: the real drive's 10 / 30 / 60 s outages 3.95 / 6.07 / 8.78 -> 3.84 / 4.98 / 6.38 m
        (``ekf``); the realistic drives' outages 7.06 -> 7.20 m, with GPS 3.97 -> 4.01 m, heading 1.70 -> 1.75 deg,
        worse on seed 2's drives, whose CAN yaw rate reads 8.5 % high (a gain the filter does not model): with that
        gain 1 their heading 1.86 -> 0.83 deg and outages 4.63 -> 4.31 m, with 0.915 8.92 -> 8.16 deg."""
        samples = self.frontend.can["yaw_rate"]
        mean = samples.mean(self._t_yaw, t)
        if mean is None:
            return None
        self._t_yaw = min(t, samples.newest)
        return mean[0]


class GaussianFilter(LeverCourse, TimedSpeed, YawRateBeforeStep):
    """A filter whose belief is a mean ``x`` and a covariance ``P`` (the layout of :mod:`.kinematics`); its noise
    is its own table's (:meth:`tuned`) unless given. It takes each CAN yaw-rate sample once, before the step
    through its time (:class:`YawRateBeforeStep`)."""

    x: FloatArray
    P: FloatArray
    snapshot_attrs = ("x", "P", "_t_yaw")

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


class OffsetFilter(GaussianFilter):
    """A Gaussian filter that estimates the offset of a receiver's heading where the fixes carry headings (the EKF, the
    RTS smoother's forward pass and the UKF, :class:`~sumhe.baseline.ukf.Ukf`; the IMM's cells alike,
    :class:`~sumhe.baseline.imm.Imm`).

    A heading (the receiver's body axis, HDT/THS, or a GNSS/IMU module's) is off the azimuth of the velocity the
    model moves along by the mounting's and the sideslip's offset (its prior sigma the config's bound read as sigmas,
    :func:`~.heading_offset.heading_offset_variance`; none where ``estimator.azimuth_offset`` is off). The filter
    carries it as one more state, ``offset_rad``, beside ``x``: its covariance with the state is ``Pt`` (``P`` is
    its top-left block), a heading measures the azimuth plus it, the position fixes tell it from the azimuth as the
    car moves, and it is a first-order Gauss-Markov process of correlation time
    :data:`~.heading_offset.OFFSET_CORRELATION_S` about 0. A course over ground is the velocity's azimuth: no
    offset, and where the fixes have no headings the offset is never seen (the realistic profile's: its estimates
    are those of the filter without it).

    Taken as a Schmidt consider parameter instead (the gains ``P``'s alone, the offset carried in ``Pt`` but never
    estimated), the filter followed the shared real drive's headings (the logger's GNSS/IMU heading at 1 Hz, whose
    offset from the course on the straights moved between -0.1 and -0.5 deg over the drive), its estimates 3-4 m
    left of the fixes on its straights, and took that into each outage: 3.84 / 4.98 / 6.38 m off the removed fixes
    in its 10 / 30 / 60 s outages, 2.88 / 3.71 / 4.75 m with the offset estimated (README, "Where it stands", with
    what a random constant offset and other correlation times gave)."""

    Pt: FloatArray
    offset_rad: float = 0.0
    snapshot_attrs = ("x", "P", "Pt", "offset_rad", "_t_yaw")

    def __init__(self, settings: EstimationSettings | None = None, noise: NoiseSettings | None = None) -> None:
        super().__init__(settings, noise)
        self._offset_var = heading_offset_variance(self.settings)

    def stats(self) -> Mapping[str, float | int | str]:
        """The counters and the heading's offset estimated (``heading_offset_deg``, the heading less the azimuth)."""
        return {**super().stats(), "heading_offset_deg": math.degrees(self.offset_rad)}

    def _reset_filter(self) -> None:
        super()._reset_filter()
        self.offset_rad, self.Pt = 0.0, considered(self.P, 0.0)

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        super()._start(x0, P0)
        self.offset_rad, self.Pt = 0.0, considered(P0, self._offset_var)
        if self._heading_known and self._heading:
            self._from_heading()
            self._marginal()

    def _from_heading(self) -> None:
        """The azimuth just set from a heading (:func:`azimuth_from_heading`)."""
        self.x, self.Pt = azimuth_from_heading(self.x, self.offset_rad, self.Pt)

    def _marginal(self) -> None:
        """``P``, the state's block of ``Pt``."""
        self.P = self.Pt[:-1, :-1].copy()

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        self.Pt = inflate(self.Pt, kind, nu, R)
        self._marginal()

    def _init_heading(self, phi: float, sigma: float) -> None:
        self.x, self.Pt = set_heading(self.x, self.Pt, phi, sigma)
        if self._heading:
            self._from_heading()
        self._marginal()

    def _take_yaw_rate(self, inputs: Inputs) -> Inputs:
        """The yaw rate of ``inputs`` taken as an input (:func:`yaw_rate_input`); the other CAN rows returned."""
        if inputs.yaw_rate is None:
            return inputs
        self.x, self.Pt = yaw_rate_input(self.x, self.Pt, inputs, self.noise, self.layout)
        self._marginal()
        return Inputs(inputs.speed, None, inputs.standstill)


class Ekf(OffsetFilter):
    """Extended Kalman filter (``ekf``): the shared model linearised at the estimate, the offset of a receiver's
    heading estimated (:class:`OffsetFilter`)."""

    name = "ekf"

    def _step(self, dt: float) -> None:
        self.x, self.offset_rad, self.Pt = offset_predict(
            self.x, self.offset_rad, self.Pt, dt, self.noise, self.layout, self._offset_var
        )
        self._marginal()

    def _update_can(self, inputs: Inputs) -> None:
        measured = can_measurement(self.x, self._take_yaw_rate(inputs), self.noise, self.layout)
        if measured is not None:
            nu, H, R = measured
            self._update(nu, grown_jacobian(H, 0.0), R)

    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        nu, S, H = offset_innovation(self.x, self.offset_rad, self.Pt, kind, z, R, lag, self._heading)
        return Pending(nu, S, lambda: self._update(nu, H, R))

    def _update(self, nu: FloatArray, H: FloatArray, R: FloatArray) -> None:
        """The update of the state and the offset (``H``: :func:`grown_jacobian`)."""
        self.x, self.offset_rad, self.Pt = offset_update(self.x, self.offset_rad, self.Pt, nu, H, R)
        self._marginal()
