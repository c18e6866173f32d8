"""Routes of the simulated drives: curvature profiles along the path, road speed limits and stops.

A route is a chain of pieces along the distance travelled s, each with a curvature varying linearly from
``k0`` to ``k1`` (1/m, positive = left): straights, clothoid transitions and arcs. Features (bends, a
roundabout, lane changes, stop-and-go, hairpins ...) are built from such pieces; each scenario draws its
features from the seed until the route certainly lasts the requested duration.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

KMH = 1.0 / 3.6
LANE_WIDTH_M = 3.5


@dataclass(frozen=True, slots=True)
class Limits:
    """Driving limits of a scenario (the speed profile never exceeds them)."""

    speed_mps: float
    accel_mps2: float
    brake_mps2: float
    lat_accel_mps2: float
    steer_rate_rps: float
    """Road-wheel steering-angle rate."""
    lat_jerk_mps3: float
    """Design rate of change of the lateral acceleration in curve transitions (clothoid length)."""


@dataclass(frozen=True, slots=True)
class Piece:
    """``length_m`` of path whose curvature goes linearly from ``k0`` to ``k1`` (1/m); road limit ``v_max_mps``."""

    length_m: float
    k0: float
    k1: float
    v_max_mps: float


@dataclass(frozen=True, slots=True)
class Route:
    """A scenario's path: pieces, stops (distance along the path, dwell s), start azimuth and limits."""

    pieces: tuple[Piece, ...]
    stops: tuple[tuple[float, float], ...]
    azimuth0_rad: float
    limits: Limits
    features: tuple[tuple[str, float], ...]
    """(name, distance along the path where it starts), for labels."""

    @property
    def length_m(self) -> float:
        return sum(p.length_m for p in self.pieces)

    def min_time_s(self) -> float:
        """A lower bound of the time needed to drive the route (road limits, dwell times included)."""
        return sum(p.length_m / p.v_max_mps for p in self.pieces) + sum(d for _, d in self.stops)


@dataclass
class _Builder:
    """Appends pieces to a route; transition lengths keep within the steering-rate limit at the road speed."""

    limits: Limits
    wheelbase_m: float
    pieces: list[Piece] = field(default_factory=list)
    stops: list[tuple[float, float]] = field(default_factory=list)
    features: list[tuple[str, float]] = field(default_factory=list)
    s: float = 0.0

    def add(self, length: float, k0: float, k1: float, v: float) -> None:
        if length > 1e-6:
            self.pieces.append(Piece(length, k0, k1, min(v, self.limits.speed_mps)))
            self.s += length

    def straight(self, length: float, v: float) -> None:
        self.add(length, 0.0, 0.0, v)

    def arc(self, radius: float, angle: float, v: float) -> None:
        """Turn by ``angle`` (rad, positive = left) on a circle of ``radius`` with clothoid entry and exit."""
        k = math.copysign(1.0 / radius, angle)
        v_turn = min(v, math.sqrt(self.limits.lat_accel_mps2 * radius))
        lim = self.limits
        ramp = max(
            abs(k) * v_turn * self.wheelbase_m / (0.5 * lim.steer_rate_rps), v_turn**3 * abs(k) / lim.lat_jerk_mps3
        )
        ramp = min(ramp, abs(angle) * radius / 2)
        self.add(ramp, 0.0, k, v)
        self.add(abs(angle) * radius - ramp, k, k, v)
        self.add(ramp, k, 0.0, v)

    def lane_change(self, width: float, length: float, v: float) -> None:
        """Move ``width`` (m, positive = left) sideways over ``length``: a triangle wave of curvature."""
        k = 8.0 * width / length**2
        self.add(length / 4, 0.0, k, v)
        self.add(length / 2, k, -k, v)
        self.add(length / 4, -k, 0.0, v)

    def feature(self, name: str) -> None:
        self.features.append((name, self.s))

    def stop(self, dwell_s: float) -> None:
        self.stops.append((self.s, dwell_s))

    def route(self, azimuth0: float) -> Route:
        return Route(tuple(self.pieces), tuple(self.stops), azimuth0, self.limits, tuple(self.features))


Feature = Callable[[_Builder, np.random.Generator], None]


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


# --- urban -------------------------------------------------------------------------------------------------


def _urban_straight(b: _Builder, rng: np.random.Generator) -> None:
    b.straight(rng.uniform(60.0, 250.0), (50 * KMH, 50 * KMH, 60 * KMH)[rng.integers(3)])


def _intersection_turn(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("intersection turn")
    b.arc(rng.uniform(9.0, 20.0), _sign(rng) * math.radians(rng.uniform(80.0, 100.0)), 50 * KMH)


def _gentle_bend(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("bend")
    b.arc(rng.uniform(50.0, 200.0), _sign(rng) * math.radians(rng.uniform(15.0, 60.0)), 50 * KMH)


def _roundabout(b: _Builder, rng: np.random.Generator) -> None:
    """Right-hand traffic: deflect right on entry, circulate anticlockwise, deflect right on exit."""
    b.feature("roundabout")
    exit_turn = math.radians(float(rng.choice([0.0, 90.0, 180.0])))
    deflect = math.radians(35.0)
    b.straight(20.0, 30 * KMH)
    b.arc(25.0, -deflect, 30 * KMH)
    b.arc(rng.uniform(12.0, 20.0), exit_turn + 2 * deflect, 30 * KMH)
    b.arc(25.0, -deflect, 40 * KMH)
    b.straight(20.0, 40 * KMH)


def _traffic_light(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("stop")
    b.straight(rng.uniform(40.0, 80.0), 50 * KMH)
    b.stop(rng.uniform(5.0, 25.0))


def _stop_and_go(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("stop-and-go")
    for _ in range(rng.integers(3, 6)):
        b.straight(rng.uniform(4.0, 20.0), rng.uniform(10.0, 20.0) * KMH)
        b.stop(rng.uniform(1.0, 5.0))


def _urban_lane_change(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("lane change")
    b.lane_change(_sign(rng) * LANE_WIDTH_M, rng.uniform(40.0, 70.0), 50 * KMH)


URBAN_FEATURES: tuple[Feature, ...] = (
    _roundabout,
    _traffic_light,
    _intersection_turn,
    _gentle_bend,
    _urban_lane_change,
    _stop_and_go,
    _intersection_turn,
    _gentle_bend,
)

# --- highway -----------------------------------------------------------------------------------------------


def _on_ramp(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("on-ramp")
    b.straight(30.0, 40 * KMH)
    b.arc(rng.uniform(50.0, 80.0), _sign(rng) * math.radians(rng.uniform(60.0, 100.0)), 60 * KMH)
    b.straight(400.0, 120 * KMH)


def _highway_straight(b: _Builder, rng: np.random.Generator) -> None:
    b.straight(rng.uniform(400.0, 1500.0), rng.uniform(110.0, 130.0) * KMH)


def _highway_bend(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("bend")
    b.arc(rng.uniform(500.0, 1500.0), _sign(rng) * math.radians(rng.uniform(5.0, 25.0)), 130 * KMH)


def _highway_lane_change(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("lane change")
    v = rng.uniform(100.0, 130.0) * KMH
    b.lane_change(_sign(rng) * LANE_WIDTH_M, v * rng.uniform(3.0, 5.0), v)


def _slowdown(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("slowdown")
    b.straight(rng.uniform(200.0, 500.0), rng.uniform(40.0, 70.0) * KMH)


def _jam(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("stop-and-go")
    for _ in range(rng.integers(2, 5)):
        b.straight(rng.uniform(10.0, 40.0), rng.uniform(15.0, 30.0) * KMH)
        b.stop(rng.uniform(2.0, 8.0))


HIGHWAY_FEATURES: tuple[Feature, ...] = (
    _highway_straight,
    _highway_lane_change,
    _highway_bend,
    _highway_straight,
    _highway_lane_change,
    _slowdown,
    _highway_bend,
    _jam,
)

# --- off-road training course (paper 000's hardest case) -------------------------------------------------------


def _offroad_straight(b: _Builder, rng: np.random.Generator) -> None:
    b.straight(rng.uniform(15.0, 60.0), rng.uniform(35.0, 60.0) * KMH)


def _hairpin(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("hairpin")
    b.arc(rng.uniform(5.0, 8.0), _sign(rng) * math.radians(rng.uniform(150.0, 200.0)), 50 * KMH)


def _sharp_turn(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("sharp turn")
    b.arc(rng.uniform(5.0, 10.0), _sign(rng) * math.radians(rng.uniform(70.0, 120.0)), 50 * KMH)


def _slalom(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("slalom")
    side = _sign(rng)
    for _ in range(rng.integers(3, 7)):
        b.arc(rng.uniform(8.0, 14.0), side * math.radians(rng.uniform(30.0, 60.0)), 50 * KMH)
        b.straight(rng.uniform(2.0, 5.0), 50 * KMH)
        side = -side


def _loop(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("loop")
    b.arc(rng.uniform(6.0, 10.0), _sign(rng) * math.radians(rng.uniform(270.0, 360.0)), 50 * KMH)


def _s_curve(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("s-curve")
    side = _sign(rng)
    b.arc(rng.uniform(7.0, 12.0), side * math.radians(rng.uniform(60.0, 90.0)), 50 * KMH)
    b.arc(rng.uniform(7.0, 12.0), -side * math.radians(rng.uniform(60.0, 90.0)), 50 * KMH)


def _offroad_stop(b: _Builder, rng: np.random.Generator) -> None:
    b.feature("stop")
    b.straight(rng.uniform(10.0, 30.0), 40 * KMH)
    b.stop(rng.uniform(2.0, 5.0))


OFFROAD_FEATURES: tuple[Feature, ...] = (
    _hairpin,
    _sharp_turn,
    _slalom,
    _loop,
    _s_curve,
    _sharp_turn,
    _offroad_stop,
)


@dataclass(frozen=True, slots=True)
class Scenario:
    """How a scenario drives: limits, an optional opening feature, the features shuffled into each block and
    the straight put between two features."""

    limits: Limits
    features: tuple[Feature, ...]
    between: Feature
    opening: Feature | None = None


SCENARIOS: dict[str, Scenario] = {
    "urban": Scenario(
        Limits(
            speed_mps=70 * KMH,
            accel_mps2=2.0,
            brake_mps2=3.0,
            lat_accel_mps2=3.0,
            steer_rate_rps=0.35,
            lat_jerk_mps3=1.5,
        ),
        URBAN_FEATURES,
        _urban_straight,
    ),
    "highway": Scenario(
        Limits(
            speed_mps=40.0, accel_mps2=1.5, brake_mps2=3.0, lat_accel_mps2=2.5, steer_rate_rps=0.2, lat_jerk_mps3=0.6
        ),
        HIGHWAY_FEATURES,
        _highway_straight,
        opening=_on_ramp,
    ),
    "offroad": Scenario(
        Limits(
            speed_mps=60 * KMH,
            accel_mps2=3.0,
            brake_mps2=5.0,
            lat_accel_mps2=7.0,
            steer_rate_rps=0.6,
            lat_jerk_mps3=4.0,
        ),
        OFFROAD_FEATURES,
        _offroad_straight,
    ),
}


def build_route(scenario: str, duration_s: float, rng: np.random.Generator, wheelbase_m: float) -> Route:
    """Draw a route of ``scenario`` that takes at least ``duration_s`` to drive.

    It starts and ends at standstill; features come in blocks, each block a shuffle of the scenario's
    features separated by straights, so every feature appears once per block.
    """
    spec = SCENARIOS[scenario]
    b = _Builder(spec.limits, wheelbase_m)
    b.stop(float(rng.uniform(3.0, 6.0)))
    b.straight(20.0, 30 * KMH)
    if spec.opening is not None:
        spec.opening(b, rng)
    while b.route(0.0).min_time_s() < duration_s + 10.0:
        for i in rng.permutation(len(spec.features)):
            spec.between(b, rng)
            spec.features[i](b, rng)
    b.straight(30.0, 30 * KMH)
    return b.route(float(rng.uniform(0.0, 2.0 * math.pi)))
