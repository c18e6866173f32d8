"""What the MHE says of its newest state's error: the SU bound box and a linearised covariance, carried from epoch to
epoch along the window's solution.

The bound box (``bound_east``/``bound_north``): half-widths, centred on the estimate, of an interval box that holds
the feasible set of the newest state (the states consistent with the SU model's bounded noise: every output within
its bound ``R``, every transition within its state bound ``Q``), carried as the arrival box is
(:mod:`.arrival`): at each epoch the previous newest state's box, widened by how far the new solution moved that
state, is moved one step on, ``alpha <- |dT/dx| alpha + 2 Q`` (twice: the box is centred on the estimate, not on the
set), and cut by what the new step's outputs bound directly, ``alpha <- min(alpha, m + |e|)`` (``m`` the half-width
the outputs bound, :func:`~sumhe.estimator.mhe.arrival.measured_bounds`; ``|e|`` the estimate's residual, since the
box is centred on the estimate). ``Q`` is the solve's own: the CAN data's bound over the step where it has one
(:mod:`.preintegration`), else the vehicle's limits. Through an outage the box grows with the CAN propagation's
bounded error and the azimuth's bound, as the set does; a fix cuts it back to (about) the fix's bound.

The error estimate (``eph`` ...): the covariance of the newest state under the same model linearised at the
solution (an extended Kalman filter's covariance recursion run along the MHE's own trajectory: for a linear model
with Gaussian noise, the covariance of the newest state of a full-information window). The noises are the window's
bounds read back as the sigmas they were made from: every output and CAN bound is ``estimator.r_cap_sigmas`` sigmas
of what the sensor claims (:mod:`.outputs`, :mod:`.preintegration`), so its sigma is the bound over
``r_cap_sigmas`` (the vehicle's limits, where they bound a step, become a ``r_cap_sigmas``-sigma event too). Why
not the bound box scaled: the box is a worst case, and grows linearly with the azimuth bound through an outage,
where the errors of a real drive grow as their sigmas do; a 95 % figure from it would be several times too wide.

Between epochs (the CAN-rate estimates) both are carried to the estimate's time by the model, as the epoch's step
is: with the state bounds the CAN data give over that part of a step (the vehicle's limits where they bound none),
the covariance then updated with the CAN speed and yaw rate measured at the estimate (their bounds read as sigmas).
Carried with the vehicle's limits for the speed and yaw rate and never updated (until 29 Nov 2026), a CAN-rate
estimate's own position variance was 8.9 times the epoch's before it at the median with GPS on the shared real drive
(129 times at the 90th percentile), 88 times in an outage's first 10 s: its ``eph`` jumped at every epoch, and the
growth scale (:class:`~sumhe.estimator.uncertainty.InnovationScale`), learned at a gap's end from that prediction,
was 0.026 / 0.26 / 0.37 (median, 10 / 30 / 60 s outages: 14-fold apart) where it is 0.26 / 0.60 / 0.43 now (one
scale nearly fits every length); the last CAN-rate estimate before an epoch now has 1.07 times that epoch's.
The CAN states (yaw-rate bias, speed scale, ...) drift in the
covariance as the arrival cost lets them: ``estimator.mhe.theta_drift`` of their half-ranges per square-root minute
is a bound like the others (the arrival cost adds its square to a covariance in units of the bounds, where a bound
is ``r_cap_sigmas`` sigmas), so its sigma is the drift over ``r_cap_sigmas`` (0.014 deg/s per square-root minute
for the yaw-rate bias by default; the realistic profile draws its sensors' drift densities from 0 to 0.05, RMS
0.029). Read as a sigma itself it was 16 times the arrival's variance, and the drift's ``t^5`` growth of the
position's variance (with the bias's ``t^4`` from the wider bias it kept at a fix) made the growth through an outage
rise faster with time than the errors: on the realistic drives ``eph`` was 2.8 times the median error 5-10 s into
an outage and 18 times at 45-60 s (4.9 times over all outages, 98.2 % of the errors within it); read as a bound,
2.7 and 8.5 times (3.4 times, 98.0 %; with the estimator's drift floor at the same reading,
:class:`~sumhe.estimator.mhe.estimator.MovingHorizonEstimator`), the growth scale learned from the gaps
(:class:`~sumhe.estimator.uncertainty.InnovationScale`) as before; with that scale measured by the innovation's
change over each gap, not by the prediction's innovation against the expected lag at the gap's start, 2.7 and 4.9
times (3.07 times, 97.9 %). What is left of the late excess is the change of the fixes' slow error over a gap
(metres after 10 s), which the innovation's change holds beside decimetres of the MHE's own growth and the truth of a
simulated drive does not: counted in the gaps' expectation (as the residuals' own change over the same time with
fixes) it took the realistic outages to 2.95 times, but the shared real drive's 30 s outages to 89.9 % of the
removed fixes within ``eph``, a reference that holds that change. Counted as a change of unknown size, between
nothing and the two fixes' slow errors independent (uniform in their correlation: the gaps' likelihood averaged over
it, :class:`~sumhe.estimator.uncertainty.InnovationScale`), 97.8 % at 2.91 times (0-5 s 2.42x, 5-15 s 2.38x, 15-30 s
3.01x, 30-60 s 3.09x, where on the same main they were 2.67, 2.53, 3.30 and 3.75x), the real drive's 90.1 / 90.3 /
91.9 %.

The growth's shape against the truth (issue 13, the realistic drives' 36 outages): at the outages' starts the newest
state's errors against its own sigmas, rms, were 0.85 against 0.33 deg (azimuth), 0.037 against 0.022 deg/s (yaw-rate
bias) and 0.0057 against 0.0013 (speed scale); at 15 m/s the position growth those rms errors make is 15, 12 and 16
times the median own growth of the 55 s outages at 5, 10 and 45 s (which rises as ``t^2.2`` from 10 to 45 s, the
bias's part of it 4 % at 10 s and 28 % at 45 s; the errors' as ``t^2.4``): one growth scale fits every outage length,
and the gaps' growth scale times its predictive factor is about that (median 16-19). Per time into an outage (main of
25 Nov 2026, 15a36b9, whose realistic positions differ by centimetres from those of 3df51f4, where the cells were
97.9 % at 2.97x with GPS and 97.9 % at 3.07x in outages, since the SQP's banded half solve, 6b8ae74: 30 s outages 4.16
-> 4.22 m mean; now 97.8 % at 3.05x with GPS), 98.0 % of the errors within ``eph`` at 3.16 times the median error: 0-5
s 95.7 % (2.82x), 5-15 s 96.5 % (2.60x), 15-30 s 99.5 % (3.36x), 30-60 s 99.6 % (3.82x). The late excess is the
learning of the scale, not the shape: the growth scale each drive's gaps find runs from 0.01 to 26 (under 0.6 on seed
2's three drives, 1.0-26 on the others), and it rests on few gaps, one per outage, so its predictive factor
(:attr:`~sumhe.estimator.uncertainty.InnovationScale.growth_spread`) is 6.3 at each drive's second outage and 1.5-2.4
after. Without that factor (measured, not landed: it is every estimator's) the realistic outages had 96.8 % within
``eph`` at 2.75x (97.7 % at 2.88x with GPS), but the shared real drive's 10 / 30 / 60 s outages 91.2 / 87.9 / 88.2 %
(2.70 / 2.51 / 2.43x), where it holds the band. Tried on the covariance, not landed (positions unchanged): the GNSS
speed's and course's errors taken as correlated (Gauss-Markov, 1 s: their variance times ``(1 + rho) / (1 - rho)``, 20
at 10 Hz) doubled the own growth at every length alike, 98.0 % at 3.23x (15-30 s 2.99x, 30-60 s 4.17x), the real
drive's 92.3 / 90.5 / 92.3 % (2.83 / 2.82 / 2.87x); every bound read as a uniform noise's sigma ``u / sqrt(3)``
(prior, state and output noise, drift, and the drift floor), 98.1 % at 3.41x, the real drive's 95.6 / 95.8 / 97.8 %
(3.28 / 3.10 / 3.03x).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from sumhe.estimator import linalg
from sumhe.estimator.mhe.arrival import StepJacobians, measured_bounds
from sumhe.estimator.mhe.window import Window
from sumhe.estimator.uncertainty import Spread
from sumhe.model.compiled import NumpyFunction
from sumhe.model.su import SuModel, state_noise

FloatArray = NDArray[np.float64]


Carry = Callable[[FloatArray, FloatArray, float, FloatArray, FloatArray, FloatArray], tuple[FloatArray, FloatArray]]
"""``(x_p, x_n, h, P, q_var, d_var) -> (A, P')``: see :func:`carry_function`."""


def _carry_expressions(
    model: SuModel, xp: ca.SX, xn: ca.SX, h: ca.SX, P: ca.SX, q_var: ca.SX, d_var: ca.SX
) -> tuple[ca.SX, ca.SX]:
    """The expressions of :func:`carry_function`: ``A`` and ``P'``."""
    m, md = model.n_states, model.n_dynamic
    w = ca.vertcat(*state_noise(model, xp, xn, h, ca))
    dwp, dwn = ca.jacobian(w, xp), ca.jacobian(w, xn)
    inv = ca.inv(dwn[:, :md])
    top = -inv @ ca.horzcat(dwp[:, :md], dwp[:, md:] + dwn[:, md:])
    A = ca.vertcat(top, ca.horzcat(ca.SX.zeros(m - md, md), ca.SX.eye(m - md)))
    G = ca.vertcat(inv, ca.SX.zeros(m - md, md))
    return A, A @ P @ A.T + G @ ca.diag(q_var) @ G.T + ca.diag(d_var)


def carry_function(model: SuModel) -> Carry:
    """One step's ``A = dx_n/dx_p`` (m x m: the CAN states carried unchanged) of the transition ``w = W(x_p, x_n)``
    (``h`` s) solved for ``x_n``, and a covariance ``P`` of ``x_p`` carried through it,
    ``P' = A P A' + G diag(q_var) G' + diag(d_var)`` (``G = dx_n/dw``, m x md: ``q_var`` the state noises'
    variances, ``d_var`` what each state drifts by): one compiled CasADi call (a few times faster than the numpy
    of its 5-10-element matrices)."""
    m, md = model.n_states, model.n_dynamic
    xp, xn, h = ca.SX.sym("xp", m), ca.SX.sym("xn", m), ca.SX.sym("h")
    P, q_var, d_var = ca.SX.sym("P", m, m), ca.SX.sym("q_var", md), ca.SX.sym("d_var", m)
    A, moved = _carry_expressions(model, xp, xn, h, P, q_var, d_var)
    f = NumpyFunction(
        ca.Function("carry", [xp, xn, h, P, q_var, d_var], [ca.vertcat(ca.vec(ca.densify(A)), ca.vec(moved))])
    )

    def carry(
        xp_: FloatArray, xn_: FloatArray, h_: float, P_: FloatArray, q_var_: FloatArray, d_var_: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        flat = f(xp_, xn_, h_, P_, q_var_, d_var_)
        return flat[: m * m].reshape(m, m).T, flat[m * m :].reshape(m, m).T

    return carry


def at_function(model: SuModel, scale: float) -> NumpyFunction:
    """What a CAN-rate estimate needs of :func:`carry_function`, from ``(x_p, x_n, h, P, q, drift, r)`` (``q`` the
    state bounds, ``drift`` the drift per s, ``r`` the bounds of the CAN speed and yaw rate measured at ``x_n``,
    ``inf`` for one not measured): ``|A|`` of the dynamic states (md x md, column-major), then of ``P'`` (the state
    noises' variances ``(scale q)^2``, the drift's ``drift h``) updated with the two CAN outputs at ``x_n`` (their
    variances ``(scale r)^2``; one after the other, as their errors are independent: the same as at once) the east,
    north and east-north entries and the speed's and azimuth's variances, then ``2 q`` of east and north. The same
    carry expressions as :func:`carry_function`'s and :func:`grow_box`'s terms; a tenth of its operations."""
    m, md = model.n_states, model.n_dynamic
    xp, xn, h = ca.SX.sym("xp", m), ca.SX.sym("xn", m), ca.SX.sym("h")
    P, q, drift, r = ca.SX.sym("P", m, m), ca.SX.sym("q", md), ca.SX.sym("drift", m), ca.SX.sym("r", 2)
    A, moved = _carry_expressions(model, xp, xn, h, P, (scale * q) ** 2, drift * h)  # ** 2: x * x, as np.square
    out_x = ca.vertcat(*model.output(xn, ca))
    for k, j in enumerate((model.j_can_speed, model.j_can_yaw_rate)):
        Ht = ca.jacobian(out_x[j], xn).T
        PHt = moved @ Ht
        moved = moved - PHt @ PHt.T / (Ht.T @ PHt + (scale * r[k]) ** 2)
    (e, n), v, phi = model.position, model.i_v, model.i_phi
    picked = [moved[e, e], moved[n, n], moved[e, n], moved[v, v], moved[phi, phi], 2 * q[e], 2 * q[n]]
    out = ca.vertcat(ca.vec(ca.densify(ca.fabs(A[:md, :md]))), *picked)
    return NumpyFunction(ca.Function("carry_at", [xp, xn, h, P, q, drift, r], [out]))


def grow_box(alpha: FloatArray, A: FloatArray, q: FloatArray) -> FloatArray:
    """The box ``alpha`` (dynamic states, ``inf`` unknown) moved by one step: ``|A| alpha + 2 q``; a state that
    depends on an unknown one is unknown."""
    md = len(alpha)
    F = np.abs(A[:md, :md])
    if np.isfinite(alpha).all():
        return F @ alpha + 2.0 * q
    unknown = ~np.isfinite(alpha)
    grown = F @ np.where(unknown, 0.0, alpha) + 2.0 * q
    return np.where((F[:, unknown] > 0).any(axis=1), np.inf, grown)


class NewestError:
    """The newest state's bound box and covariance (module docstring), carried along the MHE's solutions: the bounds
    read as ``sigmas_per_bound`` sigmas, the CAN states' drift ``drift_per_s`` (the square of their drift bound, per
    s) too."""

    def __init__(
        self, model: SuModel, step_jac: StepJacobians, sigmas_per_bound: float, drift_per_s: FloatArray
    ) -> None:
        self.model, self.step_jac = model, step_jac
        self.carry = carry_function(model)
        self.scale = 1.0 / sigmas_per_bound
        self.drift = np.zeros(model.n_states)
        self.drift[model.n_dynamic :] = np.square(self.scale) * drift_per_s
        self._at = at_function(model, self.scale)
        self._at.bind(5, self.drift)
        self.reset()

    def reset(self) -> None:
        self.limits = np.full(self.model.n_dynamic, np.inf)
        self.alpha: FloatArray | None = None
        self.P: FloatArray | None = None
        self.x: FloatArray | None = None

    def start(
        self, win: Window, half_widths: FloatArray, limits: FloatArray, out_factor: FloatArray, theta_range: FloatArray
    ) -> None:
        """At a start: the prior of ``half_widths`` around the window's one state (the covariance; the box: within
        ``limits`` of the estimate, dynamic states, ``inf`` none: the azimuth within pi, speed and yaw rate within
        the width of their ranges, always), cut by its outputs."""
        self.limits = limits
        self.alpha = limits.copy()
        self.P = np.diag(np.square(self.scale * half_widths))
        self.x = win.x[0].copy()
        self._measure(win, out_factor, theta_range)
        self._prepare()

    def epoch(self, win: Window, Q: FloatArray, out_factor: FloatArray, theta_range: FloatArray) -> None:
        """After a solve: carry box and covariance from the previous newest state (now ``win.x[-2]``) to the newest
        through the last transition (state bound ``Q[-1]``), then cut them by the newest step's outputs."""
        assert self.alpha is not None and self.P is not None and self.x is not None  # set at the start
        md = self.model.n_dynamic
        if len(win) < 2:
            self.x = win.x[-1].copy()
        else:
            xp, xn = win.x[-2], win.x[-1]
            moved = np.abs(xp[:md] - self.x[:md])
            q = Q[-1] if len(Q) else np.zeros(md)
            A, self.P = self._carried(xp, xn, float(win.t[-1] - win.t[-2]), q)
            self.alpha = np.minimum(grow_box(self.alpha + moved, A, q), self.limits)
            self.x = xn.copy()
        self._measure(win, out_factor, theta_range)
        self._prepare()

    def _measure(self, win: Window, out_factor: FloatArray, theta_range: FloatArray) -> None:
        """Cut the box by what the newest step's outputs bound, and update the covariance with them."""
        assert self.alpha is not None and self.P is not None
        model, k = self.model, len(win) - 1
        avail = win.avail[k]
        bound = win.allow[k] * out_factor
        _, _, _, e, de = self.step_jac(win.x[k], win.x[k], 0.0, win.y[k])
        direct = measured_bounds(model, win, k, theta_range, out_factor)
        for j, i in (*zip(model.j_position, model.position, strict=True), (model.j_azimuth, model.i_phi)):
            if avail[j]:
                direct[i] += abs(float(e[j]))
        self.alpha = np.minimum(self.alpha, direct)
        if avail.any():
            H = de[avail]
            R = np.diag(np.square(self.scale * bound[avail]))
            PHt = self.P @ H.T
            K = linalg.solve(H @ PHt + R, PHt.T).T
            IKH = np.eye(len(self.P)) - K @ H
            P = IKH @ self.P @ IKH.T + K @ R @ K.T
            self.P = 0.5 * (P + P.T)

    def _prepare(self) -> None:
        """What the CAN-rate estimates until the next epoch share (:meth:`at`): the newest state and its covariance
        set in the compiled carry once, whether its box is known (finite), and the answer at the newest state."""
        assert self.alpha is not None and self.P is not None and self.x is not None
        self._at.bind(0, self.x)
        self._at.bind(3, self.P)
        self._known = bool(np.isfinite(self.alpha).all())
        self._limits_en = tuple(self.limits[list(self.model.position)].tolist())
        self.here = half_widths(self.model, self.alpha), self.spread(self.P)

    def at(
        self, x: list[float], h: float, q: FloatArray, r: list[float]
    ) -> tuple[tuple[float | None, float | None], Spread]:
        """The position's box half-widths (east, north; m, None unknown) and the error figures carried ``h`` s on
        from the newest state to ``x`` (a CAN-rate estimate), with the state bound ``q`` over that part of a step,
        the covariance then updated with the CAN speed and yaw rate measured at ``x`` within the bounds ``r``
        (``inf`` for one not measured); the newest state's own for ``h <= 0``. One call of :func:`at_function`
        (the newest state and covariance set at the epoch, :meth:`_prepare`) and, for a known box, the one product
        of :func:`grow_box` it needs (the same bits as the full one)."""
        if h <= 0.0:
            return self.here
        f, md, (i_e, i_n) = self._at, self.model.n_dynamic, self.model.position
        f.bind(1, x)
        f.bind(2, h)
        f.bind(4, q)
        f.bind(6, r)
        out = f.run()
        F = out[: md * md].reshape(md, md).T
        var_e, var_n, cov_en, var_v, var_phi, q2_e, q2_n = out[md * md :].tolist()
        if self._known:
            grown = (F @ self.alpha).tolist()
            lim_e, lim_n = self._limits_en
            east, north = grown[i_e] + q2_e, grown[i_n] + q2_n
            # np.minimum's choice (a NaN kept), as grow_box's caller takes it
            box = (_known(lim_e if east > lim_e else east), _known(lim_n if north > lim_n else north))
        else:
            box = half_widths(self.model, np.minimum(grow_box(self.alpha, F, q), self.limits))
        # Spread.from_covariance of the five entries, on plain floats
        spread = Spread(var_e, var_n, cov_en, math.sqrt(max(var_v, 0.0)), math.sqrt(max(var_phi, 0.0)))
        return box, spread

    def _carried(self, xp: FloatArray, xn: FloatArray, h: float, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The transition's ``A`` from ``xp`` to ``xn`` (``h`` s) and the covariance carried through it: the state
        noise of the bounds ``q`` and the CAN states' drift."""
        assert self.P is not None
        return self.carry(xp, xn, h, self.P, np.square(self.scale * q), self.drift * h)

    def spread(self, P: FloatArray) -> Spread:
        """The error figures of a covariance of the model's states."""
        m = self.model
        return Spread.from_covariance(P, m.position[0], m.position[1], m.i_v, m.i_phi)


def half_widths(model: SuModel, alpha: FloatArray) -> tuple[float | None, float | None]:
    """The position's half-widths (east, north; m) of a box, None where unknown."""
    i_e, i_n = model.position
    return _known(float(alpha[i_e])), _known(float(alpha[i_n]))


def _known(half_width: float) -> float | None:
    """A half-width (m), None where unknown (not finite)."""
    return half_width if math.isfinite(half_width) else None
