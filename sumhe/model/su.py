"""State-uniform (SU) vehicle models: the paper's two-antenna model and a single-antenna variant.

Paper 000 (``shared/seeds/000_*.txt``), section 4.1: the state equation (19), the output equation (20) and
the antenna-distance restriction (23). Every function here is pure and works on floats, numpy arrays and
CasADi symbols alike: a state ``x`` is anything indexable by state number (a 1-D numpy array, a numpy array
of shape ``(m, T)`` to evaluate ``T`` steps at once, or a CasADi ``SX``/``MX`` column), and ``ns`` is the
namespace giving ``sin``, ``cos`` and ``arctan2`` (``numpy``, the default, or ``casadi``). Functions return
one expression per state or output, as a list; stack them with ``numpy.array`` or ``casadi.vertcat``.

Conventions (the whole package): px east, py north (m); azimuth phi clockwise from north (rad); yaw rate
omega anticlockwise positive (rad/s), so a left turn decreases phi: ``phi_t = phi_{t-1} - h * omega_{t-1}``.

Beyond the paper, optional states model real sensors and their installation (issues 7 and 12): a yaw-rate bias
``b`` and gain ``g`` (CAN yaw rate = g omega + b), a speed scale factor ``k`` (CAN speed = k v), and, for the
single-antenna model, an azimuth offset ``c`` of the receiver (its course or heading = the azimuth + c: sideslip
in steady driving, a mounting angle) and the antenna's lever arm ``l`` ahead of the reference point (the fix is
that point's position; it moves sideways in turns, so its course differs from the azimuth by ``atan(l omega /
v)``); the lever arm aside, ``antenna_left_m``, is a fixed parameter. They are appended after the kinematic states
and carried unchanged by the state equation: within a window they are the time-invariant parameters Theta of
paper 000 (2), with no state noise.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

Step = Callable[..., list[Any]]
"""``step(x, h, ns) -> list``: an explicit state equation g of (8) without noise."""
Transition = Callable[..., list[Any]]
"""``transition(x_prev, x_next, h, ns) -> list``: the prediction of x_t the state noise is measured from."""

SU7_STATES = ("px1", "py1", "px2", "py2", "phi", "v", "omega")
SU7_OUTPUTS = ("px1", "py1", "px2", "py2", "azimuth", "can_speed", "can_yaw_rate")
SU5_STATES = ("px", "py", "phi", "v", "omega")
SU5_OUTPUTS = ("px", "py", "course", "can_speed", "can_yaw_rate")
BIAS_STATE = "yaw_rate_bias"
SCALE_STATE = "speed_scale"
GAIN_STATE = "yaw_rate_gain"
AZIMUTH_OFFSET_STATE = "azimuth_offset"
LEVER_STATE = "antenna_forward"
MIN_COURSE_SPEED_MPS = 0.1
"""Speed (m/s) below which the antenna's course is taken as the azimuth's (keeps :func:`antenna_motion` smooth)."""
GPS_SPEED_OUTPUT = "gps_speed"
"""The receiver's speed over ground (Doppler), an output just before the CAN ones when the model has it."""


def wrap_angle(a: Any, ns: Any = np) -> Any:
    """Wrap an angle (rad) to (-pi, pi] as ``atan2(sin a, cos a)``; smooth, so usable inside an NLP."""
    w = ns.arctan2(ns.sin(a), ns.cos(a))
    return np.where(w <= -np.pi, np.pi, w) if ns is np else w


def _n_rows(x: Any) -> int:
    return len(x) if isinstance(x, list | tuple) else int(x.shape[0])


def _entries(x: Any, start: int = 0) -> list[Any]:
    """The entries of a state ``x`` from ``start`` on, as a new list: a list's slice (the CAN-rate propagation's
    plain floats: a third of the time of indexing them one by one), else indexed one by one (CasADi matrices are
    not iterable; a numpy array of states as columns gives its rows)."""
    if isinstance(x, list):
        return x[start:]
    return [x[i] for i in range(start, _n_rows(x))]


def su7_step(x: Any, h: Any, ns: Any = np, lever_m: float = 0.0) -> list[Any]:
    """Paper (19) without noise: the state one step of ``h`` seconds later (explicit Euler).

    ``x`` = (px1, py1, px2, py2, phi, v, omega, *extra); extra states (bias, scale) are carried unchanged.
    Both antennas move by ``h v (sin phi, cos phi)``; ``phi`` decreases by ``h omega``; v and omega are
    random walks (no fast changes between two epochs). With ``lever_m = 0`` this is (19) exactly. Antenna 2
    sits ``d`` behind antenna 1 on the vehicle's axis, so when the vehicle turns it also swings sideways:
    ``lever_m = d`` adds that rotation, ``h d omega (cos phi, -sin phi)`` (a left turn swings it right).
    """
    px1, py1, px2, py2, phi, v, omega = (x[i] for i in range(7))
    dx = h * v * ns.sin(phi)
    dy = h * v * ns.cos(phi)
    swing = h * lever_m * omega
    extra = [x[i] for i in range(7, _n_rows(x))]
    return [
        px1 + dx,
        py1 + dy,
        px2 + dx + swing * ns.cos(phi),
        py2 + dy - swing * ns.sin(phi),
        phi - h * omega,
        v,
        omega,
        *extra,
    ]


def su5_step(x: Any, h: Any, ns: Any = np) -> list[Any]:
    """Single-antenna twin of (19): ``x`` = (px, py, phi, v, omega, *extra), one step of ``h`` s later."""
    px, py, phi, v, omega = x[0], x[1], x[2], x[3], x[4]
    return [px + h * v * ns.sin(phi), py + h * v * ns.cos(phi), phi - h * omega, v, omega, *_entries(x, 5)]


def trapezoid(step: Step, i_phi: int, i_v: int, i_omega: int) -> Transition:
    """The second-order (trapezoidal) twin of an explicit Euler step such as :func:`su7_step`.

    The paper's (19) moves the position with ``v_{t-1}`` along ``phi_{t-1}`` and turns by ``h omega_{t-1}``:
    first-order, so in a slalom at 10 Hz (yaw rate swinging by 1.5 rad/s^2) the azimuth lags by
    ``h/2 (omega_t - omega_0)`` (a few degrees) and the positions by decimetres per second. The twin uses
    the step's mean speed and yaw rate ``(v_{t-1} + v_t)/2``, ``(omega_{t-1} + omega_t)/2`` and the
    mid-step azimuth ``phi_{t-1} - h omega_mean / 2``; v and omega keep their random walks. It needs
    ``x_t`` too (an implicit scheme), which an NLP over the whole trajectory has anyway.
    """

    def transition(xp: Any, xn: Any, h: Any, ns: Any = np) -> list[Any]:
        v_mean = 0.5 * (xp[i_v] + xn[i_v])
        omega_mean = 0.5 * (xp[i_omega] + xn[i_omega])
        mid = _entries(xp)
        mid[i_v], mid[i_omega], mid[i_phi] = v_mean, omega_mean, xp[i_phi] - 0.5 * h * omega_mean
        out = step(mid, h, ns)
        out[i_phi], out[i_v], out[i_omega] = xp[i_phi] - h * omega_mean, xp[i_v], xp[i_omega]
        return out

    return transition


def euler(step: Step) -> Transition:
    """An explicit step as a transition ``(x_{t-1}, x_t, h) -> prediction of x_t`` (x_t unused)."""

    def transition(xp: Any, xn: Any, h: Any, ns: Any = np) -> list[Any]:
        return step(xp, h, ns)

    return transition


def antenna_azimuth(px1: Any, py1: Any, px2: Any, py2: Any, ns: Any = np) -> Any:
    """xi of (20): azimuth (rad, clockwise from north) of antenna 1 (front) seen from antenna 2 (rear).

    The paper builds it from arctan((px1-px2)/(py1-py2)) and the two signs, which is ``atan2``.
    """
    return ns.arctan2(px1 - px2, py1 - py2)


def antenna_distance_residual(x: Any) -> Any:
    """Left side of (23) before the tolerance: squared antenna distance (m^2) of an su7 state.

    The restriction is ``|residual - d^2| <= alpha``.
    """
    return (x[0] - x[2]) ** 2 + (x[1] - x[3]) ** 2


def can_outputs(
    v: Any, omega: Any, x: Any, bias_index: int | None, scale_index: int | None, gain_index: int | None = None
) -> list[Any]:
    """CAN speed (m/s) and yaw rate (rad/s) as measured: ``k v`` and ``g omega + b`` when those states exist."""
    speed = v * x[scale_index] if scale_index is not None else v
    yaw_rate = omega * x[gain_index] if gain_index is not None else omega
    yaw_rate = yaw_rate + x[bias_index] if bias_index is not None else yaw_rate
    return [speed, yaw_rate]


def can_motion(
    speed: Any, yaw_rate: Any, x: Any, bias_index: int | None, scale_index: int | None, gain_index: int | None = None
) -> list[Any]:
    """The speed (m/s) and yaw rate (rad/s) of a vehicle whose CAN reads ``speed`` and ``yaw_rate``: the inverse of
    :func:`can_outputs` at the CAN states of ``x``, ``speed / k`` and ``(yaw_rate - b) / g``."""
    v = speed / x[scale_index] if scale_index is not None else speed
    omega = yaw_rate - x[bias_index] if bias_index is not None else yaw_rate
    omega = omega / x[gain_index] if gain_index is not None else omega
    return [v, omega]


def antenna_motion(
    phi: Any, v: Any, omega: Any, forward_m: Any, left_m: float, ns: Any = np
) -> tuple[Any, Any, Any, Any]:
    """Where an antenna ``forward_m`` ahead of and ``left_m`` left of the reference point is and how it moves:
    its offset (east, north) from the point (m), its course (rad) and its speed over ground (m/s).

    Its velocity is ``(v - left omega)`` along the azimuth plus ``forward omega`` to the left (anticlockwise
    rotation), so its course is the azimuth minus ``atan(forward omega / (v - left omega))`` and its speed
    ``(v - left omega)`` plus the second-order ``(forward omega)^2 / 2|v|``; both smoothed below
    :data:`MIN_COURSE_SPEED_MPS` so that an NLP's derivatives stay finite at rest."""
    sin, cos = ns.sin(phi), ns.cos(phi)
    along = v - left_m * omega
    side = forward_m * omega
    speed = ns.sqrt(along * along + MIN_COURSE_SPEED_MPS**2)
    course = phi - ns.arctan2(side, speed)
    return forward_m * sin - left_m * cos, forward_m * cos + left_m * sin, course, along + side * side / (2.0 * speed)


def su7_output(
    x: Any, ns: Any = np, bias_index: int | None = None, scale_index: int | None = None, gps_speed: bool = False
) -> list[Any]:
    """Paper (20) without noise: both antenna positions (m), their azimuth xi (rad), (the GNSS speed over ground,
    m/s, with ``gps_speed``), CAN speed and yaw rate."""
    px1, py1, px2, py2 = (x[i] for i in range(4))
    xi = antenna_azimuth(px1, py1, px2, py2, ns)
    return [px1, py1, px2, py2, xi, *[x[5]] * gps_speed, *can_outputs(x[5], x[6], x, bias_index, scale_index)]


@dataclass(frozen=True)
class Installation:
    """Which optional states of the single-antenna model exist (their indices, None without) and the antenna's
    fixed lever arm (m): ahead (where it is not a state) and aside."""

    bias: int | None = None
    scale: int | None = None
    gain: int | None = None
    azimuth_offset: int | None = None
    lever: int | None = None
    forward_m: float = 0.0
    left_m: float = 0.0


def su5_output(x: Any, ns: Any = np, gps_speed: bool = False, inst: Installation = Installation()) -> list[Any]:
    """Single-antenna outputs: GPS position (m), azimuth (course or heading, rad), (the GNSS speed over ground,
    m/s, with ``gps_speed``), CAN speed and yaw rate; with an antenna lever arm (:func:`antenna_motion`), the
    antenna's position, course and speed; with an azimuth offset, the azimuth output plus it."""
    px, py, phi, v, omega = (x[i] for i in range(5))
    if inst.lever is not None or inst.forward_m or inst.left_m:
        forward = x[inst.lever] if inst.lever is not None else inst.forward_m
        de, dn, azimuth, sog = antenna_motion(phi, v, omega, forward, inst.left_m, ns)
        px, py = px + de, py + dn
    else:
        azimuth, sog = phi, v
    if inst.azimuth_offset is not None:
        azimuth = azimuth + x[inst.azimuth_offset]
    return [px, py, azimuth, *[sog] * gps_speed, *can_outputs(v, omega, x, inst.bias, inst.scale, inst.gain)]


@dataclass(frozen=True)
class SuModel:
    """One SU vehicle model as plain data: names, which entries are angles, and its two functions.

    ``step(x, h, ns)`` is g of (8) (explicit Euler, the paper's (19)); ``transition(x_prev, x_next, h, ns)``
    is the prediction of x_t the estimator measures the state noise from (``step`` itself, or its
    :func:`trapezoid` twin); ``output(x, ns)`` is h of (9). ``q_power[i]`` is the power of the step
    length with which the state-noise bound of state ``i`` scales (2: Euler error of an integrated
    quantity, 1: one-step change of a random walk). ``gps_outputs`` are the outputs present only with a
    GNSS fix; ``position`` names the (east, north) state indices of the reported position. The first
    ``n_dynamic`` states carry state noise; the rest (bias, scale) are constant over a window. The indices
    below are looked up once (cached: the estimators read them per CAN sample).
    """

    name: str
    states: tuple[str, ...]
    outputs: tuple[str, ...]
    step: Step
    transition: Transition
    output: Callable[..., list[Any]]
    angle_states: tuple[int, ...]
    angle_outputs: tuple[int, ...]
    gps_outputs: tuple[int, ...]
    q_power: tuple[int, ...]
    position: tuple[int, int]
    antennas: int
    n_dynamic: int

    @functools.cached_property
    def n_states(self) -> int:
        return len(self.states)

    @functools.cached_property
    def n_outputs(self) -> int:
        return len(self.outputs)

    def index(self, state: str) -> int:
        """Index of a state by name; ValueError for a state this model does not have."""
        return self.states.index(state)

    def _optional(self, state: str) -> int | None:
        return self.states.index(state) if state in self.states else None

    @functools.cached_property
    def i_phi(self) -> int:
        """The azimuth state."""
        return self.states.index("phi")

    @functools.cached_property
    def i_v(self) -> int:
        """The speed state."""
        return self.states.index("v")

    @functools.cached_property
    def i_omega(self) -> int:
        """The yaw-rate state."""
        return self.states.index("omega")

    @functools.cached_property
    def i_bias(self) -> int | None:
        """The CAN yaw-rate bias state, None without it."""
        return self._optional(BIAS_STATE)

    @functools.cached_property
    def i_scale(self) -> int | None:
        """The CAN speed-scale state, None without it."""
        return self._optional(SCALE_STATE)

    @functools.cached_property
    def i_gain(self) -> int | None:
        """The CAN yaw-rate gain state, None without it."""
        return self._optional(GAIN_STATE)

    @functools.cached_property
    def i_azimuth_offset(self) -> int | None:
        """The receiver's azimuth offset state, None without it."""
        return self._optional(AZIMUTH_OFFSET_STATE)

    @functools.cached_property
    def i_lever(self) -> int | None:
        """The antenna's lever arm ahead of the reference point, None without it."""
        return self._optional(LEVER_STATE)

    @functools.cached_property
    def j_azimuth(self) -> int:
        """The azimuth output (course/heading; su7: the antennas' xi)."""
        return self.angle_outputs[0]

    @functools.cached_property
    def j_gps_speed(self) -> int | None:
        """The GNSS speed-over-ground output, None without it."""
        return self.outputs.index(GPS_SPEED_OUTPUT) if GPS_SPEED_OUTPUT in self.outputs else None

    @functools.cached_property
    def j_can_speed(self) -> int:
        """The CAN speed output."""
        return self.outputs.index("can_speed")

    @functools.cached_property
    def j_can_yaw_rate(self) -> int:
        """The CAN yaw-rate output."""
        return self.outputs.index("can_yaw_rate")

    @functools.cached_property
    def j_position(self) -> tuple[int, int]:
        """The (east, north) outputs of the (first) antenna's position."""
        return self.gps_outputs[0], self.gps_outputs[1]


def state_noise(model: SuModel, xp: Any, xn: Any, h: Any, ns: Any = np) -> list[Any]:
    """The state noise ``w = x_t - T(x_{t-1}, x_t, h)`` of the dynamic states (one per state).

    The one angle rule of the package: the azimuth *state* is continuous along a trajectory (never wrapped), so its
    noise is not wrapped either (a wrapped state noise would let the azimuth jump by 2 pi from step to step, away
    from its bounds); *measured* angles lie in [0, 2 pi) and their residuals are wrapped (:func:`output_noise`).
    Works on numpy (one state, or states as columns) and CasADi alike (``ns``)."""
    pred = model.transition(xp, xn, h, ns)
    return [xn[i] - pred[i] for i in range(model.n_dynamic)]


def output_noise(model: SuModel, x: Any, y: Any, ns: Any = np) -> list[Any]:
    """The output noise ``e = y - h(x)`` (one per output), angle outputs wrapped (see :func:`state_noise`)."""
    out = model.output(x, ns)
    e = [y[j] - out[j] for j in range(model.n_outputs)]
    return [wrap_angle(e[j], ns) if j in model.angle_outputs else e[j] for j in range(model.n_outputs)]


def state_residuals(model: SuModel, x: Any, h: Any) -> Any:
    """:func:`state_noise` of a trajectory ``x`` (N x m, numpy) with steps ``h`` (N-1,), s: (N-1 x n_dynamic)."""
    return np.array(state_noise(model, x[:-1].T, x[1:].T, h)).T


def output_residuals(model: SuModel, x: Any, y: Any) -> Any:
    """:func:`output_noise` of a trajectory ``x`` (N x m, numpy) against outputs ``y`` (N x n) at every step
    (mask the missing ones): (N x n).

    One step (the MHE's step leaving the window, at nearly every epoch) on its numpy scalars rather than one-element
    rows: the same ufunc loops for the functions and IEEE arithmetic for the rest (the same bits), at a tenth of a
    microsecond an operation instead of most of one (15.5 -> 6 us a call)."""
    if len(x) == 1:
        return np.array(output_noise(model, x[0], y[0]))[None, :]
    return np.array(output_noise(model, x.T, y.T)).T


def integrate_odometry(
    t: Any, v: Any, w: Any, east0: float = 0.0, north0: float = 0.0, phi0: float = 0.0
) -> tuple[Any, Any, Any]:
    """Dead reckoning: east, north (m) and azimuth (rad) at the times ``t`` (s) of a vehicle whose speed ``v``
    (m/s) and yaw rate ``w`` (rad/s, anticlockwise) at those times are linear in between, from ``(east0, north0,
    phi0)`` at ``t[0]``: the azimuth by the trapezoid rule, each interval driven at its mean speed along its mid
    azimuth (second order; exact on a straight line). The one CAN integration of the package: a fine ``t`` makes
    it the reference the noise floors and the dead-reckoning floor are measured with."""
    dt = np.diff(t)
    phi = phi0 - np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * dt)])
    mid_phi, mid_v = 0.5 * (phi[1:] + phi[:-1]), 0.5 * (v[1:] + v[:-1])
    east = east0 + np.concatenate([[0.0], np.cumsum(mid_v * np.sin(mid_phi) * dt)])
    north = north0 + np.concatenate([[0.0], np.cumsum(mid_v * np.cos(mid_phi) * dt)])
    return east, north, phi


def odometry_end(
    t: Sequence[float], v: Sequence[float], w: Sequence[float], east0: float, north0: float, phi0: float
) -> tuple[float, float, float]:
    """The last point (east, north, azimuth) of :func:`integrate_odometry` of plain floats (at least two times),
    its sums run in the same order: the same bits, without numpy's set-up on the few samples of a GNSS step."""
    phi_sum = east_sum = north_sum = math.nan
    phi_prev = phi0 - 0.0
    for k in range(1, len(t)):
        dt = t[k] - t[k - 1]
        turn = 0.5 * (w[k] + w[k - 1]) * dt
        phi_sum = turn if k == 1 else phi_sum + turn
        phi = phi0 - phi_sum
        mid_phi, mid_v = 0.5 * (phi + phi_prev), 0.5 * (v[k] + v[k - 1])
        east, north = mid_v * math.sin(mid_phi) * dt, mid_v * math.cos(mid_phi) * dt
        east_sum = east if k == 1 else east_sum + east
        north_sum = north if k == 1 else north_sum + north
        phi_prev = phi
    return east0 + east_sum, north0 + north_sum, phi_prev


@functools.lru_cache(maxsize=64)
def su_model(
    name: str,
    yaw_rate_bias: bool = False,
    speed_scale: bool = False,
    discretisation: str = "euler",
    lever_m: float = 0.0,
    gps_speed: bool = False,
    yaw_rate_gain: bool = False,
    azimuth_offset: bool = False,
    antenna_forward: bool = False,
    antenna_forward_m: float = 0.0,
    antenna_left_m: float = 0.0,
) -> SuModel:
    """The model ``"su7"`` (paper (19)-(20)) or ``"su5"`` (single antenna), with optional CAN-error states,
    discretised by ``"euler"`` (the paper's (19)) or ``"trapezoid"`` (:func:`trapezoid`); ``lever_m`` is
    the antenna-2 lever arm of :func:`su7_step` (0: the paper's rigid translation); ``gps_speed`` adds the
    receiver's speed over ground as an output (:data:`GPS_SPEED_OUTPUT`, a GNSS output before the CAN ones).
    ``su5`` only: the yaw-rate gain, the receiver's azimuth offset and the antenna's lever arm ahead as states,
    the lever arm (m) ahead ``antenna_forward_m`` (where it is not a state) and aside ``antenna_left_m`` as
    parameters (module docstring). Built once per argument set (the
    models are immutable)."""
    if name not in ("su7", "su5"):
        raise ValueError(f"model: unknown SU model {name!r} (su5, su7)")
    if discretisation not in ("euler", "trapezoid"):
        raise ValueError(f"discretisation: unknown scheme {discretisation!r} (euler, trapezoid)")
    if name == "su7" and (yaw_rate_gain or azimuth_offset or antenna_forward or antenna_forward_m or antenna_left_m):
        raise ValueError("model: the yaw-rate gain, azimuth offset and antenna lever arm are su5's only")
    base = SU7_STATES if name == "su7" else SU5_STATES
    extra = (BIAS_STATE,) * yaw_rate_bias + (SCALE_STATE,) * speed_scale + (GAIN_STATE,) * yaw_rate_gain
    extra += (AZIMUTH_OFFSET_STATE,) * azimuth_offset + (LEVER_STATE,) * antenna_forward
    states = base + extra

    def index(state: str) -> int | None:
        return states.index(state) if state in states else None

    inst = Installation(
        index(BIAS_STATE),
        index(SCALE_STATE),
        index(GAIN_STATE),
        index(AZIMUTH_OFFSET_STATE),
        index(LEVER_STATE),
        antenna_forward_m,
        antenna_left_m,
    )
    step: Step = functools.partial(su7_step, lever_m=lever_m) if name == "su7" else su5_step

    def output(x: Any, ns: Any = np) -> list[Any]:
        if name == "su7":
            return su7_output(x, ns, inst.bias, inst.scale, gps_speed)
        return su5_output(x, ns, gps_speed, inst)

    speed_out = (GPS_SPEED_OUTPUT,) * gps_speed

    i_phi, i_v, i_omega = states.index("phi"), states.index("v"), states.index("omega")
    transition = trapezoid(step, i_phi, i_v, i_omega) if discretisation == "trapezoid" else euler(step)

    if name == "su7":
        return SuModel(
            name="su7",
            states=states,
            outputs=SU7_OUTPUTS[:5] + speed_out + SU7_OUTPUTS[5:],
            step=step,
            transition=transition,
            output=output,
            angle_states=(4,),
            angle_outputs=(4,),
            gps_outputs=(0, 1, 2, 3, 4, 5)[: 5 + gps_speed],
            q_power=(2, 2, 2, 2, 2, 1, 1),
            position=(0, 1),
            antennas=2,
            n_dynamic=7,
        )
    return SuModel(
        name="su5",
        states=states,
        outputs=SU5_OUTPUTS[:3] + speed_out + SU5_OUTPUTS[3:],
        step=step,
        transition=transition,
        output=output,
        angle_states=(2,),
        angle_outputs=(2,),
        gps_outputs=(0, 1, 2, 3)[: 3 + gps_speed],
        q_power=(2, 2, 2, 1, 1),
        position=(0, 1),
        antennas=1,
        n_dynamic=5,
    )
