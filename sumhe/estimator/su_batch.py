"""``su-batch``: the batch SU estimate of a whole recorded drive, for offline replays.

It buffers the stream and, at the end (:meth:`SuBatch.finish`), smooths it in overlapping windows of
``estimator.batch.window_s`` seconds (each solved by :func:`~sumhe.estimator.batch.estimate_batch`). A window ends
only where GNSS is present (paper 000, sec. 3.2: data must be present at both ends of a window), so a boundary never
falls inside an outage; each window keeps its estimates after the last one kept, up to the middle of its overlap
with the next window: away from its ends, where the smoother has data on both sides (an outage that fills the
overlap is both windows' blend, or the one whose noise bounds are the tighter: :func:`blend_outage`). It returns one
estimate per step of the grid (GNSS epochs and the outage steps between them). During the drive :meth:`push` returns
nothing: it is not a live estimator.
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
from sumhe.frontend.measurements import fix_sigmas
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, GnssFix, Sample
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)

_STATES = ("px", "py", "phi", "v", "omega")
"""The states an estimate reports, by name (:meth:`SuResult.state`)."""


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


def filled_overlap(t_gps: np.ndarray, end: float, next_start: float, overlap_s: float) -> tuple[float, float] | None:
    """The outage (its last fix before, its first fix after) that fills the overlap of a window ending at ``end`` and
    the next one starting at ``next_start``: a gap between fixes longer than ``overlap_s`` there (the next window
    then started at the last fix before it, :func:`window_bounds`); None where the overlap holds no such gap."""
    inside = t_gps[(t_gps >= next_start) & (t_gps <= end)]
    gaps = np.diff(inside)
    if not gaps.size or gaps.max() <= overlap_s:
        return None
    i = int(np.argmax(gaps))
    return float(inside[i]), float(inside[i + 1])


def later_weight(x: float, dv: float, agree: bool) -> float:
    """The weight of the later window's estimate at the fraction ``x`` (0-1) of an outage both windows hold whole
    (:func:`filled_overlap`). Each holds one fix on one side of the outage and all of its data on the other: where
    their tracks ``agree`` (:func:`blend_outage`), ``x`` (the earlier window's near the outage's start, the later's
    near its end, no step between them); where they do not, at least one has wandered: the whole outage from the
    window whose state noise bounds hold the smaller box (``dv``, the later's :func:`state_noise_volume` less the
    earlier's, below 0: the later; a failed window's is infinite), by ``x`` where that does not tell (both failed)."""
    if agree or dv == 0.0 or math.isnan(dv):
        return x
    return 1.0 if dv < 0.0 else 0.0


def blend_outage(
    mine: list[StateEstimate], early: SuResult, late: SuResult, gap: tuple[float, float], allowance_m: float
) -> list[StateEstimate]:
    """The earlier window's estimates (``mine``, :func:`window_estimates` of ``early``) inside the outage ``gap`` (its
    last fix before, its first fix after), each blended with the later window's states at its time by
    :func:`later_weight` (the azimuth the shorter way round). The tracks agree where they are never further apart
    than ``allowance_m``, the error a fix at the outage's ends is allowed (:func:`fix_allowance`): what a fix could not
    tell apart.

    Why: the real drive's outages that fill an overlap (with its 1 Hz fixes, all of 10 s or more) changed window at
    the overlap's middle, up to 64 m apart, where one window's azimuth bound was several times the other's (at 1350 s,
    0.0151 against 0.0022 rad a step) and its half of the outage wandered within it; the tighter window's whole
    outage mended those but lost a decimetre on the simulator's clean drives, where both windows are good and a blend
    by ``x`` is better than either."""
    a, b = gap
    inside = [est for est in mine if a < est.t < b]
    t = np.array([est.t for est in inside])
    there = {n: np.interp(t, late.t, late.state(n)) for n in _STATES}
    apart = np.hypot(there["px"] - [est.east_m for est in inside], there["py"] - [est.north_m for est in inside])
    agree = not apart.size or float(apart.max()) <= allowance_m
    dv = state_noise_volume(late) - state_noise_volume(early)
    out = []
    for k, est in enumerate(inside):
        w = later_weight((est.t - a) / (b - a), dv, agree)
        east, north, phi, v, omega = (float(there[n][k]) for n in _STATES)
        out.append(
            dataclasses.replace(
                est,
                east_m=est.east_m + w * (east - est.east_m),
                north_m=est.north_m + w * (north - est.north_m),
                azimuth_rad=est.azimuth_rad + w * math.remainder(phi - est.azimuth_rad, math.tau),
                speed_mps=est.speed_mps + w * (v - est.speed_mps),
                yaw_rate_rps=est.yaw_rate_rps + w * (omega - est.yaw_rate_rps),
                mode=est.mode if w < 0.5 else _mode(late),
            )
        )
    return out


def fix_allowance(fix: GnssFix, settings: EstimationSettings) -> float:
    """The largest position error (m) the SU estimators allow a fix: ``r_cap_sigmas`` times its larger 1-sigma
    error (GST, quality, HDOP or the configured sigma: :func:`~sumhe.frontend.measurements.fix_sigmas`)."""
    sigmas = fix_sigmas(fix.quality, fix.hdop, fix.sigma_lon_m, fix.sigma_lat_m, settings.gnss)
    return settings.estimator.r_cap_sigmas * max(sigmas)


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
        fixes = [x for x in self._samples if isinstance(x, GnssFix) and x.valid]
        t_gps = np.array([f.t for f in fixes])
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
                out += [est for est in window_estimates(result) if est.t > last_t]
                break
            gap = filled_overlap(t_gps, end, after[0], s.estimator.batch.overlap_s)
            keep_to = (end + after[0]) / 2 if gap is None else gap[0]
            mine = window_estimates(result)
            out += [est for est in mine if last_t < est.t <= keep_to]
            if gap is not None:
                allowance = max(fix_allowance(fixes[i], s) for i in np.searchsorted(t_gps, gap))
                out += blend_outage(mine, result, after[2], gap, allowance)
            last_t = out[-1].t if out else last_t
        return out

    def stats(self) -> Mapping[str, float | int | str]:
        return {"windows": self._windows, "failed": self._failed, "solve_s": round(self._solve_s, 3)}


def _mode(result: SuResult) -> str:
    return "su-batch" if result.success else f"su-batch failed: {result.status}"


def window_estimates(result: SuResult) -> list[StateEstimate]:
    """One estimate per step of a window's solution, in the window's frame."""
    east, north, phi, v, omega = (result.state(n) for n in _STATES)
    mode = _mode(result)
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
