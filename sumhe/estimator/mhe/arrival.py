"""What the MHE keeps of the steps leaving its window: the arrival box and the arrival cost (``docs/mhe.md``).

(1) The arrival box: when steps are dropped, the first state is held to a box around the previous solution's
estimate of it, of half-widths ``alpha`` carried as an interval bound: ``alpha <- min(alpha, m_k)`` with ``m_k``
what the dropped step's outputs bound directly (a position by its allowance, the azimuth by the course's, speed and
yaw rate by the CAN allowances and the CAN states' limits), then moved one step on, ``alpha <- |dT/dx| alpha +
2 Q_k`` (the set grows by one step of state noise, twice because the box is centred on the estimate, not on the
set). (2) The arrival cost ``(z_0 - p)' W (z_0 - p)`` of the least-squares objective: the dropped steps' terms
(their outputs, their state noise and the previous arrival cost), linearised at the solution, with the dropped
states eliminated (a Schur complement: what an information filter carries). It keeps the correlations a box cannot,
of the speed scale with the positions above all. Every CAN and installation state (the yaw-rate bias and gain, the
speed scale, the receiver's azimuth offset, the antenna's lever arm) may drift by ``estimator.mhe.theta_drift`` of
its range per square-root minute (``docs/mhe.md``, "Arrival cost": why the gain and the installation too).

:func:`arrival_update` is a pure function of the window, the old :class:`Arrival` and the bounds.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.estimator import linalg
from sumhe.estimator.mhe.window import Window
from sumhe.model.su import MIN_COURSE_SPEED_MPS, SuModel
from sumhe.records import quick_init

EPS = 1e-9
"""Regularisation of the arrival cost's eliminations (directions without information)."""
FloatArray = NDArray[np.float64]
StepJacobians = Callable[..., tuple[FloatArray, ...]]
"""``(xp, xn, h, y) -> (w, dw/dxp, dw/dxn, e(xp), de/dxp)``: :func:`~sumhe.estimator.mhe.problem.step_jacobians`."""


@quick_init
@dataclass(frozen=True, slots=True)
class Arrival:
    """The arrival box (half-widths ``alpha`` of the dynamic states, ``inf``: none; centre ``box_centre``, m states)
    and the arrival cost (centre ``prior``, weight ``weight``, m x m) on the window's first state."""

    alpha: FloatArray
    box_centre: FloatArray
    prior: FloatArray
    weight: FloatArray


def theta_drift_variance(theta_drift: float, theta_range: FloatArray, dt: float) -> FloatArray:
    """How far (variance) the CAN states drift in ``dt`` s: ``theta_drift`` of their half-ranges per square-root
    minute."""
    return np.square(theta_drift * theta_range) * dt / 60.0


def prior_arrival(x: FloatArray, half_widths: FloatArray, n_dynamic: int, kept: FloatArray | None = None) -> Arrival:
    """The arrival at a start: no box, a weak prior of ``half_widths`` around ``x`` (their inverse squares), plus
    ``kept``, what was known of the CAN and installation states before a restart (:func:`theta_information`)."""
    weight = np.diag(1.0 / np.square(half_widths))
    if kept is not None:
        weight[n_dynamic:, n_dynamic:] += kept
    return Arrival(np.full(n_dynamic, np.inf), x.copy(), x.copy(), weight)


def measured(arrival: Arrival, i: int, value: float, bound: float) -> Arrival:
    """The arrival cost told that its state ``i`` is ``value`` within ``bound`` (a measurement of a CAN state: the
    yaw-rate bias at a standstill, :mod:`.standstill`): ``W' = W + e e' / bound^2``, the centre that minimises both
    terms."""
    weight = arrival.weight.copy()
    weight[i, i] += 1.0 / bound**2
    pull = np.zeros(len(weight))
    pull[i] = (value - arrival.prior[i]) / bound**2
    prior = arrival.prior + np.linalg.solve(weight, pull)
    return Arrival(arrival.alpha, arrival.box_centre, prior, weight)


def theta_information(weight: FloatArray, n_dynamic: int, drift: FloatArray) -> FloatArray:
    """The information an arrival cost of ``weight`` holds on the CAN and installation states alone (the states after
    the first ``n_dynamic``: its Schur complement, the dynamic states eliminated), after they drifted by the
    variances ``drift`` since (:func:`drifted`)."""
    d, th = slice(0, n_dynamic), slice(n_dynamic, None)
    w_dd = weight[d, d] + EPS * np.eye(n_dynamic)
    info = weight[th, th] - weight[th, d] @ np.linalg.solve(w_dd, weight[d, th])
    return drifted(0.5 * (info + info.T), len(info), drift)


def measured_bounds(model: SuModel, win: Window, k: int, theta_range: FloatArray, out_factor: FloatArray) -> FloatArray:
    """What the outputs of step ``k`` bound directly: half-widths per dynamic state (inf if nothing); speed and
    yaw rate through the CAN states' whole range, the azimuth and the position through the installation states'
    (a box must not rely on their estimates). In plain floats (numpy's operations in the same order: the same
    bits), 9 -> 7 us a call."""
    md = model.n_dynamic
    out = [math.inf] * md
    avail, allow, x = win.avail[k].tolist(), (win.allow[k] * out_factor).tolist(), win.x[k].tolist()
    rng = [0.0] * md + theta_range.tolist()  # the CAN states' ranges by state index
    (j_e, j_n), (i_e, i_n) = model.j_position, model.position
    for j, i in ((j_e, i_e), (j_n, i_n), (model.j_azimuth, model.i_phi)):
        if avail[j]:
            out[i] = allow[j]
    i_v, i_k, i_b, i_w = model.i_v, model.i_scale, model.i_bias, model.i_omega
    if avail[model.j_can_speed]:
        k_range = rng[i_k] if i_k is not None else 0.0
        k_low = (x[i_k] - k_range) if i_k is not None else 1.0
        out[i_v] = (allow[model.j_can_speed] + abs(x[i_v]) * k_range) / max(k_low, 1e-3)
    j_sog = model.j_gps_speed
    if j_sog is not None and avail[j_sog]:
        out[i_v] = min(out[i_v], allow[j_sog])
    if avail[model.j_can_yaw_rate]:
        out[i_w] = allow[model.j_can_yaw_rate] + (2.0 * rng[i_b] if i_b is not None else 0.0)
        if model.i_gain is not None:
            g_range = rng[model.i_gain]
            out[i_w] = (out[i_w] + abs(x[i_w]) * g_range) / max(x[model.i_gain] - g_range, 1e-3)
    if model.i_azimuth_offset is not None and avail[model.j_azimuth]:
        out[model.i_phi] += 2.0 * rng[model.i_azimuth_offset]
    if model.i_lever is not None:
        # the antenna anywhere in its range: the position it measures, and the course of its motion in a turn
        lever = abs(x[model.i_lever]) + 2.0 * rng[model.i_lever]
        out[i_e] += lever
        out[i_n] += lever
        if avail[model.j_azimuth]:
            out[model.i_phi] += math.atan2(lever * abs(x[i_w]), max(abs(x[i_v]), MIN_COURSE_SPEED_MPS))
    return np.array(out)


def arrival_update(
    model: SuModel,
    win: Window,
    drop: int,
    old: Arrival,
    Q: FloatArray,
    q_caps: FloatArray,
    step_jac: StepJacobians,
    theta_range: FloatArray,
    theta_drift: float,
    out_factor: FloatArray,
) -> Arrival:
    """The arrival after the ``drop`` oldest steps of ``win`` leave it (module docstring), linearised at the
    window's trajectory; ``Q`` the state bounds of the last solve (``q_caps`` for steps beyond them), the output
    bounds the steps' allowances times ``out_factor`` (:mod:`.envelope`)."""
    md, nt = model.n_dynamic, model.n_states - model.n_dynamic
    nx = (drop + 1) * md
    # the quadratic d' H d + 2 g' d over (x_0 .. x_drop dynamic states, CAN states) of the dropped terms
    H, g = np.zeros((nx + nt, nx + nt)), np.zeros(nx + nt)
    # the old arrival cost on the first state: its dynamic states are the first md variables, its CAN states the last
    W, pull = old.weight, old.weight @ (win.x[0] - old.prior)
    H[:md, :md], H[:md, nx:], H[nx:, :md], H[nx:, nx:] = W[:md, :md], W[:md, md:], W[md:, :md], W[md:, md:]
    g[:md], g[nx:] = pull[:md], pull[md:]
    alpha = old.alpha
    x, t, y, offset, avail, allow = win.x, win.t, win.y, win.offset, win.avail, win.allow  # the views, made once
    for k in range(drop):
        q = Q[k] if k < len(Q) else q_caps
        w, dwp, dwn, e, dep = step_jac(x[k], x[k + 1], float(t[k + 1] - t[k]), y[k])
        w = w - offset[k + 1, :md]
        # the rows divided by their bounds: the state noise's by q, the present outputs' by their allowances
        Jp, J = dwp / q[:, None], np.zeros((md, nx + nt))
        J[:, k * md : (k + 1) * md], J[:, nx:] = Jp[:, :md], Jp[:, md:]
        J[:, (k + 1) * md : (k + 2) * md] = dwn[:, :md] / q[:, None]
        ok = avail[k]
        r = (allow[k] * out_factor)[ok]
        Jo, Je = dep[ok] / r[:, None], np.zeros((len(r), nx + nt))
        Je[:, k * md : (k + 1) * md], Je[:, nx:] = Jo[:, :md], Jo[:, md:]
        H += J.T @ J + Je.T @ Je
        g += J.T @ (w / q) + Je.T @ (e[ok] / r)
        alpha = np.minimum(alpha, measured_bounds(model, win, k, theta_range, out_factor))
        # x_{k+1} = T(x_k, x_{k+1}) + w: dx_{k+1}/dx_k = (dw/dx_{k+1})^-1 (-dw/dx_k)
        F = np.abs(linalg.solve(dwn[:, :md], -dwp[:, :md]))
        if np.isfinite(alpha).all():  # a known box (nearly always): the general form's values, four calls fewer
            alpha = F @ alpha + 2.0 * q
            continue
        unknown = ~np.isfinite(alpha)
        grown = F @ np.where(unknown, 0.0, alpha) + 2.0 * q
        alpha = np.where((F[:, unknown] > 0).any(axis=1), np.inf, grown)
    prior, weight = reduce(
        H, g, drop * md, x[drop], nt, theta_drift_variance(theta_drift, theta_range, float(t[drop] - t[0]))
    )
    return Arrival(alpha, x[drop].copy(), prior, weight)


@functools.cache
def _eps_eye(n: int) -> FloatArray:
    """``EPS * np.eye(n)``, made once per size (read-only): two of the few-microsecond numpy calls of
    :func:`reduce` saved."""
    eye = EPS * np.eye(n)
    eye.flags.writeable = False
    return eye


def reduce(
    H: FloatArray, g: FloatArray, na: int, x_new: FloatArray, nt: int, drift: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Eliminate the first ``na`` variables (the dropped states) from the quadratic ``d' H d + 2 g' d``: the
    arrival cost's centre and weight on the new first state (its dynamic states, then the ``nt`` CAN states), the
    CAN states' variance grown by ``drift``."""
    K = linalg.solve(H[:na, :na] + _eps_eye(na), np.concatenate([H[:na, na:], g[:na, None]], axis=1))
    Hr = H[na:, na:] - H[na:, :na] @ K[:, :-1]
    gr = g[na:] - H[na:, :na] @ K[:, -1]
    Hr = 0.5 * (Hr + Hr.T) + _eps_eye(len(gr))
    prior = x_new - linalg.solve(Hr, gr)
    if nt == 0:
        return prior, Hr
    return prior, drifted(Hr, nt, drift)


def drifted(weight: FloatArray, nt: int, drift: FloatArray) -> FloatArray:
    """The information ``weight`` after its last ``nt`` states (the CAN states) drifted by the variances ``drift``:
    ``W <- (W^-1 + E D E')^-1`` by Woodbury, ``D`` the drift variance."""
    E = weight[:, -nt:]
    grown = weight - E @ linalg.solve(weight[-nt:, -nt:] + np.diag(1.0 / np.maximum(drift, 1e-30)), E.T)
    return 0.5 * (grown + grown.T)
