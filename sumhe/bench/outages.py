"""GNSS outages cut into a recorded drive, and the estimate's errors against the fixes cut out.

A recorded drive rarely comes with a reference trajectory; its own fixes are one wherever the estimator did not
see them. :class:`FixCut` removes the fixes inside outage windows from a sample stream and keeps them;
:func:`outage_errors` measures the estimates, interpolated to each removed fix's time, against those fixes (on the
estimates' clock: an estimator that learned the GNSS time offset places a fix at its stamped time plus that offset,
and is compared with it there); :func:`mode_shares` counts how the estimator solved its epochs. Pure: no files,
clocks or estimators (``sumhe replay --outage``, ``sumhe fleet`` and the benchmarks share it).

Units: seconds (``t`` on the drive's clock), metres, degrees for latitude and longitude.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sumhe.bench.metrics import interval_index, mean_p95_max
from sumhe.geo import LocalFrame
from sumhe.messages import GnssFix, Sample

MAX_INTERPOLATION_GAP_S = 2.0
"""A removed fix is scored only where estimates lie on both sides of it at most this far apart (s)."""

BETWEEN_EPOCHS_MODE = "can"
"""The mode of estimates between GNSS epochs (the newest solution moved on with CAN data): not an epoch."""


def outage_windows(outages: Iterable[tuple[float, float]], t0: float) -> list[tuple[float, float]]:
    """``(start_s, length_s)`` pairs, starts relative to ``t0`` (s), as absolute half-open windows
    ``[t0 + start, t0 + start + length)`` in time order; ValueError for a negative start, a length that is not
    positive, or windows that overlap."""
    out = []
    for start, length in sorted(outages):
        if not (math.isfinite(start) and start >= 0.0):
            raise ValueError(f"outage {start:g}+{length:g}: the start must be >= 0 s")
        if not (math.isfinite(length) and length > 0.0):
            raise ValueError(f"outage {start:g}+{length:g}: the length must be > 0 s")
        if out and t0 + start < out[-1][1]:
            raise ValueError(f"outage {start:g}+{length:g} overlaps the one before it")
        out.append((t0 + start, t0 + start + length))
    return out


@dataclass
class FixCut:
    """Removes the GNSS fixes whose time lies inside one of ``windows`` (absolute, s, half-open, not
    overlapping) from a stream: :meth:`keep` says whether a sample stays; ``removed`` holds the fixes taken out."""

    windows: Sequence[tuple[float, float]]
    removed: list[GnssFix] = field(default_factory=list)

    def keep(self, sample: Sample) -> bool:
        if not isinstance(sample, GnssFix) or not self.windows:
            return True
        if interval_index([sample.t], self.windows)[0] < 0:
            return True
        self.removed.append(sample)
        return False


@dataclass(frozen=True, slots=True)
class OutageErrors:
    """Horizontal errors (m) of the estimates against the valid fixes removed in one window ``[start, end)``
    (absolute, s), or over all windows: ``fixes`` removed, ``scored`` of them with estimates around (see
    :data:`MAX_INTERPOLATION_GAP_S`), mean, 95th percentile and maximum over the scored (NaN when none)."""

    start: float
    end: float
    fixes: int
    scored: int
    mean_m: float
    p95_m: float
    max_m: float


def outage_errors(
    windows: Sequence[tuple[float, float]],
    removed: Sequence[GnssFix],
    est_t: ArrayLike,
    est_lat_deg: ArrayLike,
    est_lon_deg: ArrayLike,
    offset_s: float = 0.0,
) -> tuple[list[OutageErrors], OutageErrors]:
    """The errors of estimates (times ``est_t``, s; WGS84 latitude/longitude, deg) against the valid ``removed``
    fixes of each window, and over all of them. Each fix is compared with the estimate interpolated linearly (in
    a local east/north frame) to its time plus ``offset_s`` (:func:`residuals_at_fixes`: the estimator's learned
    GNSS time offset, the fixes' true time on the estimates' clock)."""
    t_fix, d_east, d_north, _ = residuals_at_fixes(removed, est_t, est_lat_deg, est_lon_deg, offset_s=offset_s)
    errors = np.hypot(d_east, d_north)
    index = window_index(t_fix, windows, offset_s)
    per_window = [outage_stats(start, end, errors[index == i]) for i, (start, end) in enumerate(windows)]
    start = windows[0][0] if windows else math.nan
    end = windows[-1][1] if windows else math.nan
    return per_window, outage_stats(start, end, errors[index >= 0])


def window_index(
    t_fix: NDArray[np.float64], windows: Sequence[tuple[float, float]], offset_s: float = 0.0
) -> NDArray[np.intp]:
    """The window (index into ``windows``; -1: none) of each removed fix's time ``t_fix`` (s) on the estimates'
    clock (:func:`residuals_at_fixes`: the windows moved by ``offset_s`` as the fixes were)."""
    moved = [(start + offset_s, end + offset_s) for start, end in windows]
    return interval_index(t_fix, moved) if t_fix.size else np.zeros(0, dtype=np.intp)


def residuals_at_fixes(
    removed: Sequence[GnssFix],
    est_t: ArrayLike,
    est_lat_deg: ArrayLike,
    est_lon_deg: ArrayLike,
    extra: Sequence[ArrayLike] = (),
    offset_s: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], list[NDArray[np.float64]]]:
    """The valid ``removed`` fixes' times plus ``offset_s`` (s: on the estimates' clock) and the estimates'
    residuals east and north of them (m: estimate minus fix, the estimates interpolated linearly in a local
    east/north frame to each fix's time on their clock; NaN where no estimates lie on both sides within
    :data:`MAX_INTERPOLATION_GAP_S`), and each of the per-estimate values ``extra`` interpolated the same way."""
    fixes = [f for f in removed if f.valid and f.lat_deg is not None and f.lon_deg is not None]
    t_fix = np.array([f.t + offset_s for f in fixes], dtype=float)
    d_east, d_north = np.full(len(fixes), math.nan), np.full(len(fixes), math.nan)
    values = [np.full(len(fixes), math.nan) for _ in extra]
    t = np.asarray(est_t, dtype=float)
    if fixes and t.size:
        frame = LocalFrame(float(fixes[0].lat_deg), float(fixes[0].lon_deg), 0.0)  # type: ignore[arg-type]
        order = np.argsort(t, kind="stable")
        t = t[order]
        est = frame.to_enu(np.asarray(est_lat_deg, dtype=float)[order], np.asarray(est_lon_deg, dtype=float)[order])
        ref = frame.to_enu([f.lat_deg for f in fixes], [f.lon_deg for f in fixes])
        k = np.searchsorted(t, t_fix)
        inside = (k > 0) & (k < t.size)
        kk = np.clip(k, 1, max(t.size - 1, 1))
        inside &= t[kk] - t[kk - 1] <= MAX_INTERPOLATION_GAP_S
        d_east = np.where(inside, np.interp(t_fix, t, est[:, 0]) - ref[:, 0], math.nan)
        d_north = np.where(inside, np.interp(t_fix, t, est[:, 1]) - ref[:, 1], math.nan)
        values = [np.where(inside, np.interp(t_fix, t, np.asarray(v, dtype=float)[order]), math.nan) for v in extra]
    return t_fix, d_east, d_north, values


def outage_stats(start: float, end: float, errors: np.ndarray) -> OutageErrors:
    """The :class:`OutageErrors` of the errors (m; NaN: not scored) of the window ``[start, end)``."""
    scored = errors[np.isfinite(errors)]
    return OutageErrors(start, end, int(errors.size), int(scored.size), *mean_p95_max(scored))


@dataclass(frozen=True, slots=True)
class ModeShares:
    """How an estimator's epochs went, from the modes of its estimates: ``modes`` counts every mode; ``epochs``
    the estimates not between epochs (mode not :data:`BETWEEN_EPOCHS_MODE`), ``widened`` those solved on widened
    bounds (a mode containing "widened"), ``failed`` those where the solver failed and the model's prediction
    stood in (mode "predict")."""

    modes: dict[str, int]
    epochs: int
    widened: int
    failed: int

    @property
    def widened_share(self) -> float:
        return self.widened / self.epochs if self.epochs else math.nan

    @property
    def failed_share(self) -> float:
        return self.failed / self.epochs if self.epochs else math.nan


def mode_shares(modes: Iterable[str] | Mapping[str, int]) -> ModeShares:
    """Count ``modes`` (one per estimate, or already counted: mode -> count) into :class:`ModeShares`."""
    counts = Counter(modes)
    epochs = sum(n for m, n in counts.items() if m != BETWEEN_EPOCHS_MODE)
    widened = sum(n for m, n in counts.items() if "widened" in m)
    return ModeShares(dict(counts), epochs, widened, counts.get("predict", 0))
