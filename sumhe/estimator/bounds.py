"""Floors and caps of the noise bounds q (state) and r (output): what makes the MAP problem well-posed.

The paper's prior (11) is ``0 <= q <= qbar``, ``0 <= r <= rbar``. With the objective (15) falling without
limit as any ``q_i -> 0``, the lower ends decide the answer, so both ends are derived here, per window:

* q caps: what a vehicle can do in one step of the reference length ``h``: the Euler error of a position
  ``h^2/2 * max_accel``, of the azimuth ``h^2/2 * max_yaw_accel``, one-step changes ``h * max_accel`` (v)
  and ``h * max_yaw_accel`` (omega). The CAN-error states (bias, scale) are constant over a window and
  have no q.
* q floors (``derived_floors``): the state noise, under the model and its discretisation, of a vehicle
  that does exactly what this window's CAN says (speed and yaw rate integrated finely,
  :func:`can_trajectory`): the model error the measured motion itself implies, so a floor never excludes
  a vehicle that did what its CAN says (for v and omega: the one-step CAN changes, noise included); at
  least what the CAN resolution leaves unknown over a step (:func:`resolution_floors`: a second-order
  scheme integrates a yaw rate that is linear within a step exactly, and a floor of 0 is no floor).
  Otherwise a token floor ``1e-6 * cap`` (the paper: ``q >= 0``).
* r caps: the median per-epoch error allowance of :mod:`sumhe.estimator.grid` (``r_cap_sigmas`` times
  the receiver's sigma, CAN resolution and noise, plus the unmodelled CAN scale/bias when those states are
  off). Per-epoch differences enter as scales: the output bound at epoch k is ``r_j * r_scale[k, j]``.
* r floors: the quantisation of each output (half a CAN resolution step, the NMEA position resolution).

State-noise bounds scale with the step length as ``(h_t / h_ref) ** q_power``.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.estimator.grid import Grid
from sumhe.frontend.measurements import GPS_SPEED_RESOLUTION_MPS
from sumhe.model.su import GPS_SPEED_OUTPUT, SuModel, integrate_odometry, state_residuals
from sumhe.settings import EstimationSettings

TOKEN_FLOOR = 1e-6


@dataclass(frozen=True)
class NoiseBounds:
    """Box prior on q (at the reference step ``h_ref``, s) and r, and the per-step/per-epoch scales."""

    q_lo: NDArray[np.float64]
    q_hi: NDArray[np.float64]
    r_lo: NDArray[np.float64]
    r_hi: NDArray[np.float64]
    q_scale: NDArray[np.float64]
    r_scale: NDArray[np.float64]
    h_ref: float


def widen_caps(bounds: NoiseBounds, factor: float) -> NoiseBounds:
    """The bounds with the caps of q and r multiplied by ``factor`` (algorithm 3.3 of 001, step 7)."""
    return dataclasses.replace(bounds, q_hi=bounds.q_hi * factor, r_hi=bounds.r_hi * factor)


def fill_gaps(values: NDArray[np.float64], t: NDArray[np.float64], default: float = 0.0) -> NDArray[np.float64]:
    """``values`` on the grid ``t`` with NaNs interpolated (held at the ends); ``default`` if none is finite."""
    ok = np.isfinite(values)
    if not ok.any():
        return np.full(len(t), default)
    return np.interp(t, t[ok], values[ok])


def _state_kind(name: str) -> str:
    if name.startswith(("px", "py")):
        return "position"
    return name


def q_caps(model: SuModel, h: float, settings: EstimationSettings) -> NDArray[np.float64]:
    """Cap on the state noise of each dynamic state for a step of ``h`` s: vehicle limits."""
    caps = {
        "position": 0.5 * h * h * settings.vehicle.max_accel_mps2,
        "phi": 0.5 * h * h * settings.vehicle.max_yaw_accel_rps2,
        "v": h * settings.vehicle.max_accel_mps2,
        "omega": h * settings.vehicle.max_yaw_accel_rps2,
    }
    return np.array([caps[_state_kind(s)] for s in model.states[: model.n_dynamic]])


def can_trajectory(model: SuModel, grid: Grid, lever_m: float, substeps: int = 10) -> NDArray[np.float64]:
    """A trajectory (N x m) of a vehicle that does exactly what its CAN says, on the grid.

    Speed and yaw rate are linear between the steps; azimuth and positions are integrated on ``substeps``
    sub-steps per step (midpoint rule) from 0; antenna 2 (su7) sits ``lever_m`` behind antenna 1; bias 0,
    scale 1. Its state noise under ``model`` is the model's discretisation error for this motion.
    """
    t = grid.t
    v = fill_gaps(grid.can_speed, t)
    w = fill_gaps(grid.can_yaw_rate, t)
    tf = np.concatenate([np.linspace(a, b, substeps, endpoint=False) for a, b in itertools.pairwise(t)] + [t[-1:]])
    east, north, phi = integrate_odometry(tf, np.interp(tf, t, v), np.interp(tf, t, w))
    k = np.arange(len(t)) * substeps
    x = np.zeros((len(t), model.n_states))
    ie, i_n = model.position
    x[:, ie], x[:, i_n] = east[k], north[k]
    if model.antennas == 2:
        x[:, ie + 2], x[:, i_n + 2] = east[k] - lever_m * np.sin(phi[k]), north[k] - lever_m * np.cos(phi[k])
    x[:, model.i_phi], x[:, model.i_v], x[:, model.i_omega] = phi[k], v, w
    if model.i_scale is not None:
        x[:, model.i_scale] = 1.0
    return x


def resolution_floors(model: SuModel, h: float, settings: EstimationSettings) -> NDArray[np.float64]:
    """What one step of ``h`` s leaves unknown given the CAN resolution: half a resolution step of speed
    (of yaw rate) integrated over the step for positions (azimuth), and half a step for v (omega)."""
    res_v, res_w = 0.5 * settings.can.speed_quantum_mps, 0.5 * settings.can.yaw_rate_quantum_rps
    floors = {"position": h * res_v, "phi": h * res_w, "v": res_v, "omega": res_w}
    return np.array([floors[_state_kind(s)] for s in model.states[: model.n_dynamic]])


def q_floors(
    model: SuModel, grid: Grid, q_scale: NDArray[np.float64], cap: NDArray[np.float64], lever_m: float
) -> NDArray[np.float64]:
    """The largest state noise (at ``h_ref``), under the model, of the vehicle that does what the window's
    CAN says (:func:`can_trajectory`), per dynamic state."""
    w = np.abs(state_residuals(model, can_trajectory(model, grid, lever_m), grid.h)) / q_scale
    return np.minimum(w.max(axis=0), cap)


def r_floors(model: SuModel, settings: EstimationSettings) -> NDArray[np.float64]:
    """Per-output floor on the output noise: quantisation of the measured values."""
    res = settings.gnss.resolution_m
    floors = [res] * (2 * model.antennas)
    floors.append(2.0 * res / settings.vehicle.antenna_distance_m if model.antennas == 2 else 1e-4)
    if GPS_SPEED_OUTPUT in model.outputs:
        floors.append(GPS_SPEED_RESOLUTION_MPS)
    floors += [0.5 * settings.can.speed_quantum_mps, 0.5 * settings.can.yaw_rate_quantum_rps]
    return np.array(floors)


def noise_bounds(model: SuModel, grid: Grid, settings: EstimationSettings, lever_m: float = 0.0) -> NoiseBounds:
    """The floors, caps and scales of q and r for this window (see the module docstring); ``lever_m`` is
    the su7 antenna-2 lever arm of the model (m)."""
    h = grid.h
    h_ref = float(np.median(h))
    q_scale = (h[:, None] / h_ref) ** np.array(model.q_power)[None, :]
    q_hi = q_caps(model, h_ref, settings)
    r_hi = np.ones(model.n_outputs)
    r_scale = np.ones_like(grid.allow)
    for j in range(model.n_outputs):
        ok = grid.avail[:, j]
        if ok.any():
            r_hi[j] = float(np.median(grid.allow[ok, j]))
            r_scale[ok, j] = grid.allow[ok, j] / r_hi[j]
    if settings.estimator.batch.derived_floors:
        q_lo = np.maximum(q_floors(model, grid, q_scale, q_hi, lever_m), resolution_floors(model, h_ref, settings))
        q_lo = np.minimum(q_lo, q_hi)
        r_lo = np.minimum(r_floors(model, settings), r_hi)
    else:
        q_lo, r_lo = TOKEN_FLOOR * q_hi, TOKEN_FLOOR * r_hi
    return NoiseBounds(q_lo=q_lo, q_hi=q_hi, r_lo=r_lo, r_hi=r_hi, q_scale=q_scale, r_scale=r_scale, h_ref=h_ref)
