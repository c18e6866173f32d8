"""The peers' tables (``[estimator.ekf]``, ``[estimator.ukf]``, ``[estimator.rts]``, ``[estimator.pf]``,
``[estimator.imm]``) with their tuned defaults.

The defaults come from ``sumhe bench tune`` (:mod:`sumhe.bench.tune`: a coordinate-wise grid search on training
drives, seeds 100-105, never the test seeds; ``docs/baselines.md``). ``rts`` and ``ukf`` run the EKF's values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from sumhe.settings.checks import at_least, positive


@dataclass(frozen=True, slots=True)
class NoiseSettings:
    """Noise levels of a recursive filter, SI units; ``*_rw`` are random-walk densities (unit per sqrt(s)).

    Process: the position, azimuth, speed, yaw rate, bias and scale states each take white noise of the given
    density (``Q = diag(density^2) dt``). Measurements: CAN speed and yaw rate sigmas (per CAN-rate update), the
    standstill pseudo-measurement ``omega = 0`` (0 turns it off), the GNSS position sigma as a multiple of the
    fix's own (:mod:`sumhe.frontend`), ``course_rad`` the filter's model error added to the course's sigma. Gate:
    the chi-square probability of the innovation gate (1 turns the gate off) and how long rejected fixes must
    agree before the filter re-acquires them. Prior: sigmas of speed and yaw rate at the first fix.
    """

    pos_rw: float = 0.05
    heading_rw: float = 0.002
    speed_rw: float = 1.0
    yaw_rate_rw: float = 0.3
    bias_rw: float = 5e-5
    scale_rw: float = 1e-5
    can_speed_mps: float = 0.05
    can_yaw_rate_rps: float = 0.003
    standstill_rps: float = 0.001
    gps_scale: float = 1.0
    course_rad: float = 0.005
    gate_prob: float = 0.9999
    reacquire_s: float = 1.0
    speed0_mps: float = 1.0
    yaw_rate0_rps: float = 0.1

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{f.name}: must be a finite number >= 0, got {value!r}")
        positive(self, "can_speed_mps", "can_yaw_rate_rps", "gps_scale")
        if not 0 < self.gate_prob <= 1:
            raise ValueError(f"gate_prob: must be within (0, 1], got {self.gate_prob!r}")


EKF_TUNED = NoiseSettings(
    pos_rw=0.00078125,
    heading_rw=0.000125,
    speed_rw=0.5,
    yaw_rate_rw=0.009375,
    bias_rw=2.5e-05,
    gps_scale=2.0,
)
"""The EKF's tuned noise (also the RTS smoother's and the UKF's)."""
PF_TUNED = NoiseSettings(
    pos_rw=0.000390625,
    heading_rw=7.8125e-06,
    bias_rw=5e-05,
    scale_rw=0.00032,
    gps_scale=2.0,
)
IMM_STRAIGHT_TUNED = NoiseSettings(
    pos_rw=0.00078125,
    heading_rw=0.000125,
    speed_rw=0.5,
    yaw_rate_rw=0.0046875,
    bias_rw=2.5e-05,
    gps_scale=2.0,
)
IMM_TURN_TUNED = NoiseSettings(
    pos_rw=0.003125,
    heading_rw=0.000125,
    speed_rw=0.5,
    yaw_rate_rw=0.0375,
    bias_rw=2.5e-05,
    gps_scale=2.0,
)


@dataclass(frozen=True, slots=True)
class ParticleSettings:
    """``[estimator.pf]``: the particle filter's noise (``[estimator.pf.noise]``), particles and seed."""

    noise: NoiseSettings = field(default_factory=lambda: PF_TUNED)
    particles: int = 500
    seed: int = 0

    def __post_init__(self) -> None:
        at_least(self, 10, "particles")


@dataclass(frozen=True, slots=True)
class ImmSettings:
    """``[estimator.imm]``: the straight and turning cells' noise (``[estimator.imm.straight]``,
    ``[estimator.imm.turn]``; measurement noise, gate and priors come from the straight one) and the mean time
    (s) the vehicle stays in each model."""

    straight: NoiseSettings = field(default_factory=lambda: IMM_STRAIGHT_TUNED)
    turn: NoiseSettings = field(default_factory=lambda: IMM_TURN_TUNED)
    sojourn_straight_s: float = 10.0
    sojourn_turn_s: float = 0.75

    def __post_init__(self) -> None:
        positive(self, "sojourn_straight_s", "sojourn_turn_s")

    @property
    def sojourn_s(self) -> tuple[float, float]:
        return self.sojourn_straight_s, self.sojourn_turn_s
