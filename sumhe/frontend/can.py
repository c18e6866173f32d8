"""CAN samples between the bus and the estimators: a time-ordered buffer for streams and its vectorised twin for
the batch grid.

Both average the samples of an interval (a step's half-intervals around it); the stream falls back to the nearest
sample within ``max_gap_s``, the grid to linear interpolation within it. Times are measurement times (sample
timestamp minus the quantity's age, :meth:`~sumhe.settings.sensors.CanModel.delay_of`).
"""

from __future__ import annotations

import bisect
import math

import numpy as np
from numpy.typing import NDArray

from sumhe.settings.sensors import CanModel

CAN_USED = ("speed", "yaw_rate")
"""The CAN quantities the estimators read."""
TRIM_EVERY = 256
"""The buffer drops old samples once this many have accumulated in front (amortised: no shift per sample)."""


def speed_reads_low(can: CanModel) -> float:
    """How much a CAN speed reads low on the mean (m/s): half its quantum where it is truncated
    (``sensors.can.speed_rounding``), else 0."""
    return 0.5 * can.speed_quantum_mps if can.speed_rounding == "truncate" else 0.0


def centred_speed(value: float, reads_low: float) -> float:
    """A CAN speed (m/s) taken at the middle of its quantum: ``reads_low`` added towards its sign; 0 stays 0 (a
    truncated 0 is mostly a standstill)."""
    return value + math.copysign(reads_low, value) if value and reads_low else value


class Samples:
    """Time-ordered samples of one quantity (s, SI value), trimmed from the front."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.v: list[float] = []

    def add(self, t: float, value: float) -> None:
        self.t.append(t)
        self.v.append(value)

    def trim(self, t_min: float) -> None:
        """Forget the samples before ``t_min`` (in batches of :data:`TRIM_EVERY`, or all when all are older)."""
        k = bisect.bisect_left(self.t, t_min)
        if k > TRIM_EVERY or (k and k == len(self.t)):
            del self.t[:k], self.v[:k]

    def remap(self, factor: float, shift: float) -> None:
        """Multiply every value kept by ``factor`` and add ``shift`` (a quantity's mapping corrected on line)."""
        self.v[:] = [factor * v + shift for v in self.v]

    def mean(self, t0: float, t1: float) -> tuple[float, int] | None:
        """Mean of the samples in (t0, t1] and their number, None if there is none."""
        i, j = bisect.bisect_right(self.t, t0), bisect.bisect_right(self.t, t1)
        return (sum(self.v[i:j]) / (j - i), j - i) if j > i else None

    def between(self, t0: float, t1: float) -> list[float]:
        """The values of the samples in (t0, t1]."""
        return self.v[bisect.bisect_right(self.t, t0) : bisect.bisect_right(self.t, t1)]

    def at(self, t: float, max_age: float) -> float | None:
        """The newest sample at or before ``t`` if it is at most ``max_age`` s old, else the next one within it."""
        i = bisect.bisect_right(self.t, t)
        if i and t - self.t[i - 1] <= max_age:
            return self.v[i - 1]
        if i < len(self.t) and self.t[i] - t <= max_age:
            return self.v[i]
        return None

    def interpolate(self, t: float, max_gap: float) -> float | None:
        """The samples on both sides of ``t`` interpolated linearly to it, when they are at most ``max_gap`` s from
        it; None otherwise."""
        i = bisect.bisect_right(self.t, t)
        if not 0 < i < len(self.t) or t - self.t[i - 1] > max_gap or self.t[i] - t > max_gap:
            return None
        t0, t1 = self.t[i - 1], self.t[i]
        return self.v[i - 1] + (t - t0) / (t1 - t0) * (self.v[i] - self.v[i - 1])

    @property
    def newest(self) -> float:
        """Time of the newest sample (-inf when empty)."""
        return self.t[-1] if self.t else -math.inf


class CanBuffer:
    """The recent samples of each quantity of :data:`CAN_USED`."""

    def __init__(self) -> None:
        self.samples = {q: Samples() for q in CAN_USED}

    def __getitem__(self, quantity: str) -> Samples:
        return self.samples[quantity]

    @property
    def newest(self) -> float:
        """Time of the newest sample of any quantity (-inf when empty)."""
        return max(s.newest for s in self.samples.values())

    def trim(self, t_min: float) -> None:
        for s in self.samples.values():
            s.trim(t_min)


def can_on_grid(ts: NDArray[np.float64], vs: NDArray[np.float64], t: NDArray[np.float64], max_gap: float) -> NDArray:
    """CAN values (``vs`` at times ``ts``) on the grid ``t``: mean over each step's half-intervals, else
    linear interpolation, else NaN where the nearest sample is more than ``max_gap`` s away."""
    out = np.full(len(t), np.nan)
    if len(ts) == 0:
        return out
    mid = 0.5 * (t[1:] + t[:-1])
    lo = np.concatenate([[t[0] - (mid[0] - t[0] if len(mid) else 0.05)], mid])
    hi = np.concatenate([mid, [t[-1] + (t[-1] - mid[-1] if len(mid) else 0.05)]])
    cum = np.concatenate([[0.0], np.cumsum(vs)])
    i0 = np.searchsorted(ts, lo, side="left")
    i1 = np.searchsorted(ts, hi, side="left")
    count = i1 - i0
    has = count > 0
    out[has] = (cum[i1[has]] - cum[i0[has]]) / count[has]
    near = np.abs(ts[np.clip(np.searchsorted(ts, t), 0, len(ts) - 1)] - t)
    near = np.minimum(near, np.abs(ts[np.clip(np.searchsorted(ts, t) - 1, 0, len(ts) - 1)] - t))
    interp = ~has & (near <= max_gap) & (t >= ts[0] - max_gap) & (t <= ts[-1] + max_gap)
    out[interp] = np.interp(t[interp], ts, vs)
    return out
