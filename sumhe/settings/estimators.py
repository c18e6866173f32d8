"""The ``[estimator]`` table: which estimator runs with which model, and one table per estimator family.

``[estimator.mhe]``: the moving-horizon estimator (``docs/mhe.md``); ``[estimator.batch]``: the batch SU estimator
and ``su-batch`` (``docs/formulation.md``); ``[estimator.ekf]`` ... : the peers (:mod:`sumhe.settings.peers`).
:class:`EstimationSettings` bundles what an estimator reads: this table, ``[vehicle]`` and ``[sensors]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sumhe.settings.checks import at_least, non_negative, one_of, positive
from sumhe.settings.peers import (
    EKF_TUNED,
    GtsamSettings,
    ImmSettings,
    MskfSettings,
    NoiseSettings,
    ParticleSettings,
    UpfSettings,
)
from sumhe.settings.sensors import CanModel, GnssModel, SensorSettings, VehicleSettings

OBJECTIVES = ("linear", "log", "caps")
CENTRES = ("lsq", "none")
MODELS = ("su5", "su7")
DISCRETISATIONS = ("trapezoid", "euler")
MHE_SOLVERS = ("sqp", "ipopt", "fatrop")


@dataclass(frozen=True, slots=True)
class MheSettings:
    """``[estimator.mhe]``: solver, window policy (steps: N, N_B, N_A, N_max, ...), QP, the CAN and installation
    states' drift (``theta_drift``: of their ranges per square-root minute; ``docs/mhe.md``, "Arrival cost"), gate,
    retries, the output bounds learned from the residuals (``learn_bounds``: over the last ``bound_history`` steps,
    times ``bound_margin``, at most ``bound_max_factor`` times the allowances; ``docs/mhe.md``). ``nlp_max_iter``
    limits the ``ipopt``/``fatrop`` solvers. ``rest_bias_rps``: how far (one sigma, rad/s) the CAN yaw rate's bias
    at rest may differ from its bias in motion, the floor of a stop's weight as a measurement of the bias
    (:mod:`sumhe.estimator.mhe.standstill`; a large value leaves stops unused). ``fix_correlation_s``: GNSS fixes
    closer together than this (s) are not independent measurements (a receiver's own filter, its slowly varying
    errors): at a shorter GNSS period each fix's allowances grow by the square root of the fixes within it, so a second
    of fixes weighs as one fix (0: every fix as independent; :func:`sumhe.estimator.mhe.outputs.fix_outputs`)."""

    solver: str = "sqp"
    steps: int = 50
    steps_before: int = 20
    steps_after: int = 10
    max_steps: int = 300
    shrink_steps: int = 2
    max_merge: int = 4
    bucket_steps: int = 25
    sqp_iterations: int = 3
    qp_max_iter: int = 200
    qp_tol: float = 1e-5
    nlp_max_iter: int = 300
    trapezoid_q: float = 0.1
    theta_drift: float = 0.05
    rest_bias_rps: float = 0.001
    fix_correlation_s: float = 1.0
    gate_m: float = 2.0
    gate_drift: float = 0.05
    max_retries: int = 2
    learn_bounds: bool = True
    bound_history: int = 3000
    bound_margin: float = 1.1
    bound_max_factor: float = 20.0

    def __post_init__(self) -> None:
        one_of(self, "solver", MHE_SOLVERS)
        at_least(self, 1, "max_merge", "bucket_steps", "sqp_iterations", "qp_max_iter", "nlp_max_iter", "bound_history")
        at_least(self, 1.0, "bound_margin", "bound_max_factor")
        at_least(self, 2, "steps")
        at_least(self, 0, "steps_before", "steps_after", "shrink_steps", "max_retries", "fix_correlation_s")
        if self.max_steps < self.steps:
            raise ValueError(f"max_steps: must be >= steps ({self.steps}), got {self.max_steps!r}")
        if self.steps_before >= self.steps:
            raise ValueError(f"steps_before: must be below steps ({self.steps}), got {self.steps_before!r}")
        positive(self, "qp_tol", "trapezoid_q", "theta_drift", "rest_bias_rps", "gate_m", "gate_drift")


@dataclass(frozen=True, slots=True)
class BatchSettings:
    """``[estimator.batch]``: the batch formulation (stage-1 ``objective``, reported ``centre`` and its margin,
    ``derived_floors``), IPOPT, the LP start point, and ``su-batch``'s windows over a drive (s)."""

    objective: str = "linear"
    centre: str = "lsq"
    centre_margin: float = 0.1
    derived_floors: bool = True
    ipopt_max_iter: int = 300
    ipopt_tol: float = 1e-8
    lp_regularisation: float = 1e-2
    max_widenings: int = 8
    window_s: float = 30.0
    overlap_s: float = 6.0

    def __post_init__(self) -> None:
        one_of(self, "objective", OBJECTIVES)
        one_of(self, "centre", CENTRES)
        positive(self, "ipopt_max_iter", "ipopt_tol", "lp_regularisation", "window_s")
        non_negative(self, "centre_margin")
        at_least(self, 0, "max_widenings")
        if not 0.0 < self.overlap_s < self.window_s:
            raise ValueError(f"overlap_s: must be within (0, window_s), got {self.overlap_s!r}")


@dataclass(frozen=True, slots=True)
class EstimatorSettings:
    """``[estimator]``: the estimator (``name``), the SU model (``model``, the optional states: CAN yaw-rate bias,
    speed scale and yaw-rate gain, the receiver's azimuth offset, the antenna's forward lever arm; the
    discretisation), what the SU estimators share (error allowances of ``r_cap_sigmas`` sigmas; bounds widened by
    ``widen_factor`` while a problem is infeasible, 001 algorithm 3.3), what the recursive peers share (the span of
    their stored history, ``late_fix_history_s`` seconds: a fix older than their state within it is put in at its
    own time and the filter re-run, :mod:`sumhe.baseline.stream`; 0 turns it off) and one table per estimator
    family. ``can_output_hz``: the CAN-rate estimates come at every CAN speed sample and, where the speed samples
    are sparser than that, also at the yaw-rate samples at least ``1 / can_output_hz`` after the previous estimate
    (an OBD-II speed polled at 2 Hz beside a 100 Hz yaw rate; 0: at the speed samples only)."""

    name: str = "mhe"
    model: str = "su5"
    yaw_rate_bias: bool = True
    speed_scale: bool = True
    yaw_rate_gain: bool = True
    azimuth_offset: bool = True
    antenna_offset: bool = True
    discretisation: str = "trapezoid"
    r_cap_sigmas: float = 4.0
    widen_factor: float = 2.0
    late_fix_history_s: float = 1.5
    can_output_hz: float = 0.0
    mhe: MheSettings = field(default_factory=MheSettings)
    batch: BatchSettings = field(default_factory=BatchSettings)
    ekf: NoiseSettings = field(default_factory=lambda: EKF_TUNED)
    ukf: NoiseSettings = field(default_factory=lambda: EKF_TUNED)
    rts: NoiseSettings = field(default_factory=lambda: EKF_TUNED)
    pf: ParticleSettings = field(default_factory=ParticleSettings)
    imm: ImmSettings = field(default_factory=ImmSettings)
    gtsam_fls: GtsamSettings = field(default_factory=GtsamSettings)
    mskf_em: MskfSettings = field(default_factory=MskfSettings)
    sr_upf: UpfSettings = field(default_factory=UpfSettings)

    def __post_init__(self) -> None:
        one_of(self, "model", MODELS)
        one_of(self, "discretisation", DISCRETISATIONS)
        positive(self, "r_cap_sigmas")
        non_negative(self, "late_fix_history_s", "can_output_hz")
        if not self.widen_factor > 1:
            raise ValueError(f"widen_factor: must be > 1, got {self.widen_factor!r}")


@dataclass(frozen=True, slots=True)
class EstimationSettings:
    """What an estimator reads: ``[estimator]``, ``[vehicle]`` and the sensor models of ``[sensors]``."""

    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    vehicle: VehicleSettings = field(default_factory=VehicleSettings)
    gnss: GnssModel = field(default_factory=GnssModel)
    can: CanModel = field(default_factory=CanModel)

    @classmethod
    def of(cls, estimator: EstimatorSettings, vehicle: VehicleSettings, sensors: SensorSettings) -> EstimationSettings:
        return cls(estimator, vehicle, sensors.gnss, sensors.can)
