"""The peers' tables (``[estimator.ekf]``, ``[estimator.ukf]``, ``[estimator.rts]``, ``[estimator.pf]``,
``[estimator.imm]``, ``[estimator.gtsam_fls]``, ``[estimator.mskf_em]``, ``[estimator.sr_upf]``) with their tuned
defaults.

The defaults come from ``sumhe bench tune`` (:mod:`sumhe.bench.tune`: a coordinate-wise grid search on training
drives, seeds 100-105 (100-102 for ``mskf-em``, ``sr-upf`` and ``gtsam-fls``), never the test seeds nor a real drive;
``docs/baselines.md``); each table's command, seeds and date are beside it. ``rts`` and ``ukf`` run the EKF's values.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields

from sumhe.settings.checks import at_least, non_negative, positive


@dataclass(frozen=True, slots=True)
class NoiseSettings:
    """Noise levels of a recursive filter, SI units; ``*_rw`` are random-walk densities (unit per sqrt(s)).

    Process: the position, azimuth, speed, yaw rate, bias, scale and gain states each take white noise of the given
    density (``Q = diag(density^2) dt``). Measurements: CAN speed and yaw rate sigmas (per CAN-rate update), the
    standstill pseudo-measurement ``omega = 0`` (0 turns it off), the GNSS position sigma as a multiple of the
    fix's own (:mod:`sumhe.frontend`), ``course_rad`` the filter's model error added to the course's sigma. Gate:
    the chi-square probability of the innovation gate (1 turns the gate off) and how long rejected fixes must
    agree before the filter re-acquires them. Prior: sigmas of speed, yaw rate and, where ``gain0`` > 0 and
    ``estimator.yaw_rate_gain``, of the CAN yaw rate's gain, which is then a state (0 here, set in the Kalman
    filters' tables: :data:`EKF_TUNED`; :meth:`sumhe.baseline.kinematics.Layout.from_settings`).
    """

    pos_rw: float = 0.05
    heading_rw: float = 0.002
    speed_rw: float = 1.0
    yaw_rate_rw: float = 0.3
    bias_rw: float = 5e-5
    scale_rw: float = 1e-5
    gain_rw: float = 1e-4
    can_speed_mps: float = 0.05
    can_yaw_rate_rps: float = 0.003
    standstill_rps: float = 0.001
    gps_scale: float = 1.0
    course_rad: float = 0.005
    gate_prob: float = 0.9999
    reacquire_s: float = 1.0
    speed0_mps: float = 1.0
    yaw_rate0_rps: float = 0.1
    gain0: float = 0.0

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
    gain0=0.075,
)
"""The EKF's tuned noise (also the RTS smoother's and the UKF's, and the IMM cells' start). ``gain0``: the CAN yaw
rate's gain a state, its prior sigma half the default ``sensors.can.yaw_rate_gain_max`` (as the bias's and the speed
scale's are half theirs), not searched."""
PF_TUNED = NoiseSettings(
    pos_rw=0.000390625,
    heading_rw=7.8125e-06,
    bias_rw=5e-05,
    scale_rw=0.00032,
    gps_scale=2.0,
)
UPF_TUNED = dataclasses.replace(PF_TUNED, pos_rw=0.00078125, bias_rw=2.5e-05)
"""The square-root unscented particle filter's noise, searched from ``pf``'s: ``sumhe bench tune search sr-upf
--sweeps 1 --seeds 100-102 --factors 0.5,2`` (training seeds, 2026-11-24; J 3.134 -> 2.094 m; the other four
stayed; ``docs/baselines.md``)."""
IMM_STRAIGHT_TUNED = dataclasses.replace(EKF_TUNED, heading_rw=0.0005)
IMM_TURN_TUNED = dataclasses.replace(EKF_TUNED, heading_rw=0.00025, yaw_rate_rw=0.0375)
"""The IMM's cells, searched from the EKF's values (``sumhe bench tune search imm``): both the EKF's model, the
curved one's yaw rate a 4x louder random walk."""
MSKF_TUNED = dataclasses.replace(
    EKF_TUNED,
    pos_rw=0.003125,
    heading_rw=0.0005,
    bias_rw=0.0001,
    scale_rw=2.5e-06,
    gps_scale=0.5,
    course_rad=0.00125,
)
"""The multi-stage filter's start values of its EM (``pos_rw``, ``heading_rw``, ``gps_scale``) and fixed noises,
searched from the EKF's: ``sumhe bench tune search mskf-em --sweeps 1 --seeds 100-102`` (training seeds, 2026-11-24;
J 2.245 -> 1.946 m; ``docs/baselines.md``)."""
GTSAM_TUNED = dataclasses.replace(
    EKF_TUNED,
    pos_rw=0.000390625,
    heading_rw=0.00025,
    can_yaw_rate_rps=0.006,
    bias_rw=5e-05,
    scale_rw=2e-05,
    gps_scale=4.0,
    course_rad=0.0025,
)
GTSAM_SOG_SCALE = 1.0
"""The fixed-lag smoother's noise and speed-over-ground sigma scale, searched from the EKF's values (its odometry is
the EKF's process model): ``sumhe bench tune search gtsam-fls --sweeps 1 --seeds 100-102 --factors 0.5,2`` (training
seeds, 2026-11-24; J 2.017 -> 1.834 m; ``can_speed_mps`` and ``sog_scale`` stayed; ``docs/baselines.md``)."""


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
    """``[estimator.imm]``: the straight and curved cells' noise (``[estimator.imm.straight]``,
    ``[estimator.imm.turn]``; measurement noise, gate and priors come from the straight one) and the mean time (s)
    the vehicle stays in each model: paper 002's transition matrix per 1 s, ``-1 / ln(0.9168)`` and
    ``-1 / ln(0.7672)``."""

    straight: NoiseSettings = field(default_factory=lambda: IMM_STRAIGHT_TUNED)
    turn: NoiseSettings = field(default_factory=lambda: IMM_TURN_TUNED)
    sojourn_straight_s: float = -1.0 / math.log(0.9168)
    sojourn_turn_s: float = -1.0 / math.log(0.7672)

    def __post_init__(self) -> None:
        positive(self, "sojourn_straight_s", "sojourn_turn_s")

    @property
    def sojourn_s(self) -> tuple[float, float]:
        return self.sojourn_straight_s, self.sojourn_turn_s


@dataclass(frozen=True, slots=True)
class GtsamSettings:
    """``[estimator.gtsam_fls]``: GTSAM's incremental fixed-lag smoother (iSAM2) over the CAN odometry and GNSS.

    ``noise``: model error densities of the odometry (``pos_rw``, ``heading_rw``), the CAN sigmas per sample, the
    bias and scale random walks, ``gps_scale``, ``course_rad``, gate, priors (``[estimator.gtsam_fls.noise]``);
    ``sog_scale``: the GNSS speed over ground's sigma as a multiple of the front-end's (``gps_scale``'s twin for the
    speed factor); ``lag_s``: the smoother's lag (s; nodes older than this behind the newest are marginalised);
    ``relinearize_threshold`` and ``relinearize_skip``: iSAM2's (a variable is relinearised when its update exceeds
    the threshold, checked every ``relinearize_skip`` updates; GTSAM's defaults)."""

    noise: NoiseSettings = field(default_factory=lambda: GTSAM_TUNED)
    sog_scale: float = GTSAM_SOG_SCALE
    lag_s: float = 5.0
    relinearize_threshold: float = 0.1
    relinearize_skip: int = 10

    def __post_init__(self) -> None:
        positive(self, "sog_scale", "lag_s", "relinearize_threshold")
        at_least(self, 1, "relinearize_skip")


@dataclass(frozen=True, slots=True)
class MskfSettings:
    """``[estimator.mskf_em]``: paper 002's multi-stage Kalman filter with on-line EM (:mod:`sumhe.baseline.mskf_em`).

    ``noise`` (``[estimator.mskf_em.noise]``): the start values of the re-estimated scales (``heading_rw``,
    ``pos_rw``, ``gps_scale``) and the fixed noises (CAN, bias, scale), gate, priors; ``block_s``: the EM's block
    (s; 002: 2-6 s); ``r_window_s``: the GNSS noise is re-estimated over the blocks of the last this many seconds
    (002: 30-40 s); ``em_iterations``: EM iterations per block at most; ``scale_limit``: the re-estimated
    covariances stay within this factor of their start values."""

    noise: NoiseSettings = field(default_factory=lambda: MSKF_TUNED)
    block_s: float = 5.0
    r_window_s: float = 30.0
    em_iterations: int = 3
    scale_limit: float = 100.0

    def __post_init__(self) -> None:
        positive(self, "block_s", "r_window_s")
        at_least(self, 1, "em_iterations")
        at_least(self, 1.0, "scale_limit")


@dataclass(frozen=True, slots=True)
class UpfSettings:
    """``[estimator.sr_upf]``: paper 004's square-root unscented particle filter (:mod:`sumhe.baseline.sr_upf`).

    ``noise`` (``[estimator.sr_upf.noise]``): its tuned noise (searched from ``pf``'s) plus the CAN sigmas as the
    inputs' noise; ``particles`` and ``seed``; the GNSS noise's sparse kernel density: fitted on the normalised
    innovations of the last ``kde_samples`` fixes, once ``kde_min_samples`` exist, again every ``kde_refit`` fixes,
    LASSO regularisation ``kde_lasso`` (times the largest density) and weights below ``kde_threshold`` times the
    largest dropped (004: 0.1 and 0.2)."""

    noise: NoiseSettings = field(default_factory=lambda: UPF_TUNED)
    particles: int = 100
    seed: int = 0
    kde_samples: int = 200
    kde_min_samples: int = 30
    kde_refit: int = 50
    kde_lasso: float = 0.1
    kde_threshold: float = 0.2

    def __post_init__(self) -> None:
        at_least(self, 10, "particles")
        at_least(self, 2, "kde_min_samples")
        at_least(self, 1, "kde_refit")
        if self.kde_samples < self.kde_min_samples:
            raise ValueError(
                f"kde_samples: must be >= kde_min_samples ({self.kde_min_samples}), got {self.kde_samples!r}"
            )
        non_negative(self, "kde_lasso")
        if not 0 <= self.kde_threshold < 1:
            raise ValueError(f"kde_threshold: must be within [0, 1), got {self.kde_threshold!r}")
