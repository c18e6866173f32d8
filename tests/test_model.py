"""SU vehicle models: hand-computed steps, sign conventions, numpy/CasADi agreement, discretisations."""

import math

import casadi as ca
import numpy as np
import pytest

from sumhe.model import (
    antenna_azimuth,
    antenna_distance_residual,
    integrate_odometry,
    output_noise,
    output_residuals,
    state_noise,
    state_residuals,
    su5_output,
    su5_step,
    su7_output,
    su7_step,
    su_model,
    wrap_angle,
)
from sumhe.model.su import can_motion


def test_su5_step_by_hand() -> None:
    # heading east (phi = pi/2), 10 m/s, 0.1 s: 1 m east, nothing north; omega 0.5 turns phi by -0.05
    x = np.array([1.0, 2.0, math.pi / 2, 10.0, 0.5])
    px, py, phi, v, omega = su5_step(x, 0.1)
    assert px == pytest.approx(2.0)
    assert py == pytest.approx(2.0, abs=1e-12)
    assert phi == pytest.approx(math.pi / 2 - 0.05)
    assert (v, omega) == (10.0, 0.5)


def test_su7_step_by_hand_is_paper_19() -> None:
    # heading north-east (phi = pi/4): both antennas move h v (sin, cos) = (0.5 sqrt2, 0.5 sqrt2)
    x = [0.0, 0.0, -0.7, -0.7, math.pi / 4, 5.0, -0.2]
    out = su7_step(x, 0.2)
    s = 0.2 * 5.0 * math.sqrt(0.5)
    assert out[:4] == pytest.approx([s, s, -0.7 + s, -0.7 + s])
    assert out[4] == pytest.approx(math.pi / 4 + 0.04)
    assert out[5:] == [5.0, -0.2]


def test_left_turn_decreases_azimuth_and_goes_west_from_north() -> None:
    x = np.array([0.0, 0.0, 0.0, 10.0, 0.3])  # heading north, turning left (anticlockwise)
    for _ in range(30):
        x = np.array(su5_step(x, 0.1))
    assert x[2] < 0  # azimuth clockwise from north: a left turn decreases it
    assert x[0] < -1.0  # ... and the vehicle ends up west (negative east) of its start
    assert x[1] > 5.0


def test_lever_arm_swings_rear_antenna_right_in_a_left_turn() -> None:
    x = [0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.5]  # at rest, heading north, yawing left
    out = su7_step(x, 0.1, lever_m=1.0)
    assert out[0:2] == [0.0, 0.0]  # antenna 1 (the reference point) does not move
    assert out[2] == pytest.approx(0.05)  # antenna 2, 1 m behind, swings east = right
    assert su7_step(x, 0.1)[2] == 0.0  # the paper's rigid translation does not


def test_outputs_with_can_bias_and_scale() -> None:
    x = [3.0, 4.0, 0.1, 20.0, 0.05, 0.007, 1.02]
    assert su5_output(x, bias_index=5, scale_index=6) == pytest.approx([3.0, 4.0, 0.1, 20.4, 0.057])
    assert su5_output(x[:5]) == [3.0, 4.0, 0.1, 20.0, 0.05]
    y = su7_output([1.0, 1.0, 0.0, 0.0, 0.7, 8.0, 0.1])
    assert y[:4] == [1.0, 1.0, 0.0, 0.0]
    assert y[4] == pytest.approx(math.pi / 4)  # xi: antenna 1 north-east of antenna 2
    assert y[5:] == [8.0, 0.1]


@pytest.mark.parametrize(
    ("d_east", "d_north", "azimuth"),
    [(0.0, 1.0, 0.0), (1.0, 0.0, math.pi / 2), (0.0, -1.0, math.pi), (-1.0, 0.0, -math.pi / 2)],
)
def test_antenna_azimuth_is_clockwise_from_north(d_east: float, d_north: float, azimuth: float) -> None:
    assert antenna_azimuth(d_east, d_north, 0.0, 0.0) == pytest.approx(azimuth)


def test_antenna_distance_residual() -> None:
    assert antenna_distance_residual([3.0, 4.0, 0.0, 0.0]) == pytest.approx(25.0)


def test_wrap_angle_range() -> None:
    a = np.array([0.0, math.pi, -math.pi, 3 * math.pi / 2, -3 * math.pi / 2, 7.0])
    w = wrap_angle(a)
    assert np.all(w > -math.pi)
    assert np.all(w <= math.pi)
    assert w == pytest.approx([0.0, math.pi, math.pi, -math.pi / 2, math.pi / 2, 7.0 - 2 * math.pi])
    assert float(wrap_angle(ca.DM(3 * math.pi / 2), ca)) == pytest.approx(-math.pi / 2)


@pytest.mark.parametrize("name", ["su5", "su7"])
@pytest.mark.parametrize("discretisation", ["euler", "trapezoid"])
def test_numpy_and_casadi_agree(name: str, discretisation: str) -> None:
    model = su_model(name, yaw_rate_bias=True, speed_scale=True, discretisation=discretisation, lever_m=0.8)
    rng = np.random.default_rng(1)
    xp, xn = rng.normal(size=model.n_states), rng.normal(size=model.n_states)
    sp, sn = ca.SX.sym("xp", model.n_states), ca.SX.sym("xn", model.n_states)
    f = ca.Function("f", [sp, sn], [ca.vertcat(*model.transition(sp, sn, 0.1, ca)), ca.vertcat(*model.output(sp, ca))])
    g, y = f(xp, xn)
    assert np.asarray(g).ravel() == pytest.approx(model.transition(xp, xn, 0.1))
    assert np.asarray(y).ravel() == pytest.approx(model.output(xp))


def test_vectorised_over_steps() -> None:
    x = np.random.default_rng(2).normal(size=(5, 4))
    out = np.array(su5_step(x, 0.1))
    for k in range(4):
        assert out[:, k] == pytest.approx(su5_step(x[:, k], 0.1))


def test_trapezoid_is_second_order_on_a_circle() -> None:
    v, omega, h = 10.0, 0.8, 0.1
    phi0 = 0.2
    east = (v / omega) * (math.cos(phi0 - omega * h) - math.cos(phi0))
    north = -(v / omega) * (math.sin(phi0 - omega * h) - math.sin(phi0))
    xp = np.array([0.0, 0.0, phi0, v, omega])
    xn = np.array([east, north, phi0 - omega * h, v, omega])
    w_euler = state_residuals(su_model("su5"), np.array([xp, xn]), np.array([h]))
    w_trap = state_residuals(su_model("su5", discretisation="trapezoid"), np.array([xp, xn]), np.array([h]))
    assert np.abs(w_euler[0, :2]).max() > 0.01  # Euler: h^2 v omega / 2 = 4 cm
    assert np.abs(w_trap).max() < 1e-3
    assert w_trap[0, 2] == pytest.approx(0.0, abs=1e-12)


def test_residuals_of_an_exact_trajectory_are_zero() -> None:
    model = su_model("su7", yaw_rate_bias=True, lever_m=1.0)
    x = [np.array([0.0, 0.0, 0.0, -1.0, 0.1, 8.0, 0.3, 0.01])]
    for _ in range(5):
        x.append(np.array(model.step(x[-1], 0.1)))
    xs = np.array(x)
    assert np.abs(state_residuals(model, xs, np.full(5, 0.1))).max() < 1e-12
    y = np.array(model.output(xs.T)).T
    assert np.abs(output_residuals(model, xs, y)).max() < 1e-12
    assert model.n_dynamic == 7
    assert model.index("yaw_rate_bias") == 7


def test_unknown_model_or_scheme() -> None:
    with pytest.raises(ValueError, match="model"):
        su_model("su9")
    with pytest.raises(ValueError, match="discretisation"):
        su_model("su5", discretisation="rk4")


def test_can_motion_inverts_the_can_outputs() -> None:
    m = su_model("su5", yaw_rate_bias=True, speed_scale=True)
    x = np.array([0.0, 0.0, 0.1, 12.0, 0.2, 0.01, 1.03])
    speed, yaw_rate = m.output(x)[m.j_can_speed], m.output(x)[m.j_can_yaw_rate]
    assert can_motion(speed, yaw_rate, x, m.i_bias, m.i_scale) == pytest.approx([12.0, 0.2])
    assert can_motion(5.0, 0.1, x[:5], None, None) == [5.0, 0.1]


def test_named_indices() -> None:
    m = su_model("su5", yaw_rate_bias=True, speed_scale=True, gps_speed=True)
    assert (m.i_phi, m.i_v, m.i_omega, m.i_bias, m.i_scale) == (2, 3, 4, 5, 6)
    assert (m.j_position, m.j_azimuth, m.j_gps_speed, m.j_can_speed, m.j_can_yaw_rate) == ((0, 1), 2, 3, 4, 5)
    plain = su_model("su7")
    assert (plain.i_phi, plain.i_bias, plain.i_scale, plain.j_gps_speed) == (4, None, None, None)
    assert (plain.j_azimuth, plain.j_can_speed, plain.j_can_yaw_rate) == (4, 5, 6)


def test_one_angle_rule_for_residuals_numpy_and_casadi() -> None:
    model = su_model("su5", discretisation="trapezoid")
    xp = np.array([0.0, 0.0, 3.1, 0.0, 0.0])
    xn = np.array([0.0, 0.0, 3.1 + 2 * math.pi + 0.01, 0.0, 0.0])
    # the azimuth state is continuous: a 2 pi jump is state noise, not wrapped away
    assert state_noise(model, xp, xn, 0.1)[2] == pytest.approx(2 * math.pi + 0.01)
    # a measured course of -3.1 rad is 0.083 rad from a state at 3.1 rad: output residuals are wrapped
    y = np.array([0.0, 0.0, -3.1, 0.0, 0.0])
    assert output_noise(model, xp, y)[2] == pytest.approx(2 * math.pi - 6.2)
    sp, sn, sy = ca.SX.sym("xp", 5), ca.SX.sym("xn", 5), ca.SX.sym("y", 5)
    f = ca.Function(
        "r", [sp, sn, sy], [ca.vertcat(*state_noise(model, sp, sn, 0.1, ca), *output_noise(model, sp, sy, ca))]
    )
    expected = np.array([*state_noise(model, xp, xn, 0.1), *output_noise(model, xp, y)], dtype=float)
    assert np.asarray(f(xp, xn, y)).ravel() == pytest.approx(expected)


def test_odometry_is_exact_on_a_line_and_second_order_on_a_circle() -> None:
    t = np.linspace(0.0, 10.0, 101)
    east, north, phi = integrate_odometry(t, np.full_like(t, 5.0), np.zeros_like(t), 1.0, 2.0, math.pi / 2)
    assert east[-1] == pytest.approx(51.0) and north[-1] == pytest.approx(2.0) and phi[-1] == math.pi / 2
    v, omega = 10.0, 0.3
    errors = []
    for n in (51, 101):
        t = np.linspace(0.0, 5.0, n)
        east, north, phi = integrate_odometry(t, np.full(n, v), np.full(n, omega))
        truth_e, truth_n = (v / omega) * (np.cos(-omega * t) - 1.0), -(v / omega) * np.sin(-omega * t)
        assert phi[-1] == pytest.approx(-omega * 5.0)
        errors.append(max(abs(east[-1] - truth_e[-1]), abs(north[-1] - truth_n[-1])))
    assert errors[1] < 0.3 * errors[0]  # halving the step quarters the error


# ---- the Kalman peers run this model ---------------------------------------------------------------------------


@pytest.mark.parametrize(("bias", "scale"), [(False, False), (True, False), (True, True)])
@pytest.mark.parametrize("dt", [0.02, -0.15])
def test_kalman_kinematics_are_su5(bias: bool, scale: bool, dt: float) -> None:
    from sumhe.baseline import kinematics as kin

    layout = kin.Layout(bias=bias, scale=scale)
    su5 = su_model("su5", bias, scale, "trapezoid")
    assert (layout.b, layout.k) == (su5.i_bias, su5.i_scale)
    rng = np.random.default_rng(4)
    x = rng.normal(size=layout.n) + np.r_[0.0, 0.0, 0.0, 12.0, 0.0, [0.0] * bias, [1.0] * scale]
    # the step is su5's transition at constant speed and yaw rate: the midpoint rule
    assert kin.step(x, dt) == pytest.approx(su5.transition(x, x, dt))
    mid = x[2] - 0.5 * dt * x[4]
    assert kin.step(x, dt)[:3] == pytest.approx(
        [x[0] + dt * x[3] * math.sin(mid), x[1] + dt * x[3] * math.cos(mid), x[2] - dt * x[4]]
    )
    stacked = np.column_stack([x, 2 * x])
    assert kin.step(stacked, dt)[:, 1] == pytest.approx(kin.step(2 * x, dt))
    # Jacobians: CasADi's, checked against central differences
    eps = 1e-6
    fd = np.column_stack([(kin.step(x + eps * e, dt) - kin.step(x - eps * e, dt)) / (2 * eps) for e in np.eye(len(x))])
    assert kin.step_jacobian(x, dt) == pytest.approx(fd, abs=1e-7)
    rows = (kin.CAN_SPEED, kin.CAN_YAW_RATE, kin.STANDSTILL)
    assert kin.can_model(x, rows, layout)[:2] == pytest.approx(su5.output(x)[-2:])
    fd = np.column_stack(
        [
            (kin.can_model(x + eps * e, rows, layout) - kin.can_model(x - eps * e, rows, layout)) / (2 * eps)
            for e in np.eye(len(x))
        ]
    )
    assert kin.can_jacobian(x, rows, layout) == pytest.approx(fd, abs=1e-7)
