"""The simulated vehicle: a kinematic bicycle model driving a route, exact at any time.

The path is integrated once on a fine grid of distance (``DS_M``) from the route's curvature, which is linear
in s within each piece, so the azimuth is exact (quadratic in s). The speed profile is the largest one within
the road limit, the lateral-acceleration limit (v^2 |k| <= a_lat), the steering-rate limit and the
acceleration/braking limits (forward-backward pass), zero at stops, at the start and at the end. Between two
grid points the acceleration is constant, so s(t) and v(t) are exact quadratics and linears in time.
The reference point is the rear-axle centre: its velocity is along the azimuth, yaw rate = v * k =
v * tan(steering) / wheelbase. Azimuth clockwise from north, yaw rate anticlockwise positive, east = x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sumhe.sim.routes import Route

WHEELBASE_M = 2.7
TRACK_M = 1.55
STEERING_RATIO = 15.0
DS_M = 0.05
"""Grid step of the path integration (m)."""

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Motion:
    """The vehicle's state at times ``t`` (s from the start): equal-length arrays in SI units."""

    t: FloatArray
    s: FloatArray
    east: FloatArray
    north: FloatArray
    azimuth: FloatArray
    """rad, clockwise from north, unwrapped."""
    speed: FloatArray
    accel: FloatArray
    yaw_rate: FloatArray
    """rad/s, anticlockwise positive."""
    curvature: FloatArray
    steering: FloatArray
    """Road-wheel angle (rad, left positive)."""
    steering_rate: FloatArray

    @property
    def lat_accel(self) -> FloatArray:
        """Lateral acceleration (m/s^2, positive to the left)."""
        return self.speed * self.yaw_rate


class Trajectory:
    """A route driven once: the path on a distance grid and the speed profile as time nodes."""

    def __init__(self, route: Route) -> None:
        lengths = np.array([p.length_m for p in route.pieces])
        self._k0 = np.array([p.k0 for p in route.pieces])
        self._k1 = np.array([p.k1 for p in route.pieces])
        self._len = lengths
        self._start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        self._phi0 = route.azimuth0_rad - np.concatenate([[0.0], np.cumsum((self._k0 + self._k1) / 2 * lengths)[:-1]])
        self.length_m = float(lengths.sum())
        n = max(2, math.ceil(self.length_m / DS_M) + 1)
        self._s = np.linspace(0.0, self.length_m, n)
        self._ds = self._s[1] - self._s[0]
        phi_mid = self._curve(self._s[:-1] + self._ds / 2)[0]
        self._east = np.concatenate([[0.0], np.cumsum(self._ds * np.sin(phi_mid))])
        self._north = np.concatenate([[0.0], np.cumsum(self._ds * np.cos(phi_mid))])
        v = self._speed_profile(route)
        dwell = np.zeros(n)
        for s_stop, d in route.stops:
            dwell[min(round(s_stop / self._ds), n - 1)] += d
        dt = 2.0 * self._ds / (v[:-1] + v[1:])
        arrive = np.concatenate([[0.0], np.cumsum(dt + dwell[:-1])])
        idx = np.repeat(np.arange(n), 1 + (dwell > 0))
        first = np.concatenate([[True], idx[1:] != idx[:-1]])
        self._t = np.where(first, arrive[idx], arrive[idx] + dwell[idx])
        self._node_s = self._s[idx]
        self._node_v = np.where(first, v[idx], 0.0)
        self._node_a = np.diff(self._node_v) / np.diff(self._t)
        self.end_time_s = float(self._t[-1])

    def _piece(self, s: FloatArray) -> NDArray[np.intp]:
        return np.clip(np.searchsorted(self._start, s, side="right") - 1, 0, len(self._start) - 1)

    def _curve(self, s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Azimuth (rad), curvature (1/m) and its derivative along s (1/m^2) at distances ``s``."""
        p = self._piece(s)
        u = np.clip(s - self._start[p], 0.0, self._len[p])
        slope = (self._k1[p] - self._k0[p]) / self._len[p]
        phi = self._phi0[p] - (self._k0[p] * u + slope * u * u / 2)
        return phi, self._k0[p] + slope * u, slope

    def _speed_profile(self, route: Route) -> FloatArray:
        lim = route.limits
        _, k, slope = self._curve(self._s)
        road = np.array([p.v_max_mps for p in route.pieces])[self._piece(self._s)]
        with np.errstate(divide="ignore"):
            lateral = np.sqrt(lim.lat_accel_mps2 / np.abs(k))
            steer = lim.steer_rate_rps * (1.0 + (k * WHEELBASE_M) ** 2) / (WHEELBASE_M * np.abs(slope))
        vmax2 = np.minimum.reduce([road, lateral, steer, np.full_like(road, lim.speed_mps)]) ** 2
        for s_stop, _ in route.stops:
            vmax2[min(round(s_stop / self._ds), len(vmax2) - 1)] = 0.0
        vmax2[[0, -1]] = 0.0
        s = self._s
        forward = 2 * lim.accel_mps2 * s + np.minimum.accumulate(vmax2 - 2 * lim.accel_mps2 * s)
        backward = np.minimum.accumulate((forward + 2 * lim.brake_mps2 * s)[::-1])[::-1] - 2 * lim.brake_mps2 * s
        return np.sqrt(np.clip(backward, 0.0, None))

    def time_at(self, s: ArrayLike) -> FloatArray:
        """When the vehicle first reaches distances ``s`` (m along the path), s from the start."""
        return self._t[np.searchsorted(self._node_s, np.asarray(s, dtype=float), side="left")]

    def at(self, t: ArrayLike) -> Motion:
        """The exact state at times ``t`` (s from the start; before the start and after the end at rest)."""
        t = np.asarray(t, dtype=float)
        k = np.clip(np.searchsorted(self._t, t, side="right") - 1, 0, len(self._t) - 2)
        span = self._t[k + 1] - self._t[k]
        tau = np.clip(t - self._t[k], 0.0, span)
        a = self._node_a[k]
        s = np.minimum(self._node_s[k] + self._node_v[k] * tau + a * tau * tau / 2, self._node_s[k + 1])
        v = np.maximum(self._node_v[k] + a * tau, 0.0)
        accel = np.where((t >= self._t[0]) & (t < self._t[-1]), a, 0.0)
        phi, kappa, slope = self._curve(s)
        i = np.clip(((s - self._s[0]) / self._ds).astype(np.intp), 0, len(self._s) - 2)
        rest = s - self._s[i]
        phi_mid = self._curve((self._s[i] + s) / 2)[0]
        steering = np.arctan(kappa * WHEELBASE_M)
        return Motion(
            t=t,
            s=s,
            east=self._east[i] + rest * np.sin(phi_mid),
            north=self._north[i] + rest * np.cos(phi_mid),
            azimuth=phi,
            speed=v,
            accel=accel,
            yaw_rate=v * kappa,
            curvature=kappa,
            steering=steering,
            steering_rate=WHEELBASE_M * slope * v / (1.0 + (kappa * WHEELBASE_M) ** 2),
        )


SLIP_STEP_S = 0.01
"""Half-step of the central difference that gives the sideslip's rate of change."""


@dataclass(frozen=True, eq=False)
class Body:
    """The car body over a trajectory: its heading differs from the direction of motion of the reference point
    by the sideslip ``thrust_rad + slip_rad_per_mps2 * lateral acceleration`` (positive = nose to the left of the
    motion, into a left turn), as a real rear axle's tyres slip under lateral load and a misaligned axle crabs.

    A yaw-rate sensor sees the body's rate: the path's yaw rate plus the sideslip's rate. With both parameters
    zero the body is the kinematic bicycle exactly (heading = azimuth).
    """

    trajectory: Trajectory
    thrust_rad: float = 0.0
    slip_rad_per_mps2: float = 0.0

    def sideslip(self, m: Motion) -> FloatArray:
        """Direction of motion minus body heading (rad, azimuth sense) at the states ``m``."""
        return self.thrust_rad + self.slip_rad_per_mps2 * m.lat_accel

    def heading(self, m: Motion) -> FloatArray:
        """Body heading (rad, clockwise from north, unwrapped) at the states ``m``."""
        return m.azimuth - self.sideslip(m)

    def yaw_rate(self, m: Motion) -> FloatArray:
        """Body yaw rate (rad/s, anticlockwise positive) at the states ``m``: path yaw rate + d(sideslip)/dt."""
        if self.slip_rad_per_mps2 == 0.0:
            return m.yaw_rate
        ahead = self.trajectory.at(m.t + SLIP_STEP_S)
        behind = self.trajectory.at(m.t - SLIP_STEP_S)
        return m.yaw_rate + (self.sideslip(ahead) - self.sideslip(behind)) / (2.0 * SLIP_STEP_S)

    def point(self, m: Motion, forward_m: float, left_m: float) -> tuple[FloatArray, ...]:
        """East, north (m) and velocity east, north (m/s) of the body point ``forward_m`` ahead of and ``left_m``
        left of the reference point: position + R(heading) offset; velocity + body yaw rate x offset."""
        psi = self.heading(m)
        fwd = (np.sin(psi), np.cos(psi))
        left = (-np.cos(psi), np.sin(psi))
        omega = self.yaw_rate(m)
        east = m.east + forward_m * fwd[0] + left_m * left[0]
        north = m.north + forward_m * fwd[1] + left_m * left[1]
        v_east = m.speed * np.sin(m.azimuth) + omega * (forward_m * left[0] - left_m * fwd[0])
        v_north = m.speed * np.cos(m.azimuth) + omega * (forward_m * left[1] - left_m * fwd[1])
        return east, north, v_east, v_north
