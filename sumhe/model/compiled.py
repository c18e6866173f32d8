"""CasADi functions of the model evaluated from numpy without conversions, and the Jacobians derived from them."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from sumhe.model.su import can_outputs, su_model

JacobianFunction = Callable[..., NDArray[np.float64]]
"""Numpy arguments -> a dense Jacobian (rows x columns)."""


class NumpyFunction:
    """A CasADi function of dense inputs and outputs evaluated through its buffer interface: numpy in, numpy out,
    without the DM conversions of a plain call (0.3 us instead of 40-150 us per call here, where the MHE makes
    two calls per epoch). Arguments are read column-major, as CasADi stores matrices; not thread-safe (one
    estimator, one thread)."""

    def __init__(self, f: ca.Function) -> None:
        self._buffer, self._trigger = f.buffer()
        self._args = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self._res = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        for i, a in enumerate(self._args):
            self._buffer.set_arg(i, memoryview(a))
        for i, r in enumerate(self._res):
            self._buffer.set_res(i, memoryview(r))

    def __call__(self, *args: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """The first output (a copy) for these arguments."""
        for dst, src in zip(self._args, args, strict=True):
            if isinstance(src, np.ndarray) and src.ndim > 1:
                dst[:] = src.ravel(order="F")
            else:  # a vector or a number: no reordering (a ravel per argument was half this call's time)
                dst[:] = src
        self._trigger()
        return self._res[0].copy()

    def bind(self, i: int, value: NDArray[np.float64] | Sequence[float] | float) -> None:
        """Set argument ``i`` for the calls of :meth:`run` (an argument the same over many calls is set once, not at
        every call)."""
        self._args[i][:] = value.ravel(order="F") if isinstance(value, np.ndarray) else value

    def run(self) -> NDArray[np.float64]:
        """The first output for the arguments set by :meth:`bind` (and the last call): the result buffer itself,
        overwritten by the next call (no copy)."""
        self._trigger()
        return self._res[0]


def _dense(f: ca.Function, n_rows: int) -> JacobianFunction:
    """``f`` (one dense matrix output of ``n_rows`` rows, stored column-major) as a numpy function."""
    g = NumpyFunction(f)
    return lambda *args: g(*args).reshape(-1, n_rows).T


@functools.lru_cache(maxsize=8)
def kinematic_jacobian(n_states: int) -> JacobianFunction:
    """``(x, dt) -> d T(x, x, dt) / dx`` (n x n) of the single-antenna trapezoidal transition with ``n_states``
    states (the five kinematic ones, then states it carries unchanged): the Jacobian of a step at constant speed
    and yaw rate, which the Kalman peers predict with."""
    model = su_model("su5", discretisation="trapezoid")
    x, h = ca.SX.sym("x", n_states), ca.SX.sym("h")
    moved = ca.vertcat(*model.transition(x, x, h, ca))
    return _dense(ca.Function("kinematic_jacobian", [x, h], [ca.densify(ca.jacobian(moved, x))]), n_states)


@functools.lru_cache(maxsize=8)
def can_jacobian(yaw_rate_bias: bool, speed_scale: bool, yaw_rate_gain: bool = False) -> JacobianFunction:
    """``x -> d (CAN speed, CAN yaw rate) / dx`` (2 x m) of :func:`~sumhe.model.su.can_outputs` for the
    single-antenna model with these CAN states."""
    model = su_model("su5", yaw_rate_bias, speed_scale, yaw_rate_gain=yaw_rate_gain)
    x = ca.SX.sym("x", model.n_states)
    out = ca.vertcat(*can_outputs(x[model.i_v], x[model.i_omega], x, model.i_bias, model.i_scale, model.i_gain))
    return _dense(ca.Function("can_jacobian", [x], [ca.densify(ca.jacobian(out, x))]), 2)
