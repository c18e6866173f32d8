"""``su-batch``: the batch SU estimate of a whole recorded drive, for offline replays.

It buffers the stream and, at the end (:meth:`SuBatch.finish`), smooths it in overlapping windows of
``estimator.batch.window_s`` seconds (each solved by :func:`~sumhe.estimator.batch.estimate_batch`). A window ends
only where GNSS is present (paper 000, sec. 3.2: data must be present at both ends of a window), so a boundary never
falls inside an outage; each window keeps its estimates after the last one kept, up to the middle of its overlap
with the next window: away from its ends, where the smoother has data on both sides (an outage that fills the
overlap comes whole from the window with the tighter noise bounds: :func:`seam`). It returns one estimate per step
of the grid (GNSS epochs and the outage steps between them). During the drive :meth:`push` returns nothing: it is
not a live estimator.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
from collections.abc import Mapping

import numpy as np

from sumhe.config import Config
from sumhe.errors import EstimatorInputError
from sumhe.estimator.base import StateEstimate
from sumhe.estimator.batch import SuResult, estimate_batch
from sumhe.frontend.can import centred_speed, speed_reads_low
from sumhe.frontend.fixes import LocalFix
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, GnssFix, Sample
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)


def window_bounds(t_gps: np.ndarray, t_end: float, length_s: float, overlap_s: float) -> list[tuple[float, float]]:
    """Window [start, end] times over a drive: each ``length_s`` long (stretched to the next GNSS time so no window
    ends in an outage), consecutive windows overlapping by ``overlap_s``. A window that starts before an outage
    (no GNSS time within ``overlap_s`` of the last window's end) reaches ``overlap_s`` past that end, so the
    outage's end too lies inside a window with data on both sides of it."""
    if t_gps.size == 0:
        return []
    out = []
    start, end = float(t_gps[0]), -math.inf
    while True:
        later = t_gps[t_gps >= max(start + length_s, end + overlap_s)]
        end = float(later[0]) if later.size else t_end
        out.append((start, end))
        if end >= t_end or not later.size:
            return out
        earlier = t_gps[(t_gps <= end - overlap_s) & (t_gps > start)]
        start = float(earlier[-1]) if earlier.size else end


def state_noise_volume(result: SuResult) -> float:
    """The log-volume of the box of state noises a window's solution allows (the sum of the logs of its q): the
    smaller, the tighter the set S(q, r) its estimates come from; infinite where its solve failed."""
    return float(np.sum(np.log(result.q))) if result.success else math.inf


def seam(t_gps: np.ndarray, end: float, next_start: float, overlap_s: float, next_tighter: bool) -> float:
    """Up to which time the estimates of a window ending at ``end`` are kept, those of the next window (starting at
    ``next_start``) after it: the middle of their overlap, away from both windows' ends. Where the overlap holds an
    outage longer than ``overlap_s`` (the next window started at the last fix before it, :func:`window_bounds`),
    the outage comes whole from one window: the next (``next_start``) where its state noises are the tighter
    (``next_tighter``, :func:`state_noise_volume`), else this one (``end``). At the middle, the real drive's 60 s
    outages changed window half-way, up to 64 m apart: each window holds one fix on one side of the outage, and
    one window's azimuth bound can be several times the other's (at the outage of 1350 s, 0.0151 against 0.0022 rad
    a step): its half of the outage wandered within it."""
    gaps = np.diff(t_gps[(t_gps >= next_start) & (t_gps <= end)])
    if gaps.size and gaps.max() > overlap_s:
        return next_start if next_tighter else end
    return (end + next_start) / 2


class SuBatch:
    """The batch SU estimator over a whole drive, in overlapping windows (see the module docstring)."""

    name = "su-batch"

    def __init__(self, settings: EstimationSettings) -> None:
        self.settings = settings
        self._reads_low = speed_reads_low(settings.can)
        self.reset()

    @classmethod
    def from_config(cls, config: Config) -> SuBatch:
        return cls(config.estimation)

    def reset(self) -> None:
        self._samples: list[Sample] = []
        self._frame: LocalFrame | None = None
        self._windows = 0
        self._failed = 0
        self._solve_s = 0.0

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        if isinstance(sample, LocalFix):
            if sample.fix is None:
                return []
            if self._frame is None and sample.valid:
                self._frame = sample.frame
            self._samples.append(sample.fix)
        elif sample.quantity == "speed":
            self._samples.append(dataclasses.replace(sample, value=centred_speed(sample.value, self._reads_low)))
        elif sample.quantity == "yaw_rate":
            self._samples.append(sample)
        return []

    def finish(self) -> list[StateEstimate]:
        """Smooth everything pushed so far; one estimate per grid step, in time order."""
        if self._frame is None or len(self._samples) < 2:
            return []
        s = self.settings
        t_gps = np.array([x.t for x in self._samples if isinstance(x, GnssFix) and x.valid])
        t_end = self._samples[-1].t
        out: list[StateEstimate] = []
        last_t = -math.inf
        windows = window_bounds(t_gps, t_end, s.estimator.batch.window_s, s.estimator.batch.overlap_s)
        solved: list[tuple[float, float, SuResult]] = []
        for i, (start, end) in enumerate(windows):
            chunk = [x for x in self._samples if start <= x.t <= end]
            try:
                result = estimate_batch(chunk, s, frame=self._frame)
            except EstimatorInputError as e:
                log.warning("su-batch: window %d (%.1f-%.1f s) skipped: %s", i, start, end, e)
                continue
            self._windows += 1
            self._failed += not result.success
            self._solve_s += result.solve_time_s
            solved.append((start, end, result))
        for (_, end, result), after in itertools.zip_longest(solved, solved[1:]):
            if after is None:
                keep_to = math.inf
            else:
                tighter = state_noise_volume(after[2]) <= state_noise_volume(result)
                keep_to = seam(t_gps, end, after[0], s.estimator.batch.overlap_s, tighter)
            out += [est for est in _estimates(result) if last_t < est.t <= keep_to]
            last_t = out[-1].t if out else last_t
        return out

    def stats(self) -> Mapping[str, float | int | str]:
        return {"windows": self._windows, "failed": self._failed, "solve_s": round(self._solve_s, 3)}


def _estimates(result: SuResult) -> list[StateEstimate]:
    names = result.state_names
    east, north = result.east, result.north
    phi, v, omega = (result.states[:, names.index(n)] for n in ("phi", "v", "omega"))
    mode = "su-batch" if result.success else f"su-batch failed: {result.status}"
    return [
        StateEstimate(
            t=float(result.t[k]),
            east_m=float(east[k]),
            north_m=float(north[k]),
            azimuth_rad=float(phi[k]),
            speed_mps=float(v[k]),
            yaw_rate_rps=float(omega[k]),
            gps="ok" if result.gps[k] else "outage",
            mode=mode,
            window=len(result.t),
            solve_ms=result.solve_time_s * 1000.0,
        )
        for k in range(len(result.t))
    ]
