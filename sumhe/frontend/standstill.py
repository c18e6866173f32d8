"""The CAN yaw rate at a standstill as a measurement of its bias: the MHE's form of the Kalman peers' ``omega = 0`` row
(``docs/mhe.md``), and the on-line sensor check's first word on a bias beyond the estimators' bounds
(:mod:`sumhe.frontend.sensor_check`, at its own number of sigmas).

A car at rest does not turn, so what its CAN yaw rate reads then is the bias (``g omega + b`` with ``omega = 0``).
The window cannot see it: at rest no course is measured and the azimuth's change is free. A stop (consecutive GNSS
steps whose CAN speed samples all read 0) is told to the arrival cost once, when the car drives off, as one
measurement of the bias: the mean of its yaw-rate samples, within ``0.5 quantum + k sqrt(sigma^2 / n + rest^2)``
(``k`` the allowances' sigmas). ``rest`` (``estimator.mhe.rest_bias_rps``) is how far a gyro's bias at rest may
differ from its bias in motion (vibration, the quantisation's dither): samples counted as independent would make a
long stop as sure as no gyro is (tried per step: on the shared real drive, whose gyro reads 0.346 +- 0.025 deg/s at
rest and 0.384 in motion, the 30 s outage 20 s after its receiver's cold start ended 42 m off instead of 26 m). A
stop whose samples spread more than a resting gyro's do (``0.5 quantum + 2 sigma``: a car creeping through a turn
below the speed's quantum) is not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sumhe.frontend.can import CanBuffer
from sumhe.settings.sensors import CanModel

SPREAD_SIGMAS = 2.0
"""A stop's yaw-rate samples spread (standard deviation) at most half a quantum plus this many sigmas."""


@dataclass(slots=True)
class Stop:
    """The yaw-rate samples of a standstill so far: their count, sum and sum of squares (rad/s)."""

    n: int = 0
    total: float = 0.0
    squares: float = 0.0

    def add(self, values: list[float]) -> None:
        self.n += len(values)
        self.total += sum(values)
        self.squares += sum(v * v for v in values)

    @property
    def mean(self) -> float:
        return self.total / self.n

    @property
    def spread(self) -> float:
        """The samples' standard deviation (rad/s)."""
        return math.sqrt(max(self.squares / self.n - self.mean**2, 0.0))


def still_yaw_rates(can: CanBuffer, t0: float, t1: float, still_mps: float, max_gap_s: float) -> list[float] | None:
    """The CAN yaw-rate samples in (t0, t1] when every CAN speed sample in it reads at most ``still_mps`` (half
    the speed's quantum: 0), or, with none in it, the one held at ``t1`` (within ``max_gap_s``) does; None
    otherwise (moving, or no speed known)."""
    speeds = can["speed"].between(t0, t1)
    held = can["speed"].at(t1, max_gap_s) if not speeds else None
    if held is not None:
        speeds = [held]
    if not speeds or max(map(abs, speeds)) > still_mps:
        return None
    return can["yaw_rate"].between(t0, t1)


class StopWatch:
    """A standstill's CAN yaw rates gathered step by step (:func:`still_yaw_rates`), the stop handed out whole
    when the car drives off; :attr:`since` is when it began (s)."""

    def __init__(self) -> None:
        self.stop = Stop()
        self.since = math.nan

    def step(self, can: CanBuffer, t0: float, t1: float, still_mps: float, max_gap_s: float) -> Stop | None:
        """Take the step (``t0``, ``t1``]: the stop that ended before it where the car moves in it (None where
        there was none, or the car is still at rest)."""
        still = still_yaw_rates(can, t0, t1, still_mps, max_gap_s)
        if still is not None:
            if not self.stop.n:
                self.since = t0
            self.stop.add(still)
            return None
        stop, self.stop = self.stop, Stop()
        return stop if stop.n else None


def bias_at_rest(stop: Stop, can: CanModel, k_sigmas: float, rest_rps: float) -> tuple[float, float] | None:
    """What ``stop`` measures of the yaw-rate bias: its mean and the bound on the mean's error (rad/s), None where
    it has no sample or its samples spread too much (module docstring)."""
    q, sigma = can.yaw_rate_quantum_rps, can.yaw_rate_sigma_rps
    if not stop.n or stop.spread > 0.5 * q + SPREAD_SIGMAS * sigma:
        return None
    return stop.mean, 0.5 * q + k_sigmas * math.sqrt(sigma**2 / stop.n + rest_rps**2)
