"""The sample-stream side of every recursive baseline: :meth:`RecursiveEstimator.push` and its contract.

The contract (module docstring of :mod:`sumhe.estimator.base`) is implemented once here; a filter supplies
only the maths, as hooks on its own state:

* ``_start(x0, P0)``: a state and covariance at the first valid fix (layout of :mod:`.kinematics`);
* ``_predict(dt, inputs)``: move the state ``dt`` seconds on (``inputs``: the newest CAN data);
* ``_can_update(inputs)``: use the CAN speed / yaw rate at a CAN speed sample (measurements, or just inputs);
* ``_innovation(kind, z, R, lag)``: a GNSS measurement's innovation and its covariance, with a ``commit``
  that applies the update; the gate here decides whether to commit;
* ``_inflate(kind, nu, R)``: widen the state so that a re-acquired fix can pull it (after a rejected run);
* ``_init_heading(phi, sigma)``: the first azimuth measurement sets the azimuth outright;
* ``_mean()``: the state estimate now (layout of :mod:`.kinematics`, speed and yaw rate filled in).

Timing: the filter's state lives at ``t_state``, the newest CAN speed sample (or fix, if newer); CAN samples
are taken as measured ``settings.can.delay_s`` before their timestamp (the sensor delay, a calibration), and
their estimates are reported at the timestamp. A fix older
than the state (the receiver's latency: fix time = receive time - latency, and CAN data of the meantime came
first) is compared with the state through the model run back by the lag. Each epoch's estimate is reported at
the epoch's own time (the state moved there by the model), so an epoch's estimate may be up to the latency
older than the CAN-rate estimate before it. GNSS silence is measured on the fix clock: the newest sample time
minus the typical delay of fixes behind CAN data (median of the last fixes), compared with 1.5 nominal periods
(from the last intervals between epochs, ``settings.gnss.period_s`` until two epochs were seen).

Bad input never raises: non-finite values, unknown sample types, CAN values beyond the vehicle limits, valid fixes
without a usable position (taken as "no fix"), samples going back in time, fixes older than
``MAX_FIX_LAG_S`` behind the state: each is counted (:meth:`stats`) and logged at the 1st, 10th, 100th ...
occurrence. A numerical failure (non-finite state) or more than ``MAX_DATA_GAP_S`` without any sample restarts
the filter from the next valid fix.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np

from sumhe.baseline.kinematics import (
    AZIMUTH,
    GPS_SPEED,
    OMEGA,
    PHI,
    POSITION,
    E,
    FloatArray,
    Layout,
    N,
    V,
    chi2_threshold,
    step,
)
from sumhe.estimator.base import BadInputCounter, LocalFix, StateEstimate, bad_epoch_time
from sumhe.estimator.grid import GPS_SPEED_RESOLUTION_MPS, gps_speed
from sumhe.messages import CanSample, GpsStatus
from sumhe.settings import EstimationSettings, NoiseSettings

MAX_FIX_LAG_S = 1.0
"""Fixes older than this behind the newest CAN data are dropped (counted ``late_fixes``)."""
MAX_DATA_GAP_S = 10.0
"""No sample at all for this long (a clock jump, a paused replay) restarts the filter from the next fix."""
PERIOD_HISTORY = 32
MAX_PERIOD_S = 5.0
HEADING_UNKNOWN_RAD = math.pi / math.sqrt(3.0)
"""Prior sigma of the azimuth when the first fix has none (the sigma of a uniform angle)."""
REACQUIRE_SPREAD_SIGMAS = 4.0
"""Rejected innovations agree when each is within this many measurement sigmas of their mean."""
REACQUIRE_MIN_FIXES = 3

Decision = Literal["ok", "rejected", "reacquire"]
STATUS_COUNTERS: dict[str, str] = {"ok": "gps_ok", "rejected": "gps_rejected", "outage": "outage_epochs"}


@dataclass(frozen=True, slots=True)
class Inputs:
    """The newest CAN data: speed (m/s), yaw rate (rad/s, mean of the samples since the previous speed
    sample), None when missing or older than ``can_max_gap_s``; ``standstill`` when the CAN speed reads 0."""

    speed: float | None
    yaw_rate: float | None
    standstill: bool


@dataclass(frozen=True, slots=True)
class Pending:
    """A GNSS measurement's innovation ``nu`` and its covariance ``S``; ``commit()`` applies the update."""

    nu: FloatArray
    S: FloatArray
    commit: Callable[[], None]


class Gate:
    """Chi-square innovation gate with re-acquisition.

    A fix is accepted when its normalised innovation squared is within ``threshold``. Rejected fixes are
    remembered; once they have agreed with each other (each innovation within ``REACQUIRE_SPREAD_SIGMAS``
    measurement sigmas of their mean) for ``reacquire_s`` seconds, it is the filter that is wrong (it drifted
    through an outage with too small a covariance) and the gate says ``"reacquire"``. Without this rule a
    long outage can lock GPS out for good (a known robot_localization failure).
    """

    def __init__(self, threshold: float, reacquire_s: float) -> None:
        self.threshold = threshold
        self.reacquire_s = reacquire_s
        self._run: list[tuple[float, FloatArray]] = []

    def clear(self) -> None:
        self._run.clear()

    def check(self, t: float, nu: FloatArray, d2: float, sigma: float) -> Decision:
        """Decide on one innovation ``nu`` (normalised square ``d2``) at time ``t``; ``sigma``: measurement sigma."""
        if d2 <= self.threshold:
            self._run.clear()
            return "ok"
        if self._run:
            mean = np.mean([v for _, v in self._run], axis=0)
            if np.max(np.abs(nu - mean)) > REACQUIRE_SPREAD_SIGMAS * sigma:
                self._run.clear()
        self._run.append((t, nu))
        if len(self._run) >= REACQUIRE_MIN_FIXES and t - self._run[0][0] >= self.reacquire_s:
            self._run.clear()
            return "reacquire"
        return "rejected"


class _NumericFailure(Exception):
    """The state went non-finite; the filter restarts."""


class RecursiveEstimator(BadInputCounter, ABC):
    """Base of the recursive baselines: implements the :class:`~sumhe.estimator.base.Estimator` protocol.

    ``gated = False`` turns the innovation gate off (dead reckoning takes every fix as it is);
    ``uses_gps_speed = False`` leaves the fixes' speed over ground out even with ``settings.gnss.use_speed``.
    """

    name: ClassVar[str] = ""
    gated: ClassVar[bool] = True
    uses_gps_speed: ClassVar[bool] = True

    def __init__(self, settings: EstimationSettings, noise: NoiseSettings) -> None:
        self.settings = settings
        self.noise = noise
        self.layout = Layout.from_settings(settings)
        prob = noise.gate_prob if self.gated else 1.0
        self._pos_gate = Gate(chi2_threshold(prob, 2), noise.reacquire_s)
        self._az_gate = Gate(chi2_threshold(prob, 1), noise.reacquire_s)
        self._sog_gate = Gate(chi2_threshold(prob, 1), noise.reacquire_s)
        self._counts: Counter[str] = Counter()
        self.reset()

    # ---- the Estimator protocol -------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget the state and the stream's timing; the next valid fix starts over (counters are kept)."""
        self._started = False
        self._heading_known = False
        self._t_state = math.nan
        self._t_last = -math.inf
        self._t_can = -math.inf
        self._last_epoch: float | None = None
        self._last_real_epoch: float | None = None
        self._intervals: deque[float] = deque(maxlen=PERIOD_HISTORY)
        self._delays: deque[float] = deque(maxlen=PERIOD_HISTORY)
        self._speed: tuple[float, float] | None = None
        self._yaw: tuple[float, float] | None = None
        self._yaw_sum = 0.0
        self._yaw_n = 0
        self._status: GpsStatus = "outage"
        self._push_t0 = time.perf_counter()
        self._pos_gate.clear()
        self._az_gate.clear()
        self._sog_gate.clear()
        self._reset_filter()

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        """Feed one sample (time-ordered); returns the estimates it produced (see the module docstring)."""
        self._push_t0 = time.perf_counter()
        try:
            if isinstance(sample, LocalFix):
                return self._push_fix(sample)
            if isinstance(sample, CanSample):
                return self._push_can(sample)
            self._count("bad_samples", "not a LocalFix or CanSample: %s", type(sample).__name__)
            return []
        except (_NumericFailure, np.linalg.LinAlgError) as e:
            self._count("numeric_failures", "numerical failure (%s); restarting from the next fix", e)
            self.reset()
            return []

    def stats(self) -> Mapping[str, float | int | str]:
        """Counters (epochs, fixes used/rejected, outage epochs, re-acquisitions, dropped samples) and timing."""
        out: dict[str, float | int | str] = {"estimator": self.name, "period_s": self.period_s}
        out.update(self._counts)
        return out

    @property
    def period_s(self) -> float:
        """The nominal GNSS period (s): mean of the recent intervals between epochs within 50 % of their median
        (the mean of consecutive intervals cancels the latency jitter; the median test leaves gaps out)."""
        if not self._intervals:
            return self.settings.gnss.period_s
        d = np.asarray(self._intervals)
        median = float(np.median(d))
        regular = d[np.abs(d - median) <= 0.5 * median]
        return float(np.mean(regular)) if regular.size else median

    # ---- hooks ------------------------------------------------------------------------------------------------

    @abstractmethod
    def _reset_filter(self) -> None:
        """Drop the filter's state."""

    @abstractmethod
    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        """Initialise at the first valid fix."""

    @abstractmethod
    def _predict(self, dt: float, inputs: Inputs) -> None:
        """Move the state ``dt`` s on."""

    @abstractmethod
    def _can_update(self, inputs: Inputs) -> None:
        """Use the CAN data at a CAN speed sample."""

    @abstractmethod
    def _innovation(self, kind: str, z: FloatArray, R: FloatArray, lag: float) -> Pending:
        """The innovation of a GNSS measurement of ``kind`` (taken ``lag`` s before the state's time)."""

    @abstractmethod
    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        """Widen the state along the rows of ``kind`` so that a re-acquired measurement can pull it."""

    @abstractmethod
    def _init_heading(self, phi: float, sigma: float) -> None:
        """Set the azimuth (rad) with the given sigma."""

    @abstractmethod
    def _mean(self) -> FloatArray:
        """The state estimate at ``t_state``."""

    def _on_report(self, estimate: StateEstimate, epoch: bool) -> None:
        """Called with every estimate returned, ``epoch`` False for the CAN-rate ones (the RTS records them)."""

    def _window(self) -> int:
        return 0

    # ---- stream handling --------------------------------------------------------------------------------------

    def _push_can(self, sample: CanSample) -> list[StateEstimate]:
        t, q, value = sample.t, sample.quantity, sample.value
        if not (isinstance(t, int | float) and isinstance(value, int | float) and math.isfinite(t)):
            self._count("bad_samples", "CAN %s sample with a non-finite time or value", q)
            return []
        if t < self._t_can:
            self._count("dropped_backwards", "CAN %s sample %.3f s back in time dropped", q, self._t_can - t)
            return []
        if q not in ("speed", "yaw_rate"):
            return []
        limit = self.settings.vehicle.max_speed_mps if q == "speed" else 2.0 * self.settings.vehicle.max_yaw_rate_rps
        if not (math.isfinite(value) and abs(value) <= limit):
            self._count("bad_samples", "CAN %s = %r beyond the vehicle limits dropped", q, value)
            return []
        self._t_can = t
        tm = t - self.settings.can.delay_s
        self._check_gap(tm)
        if q == "yaw_rate":
            self._yaw = (tm, value)
            self._yaw_sum += value
            self._yaw_n += 1
            return []
        self._speed = (tm, value)
        if not self._started:
            return []
        out = self._missed_epochs(tm - self._delay_s())
        inputs = self._inputs(tm)
        self._advance(tm, inputs)
        self._can_update(inputs)
        self._yaw_sum, self._yaw_n = 0.0, 0
        self._counts["can_updates"] += 1
        out.append(self._report(t, self._status, epoch=False))
        return out

    def _push_fix(self, fix: LocalFix) -> list[StateEstimate]:
        t = fix.t
        bad = bad_epoch_time(t, self._last_epoch)
        if bad is not None:
            self._count(bad[0], bad[1], *bad[2])
            return []
        if self._started and t < self._t_state - MAX_FIX_LAG_S:
            self._count("late_fixes", "GNSS epoch %.2f s behind the CAN data dropped", self._t_state - t)
            return []
        usable = self._usable(fix)
        if self._last_real_epoch is not None and t - self._last_real_epoch <= MAX_PERIOD_S:
            self._intervals.append(t - self._last_real_epoch)
        self._last_real_epoch = t
        if self._t_last > t:
            self._delays.append(self._t_last - t)
        self._check_gap(t)
        if not self._started:
            self._last_epoch = t
            if not usable:
                return []
            self._begin(fix)
            self._counts["epochs"] += 1
            self._counts["gps_ok"] += 1
            self._status = "ok"
            return [self._report(t, "ok")]
        out = self._missed_epochs(t)
        self._last_epoch = t
        self._counts["epochs"] += 1
        if usable:
            self._advance(t, self._inputs(t))
            status = self._fix_updates(fix, self._t_state - t)
        else:
            status = "outage"
        self._counts[STATUS_COUNTERS[status]] += 1
        self._status = status
        out.append(self._report(t, status))
        return out

    def _check_gap(self, t: float) -> None:
        if self._started and t - self._t_last > MAX_DATA_GAP_S:
            gap = t - self._t_last
            self._count("restarts", "no data for %.1f s: restarting from the next fix", gap)
            self.reset()
        self._t_last = max(self._t_last, t)

    def _delay_s(self) -> float:
        """Typical delay of fixes behind the CAN data (s)."""
        return float(np.median(self._delays)) if self._delays else 0.0

    def _missed_epochs(self, t_fix_clock: float) -> list[StateEstimate]:
        """Outage epochs for the epochs GNSS missed up to ``t_fix_clock`` (silence > 1.5 periods)."""
        out: list[StateEstimate] = []
        period = self.period_s
        while self._last_epoch is not None and t_fix_clock - self._last_epoch > 1.5 * period:
            self._last_epoch += period
            self._counts["epochs"] += 1
            self._counts["outage_epochs"] += 1
            self._counts["missed_epochs"] += 1
            self._status = "outage"
            out.append(self._report(self._last_epoch, "outage"))
        return out

    def _inputs(self, t: float) -> Inputs:
        gap = self.settings.can.max_gap_s
        speed = self._speed[1] if self._speed is not None and t - self._speed[0] <= gap else None
        if self._yaw_n:
            yaw: float | None = self._yaw_sum / self._yaw_n
        else:
            yaw = self._yaw[1] if self._yaw is not None and t - self._yaw[0] <= gap else None
        still = speed is not None and abs(speed) <= 0.5 * self.settings.can.speed_quantum_mps
        return Inputs(speed, yaw, still)

    def _advance(self, t: float, inputs: Inputs) -> None:
        if t > self._t_state:
            self._predict(t - self._t_state, inputs)
            self._t_state = t

    def _begin(self, fix: LocalFix) -> None:
        inputs = self._inputs(fix.t)
        angle = self._fix_angle(fix)
        self._heading_known = angle is not None
        phi, sigma_phi = angle if angle is not None else (0.0, HEADING_UNKNOWN_RAD)
        sigma = self._fix_sigma(fix)
        x0 = np.zeros(self.layout.n)
        x0[E], x0[N], x0[PHI] = fix.east_m, fix.north_m, phi
        x0[V] = inputs.speed if inputs.speed is not None else 0.0
        x0[OMEGA] = inputs.yaw_rate if inputs.yaw_rate is not None and not inputs.standstill else 0.0
        sig = [sigma, sigma, sigma_phi, self.noise.speed0_mps, self.noise.yaw_rate0_rps]
        if self.layout.b is not None:
            sig.append(0.5 * self.settings.can.yaw_rate_bias_max_rps)
        if self.layout.k is not None:
            x0[self.layout.k] = 1.0
            sig.append(0.5 * self.settings.can.speed_scale_max)
        self._t_state = fix.t
        self._start(x0, np.diag(np.square(sig)))
        self._started = True

    def _fix_sigma(self, fix: LocalFix) -> float:
        """The fix's 1-sigma position error (m) times ``gps_scale``: its own (GST, HDOP; at least the resolution
        ``gps_resolution_m``), else by GGA quality, else the default."""
        s = self.settings
        if fix.sigma_m is not None:
            sigma = max(fix.sigma_m, s.gnss.resolution_m)
        elif fix.quality == 4:
            sigma = s.gnss.sigma_rtk_m
        elif fix.quality == 5:
            sigma = s.gnss.sigma_float_m
        else:
            sigma = s.gnss.sigma_m
        return self.noise.gps_scale * sigma

    def _fix_angle(self, fix: LocalFix) -> tuple[float, float] | None:
        """The azimuth a fix measures (rad) and its sigma: HDT heading, else course above the minimum speed."""
        s = self.settings
        if s.gnss.use_heading and fix.heading_rad is not None and math.isfinite(fix.heading_rad):
            return fix.heading_rad, s.gnss.heading_sigma_rad
        speed = fix.speed_mps
        if speed is None or not math.isfinite(speed):
            speed = self._speed[1] if self._speed is not None else None
        if (
            fix.course_rad is not None
            and math.isfinite(fix.course_rad)
            and speed is not None
            and speed >= s.gnss.course_min_speed_mps
        ):
            return fix.course_rad, math.hypot(self.noise.course_rad, s.gnss.speed_sigma_mps / speed)
        return None

    def _fix_updates(self, fix: LocalFix, lag: float) -> GpsStatus:
        sigma = self._fix_sigma(fix)
        z = np.array([fix.east_m, fix.north_m])
        status = self._gated_update(POSITION, z, np.eye(2) * sigma**2, lag, self._pos_gate, fix.t, sigma)
        if status == "rejected":
            return status
        self._angle_update(fix, lag)
        s = self.settings
        use = s.gnss.use_speed and self.uses_gps_speed
        speed = gps_speed(fix.speed_mps, self._speed[1] if self._speed is not None else None, s) if use else None
        if speed is not None:
            sigma_v = max(s.gnss.speed_sigma_mps, GPS_SPEED_RESOLUTION_MPS)
            R = np.array([[sigma_v**2]])
            if self._gated_update(GPS_SPEED, np.array([speed]), R, lag, self._sog_gate, fix.t, sigma_v) == "rejected":
                self._count("speed_rejected", "GNSS speed over ground rejected by the gate")
        return status

    def _angle_update(self, fix: LocalFix, lag: float) -> None:
        angle = self._fix_angle(fix)
        if angle is None:
            return
        phi, sigma_phi = angle
        if not self._heading_known:
            self._init_heading(phi, sigma_phi)
            self._heading_known = True
            return
        R = np.array([[sigma_phi**2]])
        if self._gated_update(AZIMUTH, np.array([phi]), R, lag, self._az_gate, fix.t, sigma_phi) == "rejected":
            self._count("azimuth_rejected", "GNSS course/heading rejected by the gate")

    def _gated_update(
        self, kind: str, z: FloatArray, R: FloatArray, lag: float, gate: Gate, t: float, sigma: float
    ) -> GpsStatus:
        pending = self._innovation(kind, z, R, lag)
        d2 = float(pending.nu @ np.linalg.solve(pending.S, pending.nu))
        decision = gate.check(t, pending.nu, d2, sigma)
        if decision == "rejected":
            return "rejected"
        if decision == "reacquire":
            self._count(
                "reacquired", "re-acquired GNSS %s after %.1f s of agreeing rejected fixes", kind, gate.reacquire_s
            )
            self._inflate(kind, pending.nu, R)
            pending = self._innovation(kind, z, R, lag)
        pending.commit()
        return "ok"

    def _report(self, t: float, status: GpsStatus, epoch: bool = True) -> StateEstimate:
        x = self._mean()
        if t != self._t_state:
            x = step(x, t - self._t_state)
        if not np.all(np.isfinite(x)):
            raise _NumericFailure("non-finite state")
        estimate = StateEstimate(
            t=t,
            east_m=float(x[E]),
            north_m=float(x[N]),
            azimuth_rad=float(x[PHI] % (2.0 * math.pi)),
            speed_mps=float(x[V]),
            yaw_rate_rps=float(x[OMEGA]),
            gps=status,
            mode=self.name,
            window=self._window(),
            solve_ms=1000.0 * (time.perf_counter() - self._push_t0),
        )
        self._on_report(estimate, epoch)
        return estimate
