"""From time-ordered samples to the estimator's time grid: outputs, availability and error allowances (the
batch estimators' front-end: the measurement functions of :mod:`sumhe.frontend`, on whole windows).

The grid's steps are the GNSS epochs (the fixes' times ``t``: the time their position refers to, stamped once where
fixes enter, :func:`sumhe.io.fixtime.stamp_fix`); gaps longer than 1.5 nominal periods
(:func:`~sumhe.frontend.epochs.nominal_period`; an outage) are filled with evenly spaced steps that carry only CAN
outputs, and the grid reaches the first and last sample. CAN speed and yaw rate are averaged over each step's
half-intervals (:func:`~sumhe.frontend.can.can_on_grid`). Each output also gets a per-step *error allowance*: a bound
on its measurement error in its own unit, ``estimator.r_cap_sigmas`` sigmas of its measurement
(:mod:`sumhe.frontend.measurements`: the receiver's reported accuracy, the CAN sensors' resolution and noise; a CAN
value's as one sample's, its r is estimated anyway); :mod:`sumhe.estimator.bounds` turns allowances into caps on r.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.errors import EstimatorInputError
from sumhe.frontend.can import CAN_USED, can_on_grid
from sumhe.frontend.epochs import nominal_period
from sumhe.frontend.measurements import (
    azimuth_measurement,
    can_allowance,
    fix_sigmas,
    gps_speed,
    gps_speed_sigma,
    unmodelled_can_errors,
)
from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, GnssFix, Sample
from sumhe.model.su import SuModel, antenna_azimuth
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Grid:
    """Data of one estimation window on its step grid (``N`` steps, ``n`` outputs of the model).

    ``y`` holds the outputs (positions in the local frame, m; angles rad; CAN SI) with 0 where missing;
    ``avail`` says which are present; ``allow`` is each output's error allowance (its unit) where present.
    ``can_speed``/``can_yaw_rate`` are the CAN values on the grid (NaN where missing).
    """

    t: NDArray[np.float64]
    y: NDArray[np.float64]
    avail: NDArray[np.bool_]
    allow: NDArray[np.float64]
    can_speed: NDArray[np.float64]
    can_yaw_rate: NDArray[np.float64]
    frame: LocalFrame

    @property
    def h(self) -> NDArray[np.float64]:
        """Step lengths (s), ``N - 1`` of them."""
        return np.diff(self.t)

    @property
    def n_steps(self) -> int:
        return len(self.t)

    @property
    def gps(self) -> NDArray[np.bool_]:
        """Steps with a GNSS position (of antenna 1)."""
        return self.avail[:, 0]


def check_samples(samples: Sequence[Sample]) -> None:
    """Raise EstimatorInputError for input no estimator can use: empty, one sample, NaN, time going back."""
    if len(samples) < 2:
        raise EstimatorInputError(f"need at least 2 samples, got {len(samples)}")
    prev = -math.inf
    for i, s in enumerate(samples):
        if not isinstance(s, GnssFix | CanSample):
            raise EstimatorInputError(f"sample {i}: not a GnssFix or CanSample: {type(s).__name__}")
        if not math.isfinite(s.t):
            raise EstimatorInputError(f"sample {i}: time is not finite: {s.t!r}")
        if s.t < prev:
            raise EstimatorInputError(f"sample {i}: time goes backwards ({s.t:.3f} s after {prev:.3f} s)")
        prev = s.t
        if isinstance(s, CanSample) and not math.isfinite(s.value):
            raise EstimatorInputError(f"sample {i}: CAN {s.quantity} is not finite: {s.value!r}")
        if isinstance(s, GnssFix) and s.valid:
            for name in ("lat_deg", "lon_deg"):
                value = getattr(s, name)
                if value is None or not math.isfinite(value):
                    raise EstimatorInputError(f"sample {i}: valid fix with {name} = {value!r}")


def step_times(anchors: NDArray[np.float64], t_lo: float, t_hi: float, period: float) -> NDArray[np.float64]:
    """The grid: ``anchors`` (GNSS epochs, s), widened to [t_lo, t_hi] and with gaps filled at ``period``."""
    pts = np.unique(anchors)
    if pts[0] - t_lo > 0.5 * period:
        pts = np.concatenate([[t_lo], pts])
    if t_hi - pts[-1] > 0.5 * period:
        pts = np.concatenate([pts, [t_hi]])
    out = [pts[:1]]
    for a, b in itertools.pairwise(pts):
        n = round((b - a) / period)
        if n >= 2 and b - a > 1.5 * period:
            out.append(np.linspace(a, b, n + 1)[1:])
        else:
            out.append(np.array([b]))
    return np.concatenate(out)


def build_grid(
    samples: Sequence[Sample],
    model: SuModel,
    settings: EstimationSettings,
    frame: LocalFrame | None = None,
) -> Grid:
    """Check the samples and put them on the step grid of ``model``; EstimatorInputError if unusable.

    ``frame`` defaults to a local frame at the first valid fix. Fixes are projected into it at the datum's
    height ``frame.alt0_m`` (a level road; NMEA altitudes are above the geoid, not the ellipsoid, and mixing
    the two moves positions by ``dh * distance / R_earth``). Fixes of antenna 2 are used by ``su7`` only;
    Fix times ``t`` are their measurement times (:func:`sumhe.io.fixtime.stamp_fix`); CAN times are moved back
    by each quantity's age (``settings.can.delay_s``, and ``speed_delay_s`` more for the speed).
    """
    check_samples(samples)
    fixes = [s for s in samples if isinstance(s, GnssFix)]
    ant1 = [f for f in fixes if f.antenna != 2]
    ant2 = [f for f in fixes if f.antenna == 2 and model.antennas == 2]
    valid1 = [f for f in ant1 if f.valid]
    if len(valid1) < 2:
        raise EstimatorInputError(f"need at least 2 valid GNSS positions in the window, got {len(valid1)}")
    if frame is None:
        first = valid1[0]
        frame = LocalFrame(float(first.lat_deg), float(first.lon_deg), first.alt_m or 0.0)  # type: ignore[arg-type]
    cans = [s for s in samples if isinstance(s, CanSample)]
    t_can = {q: np.array([s.t - settings.can.delay_of(q) for s in cans if s.quantity == q]) for q in CAN_USED}
    v_can = {q: np.array([s.value for s in cans if s.quantity == q]) for q in CAN_USED}
    epochs = np.array([f.t for f in ant1])
    t_all = np.concatenate([epochs, *t_can.values()])
    period = nominal_period(np.diff(np.unique(epochs)), settings.gnss.period_s)
    t = step_times(epochs, float(t_all.min()), float(t_all.max()), period)
    n_out = model.n_outputs
    y = np.zeros((len(t), n_out))
    avail = np.zeros((len(t), n_out), dtype=bool)
    allow = np.ones((len(t), n_out))
    k_sig = settings.estimator.r_cap_sigmas
    j_east, j_north = model.j_position
    antenna2 = (model.outputs.index("px2"), model.outputs.index("py2")) if model.antennas == 2 else ()
    for group, cols in ((valid1, (j_east, j_north)), ([f for f in ant2 if f.valid], antenna2)):
        if not group:
            continue
        tf = np.array([f.t for f in group])
        k = _nearest(t, tf, 0.5 * period)
        ok = k >= 0
        enu = frame.to_enu([f.lat_deg for f in group], [f.lon_deg for f in group], frame.alt0_m)
        sigmas = _fix_sigmas(group, settings)
        for c, col in enumerate(cols):
            y[k[ok], col] = enu[ok, c]
            avail[k[ok], col] = True
            allow[k[ok], col] = k_sig * sigmas[c][ok]
    can_speed, can_yaw = (can_on_grid(t_can[q], v_can[q], t, settings.can.max_gap_s) for q in CAN_USED)
    _angle_output(model, settings, t, y, avail, allow, valid1, can_speed, can_yaw, period)
    j = model.j_gps_speed
    if j is not None:
        k = _nearest(t, np.array([f.t for f in valid1]), 0.5 * period)
        ok = k >= 0
        speed = gps_speed(np.array([_or_nan(f.speed_mps) for f in valid1])[ok], can_speed[k[ok]], settings.gnss)
        measured = np.isfinite(speed)
        y[k[ok][measured], j], avail[k[ok][measured], j] = speed[measured], True
        allow[:, j] = k_sig * gps_speed_sigma(settings.gnss)
    i_v, i_w = model.j_can_speed, model.j_can_yaw_rate
    for col, values in ((i_v, can_speed), (i_w, can_yaw)):
        ok = np.isfinite(values)
        y[ok, col] = values[ok]
        avail[ok, col] = True
    c = settings.can
    extra = unmodelled_can_errors(can_speed, c, model.i_scale is not None, model.i_bias is not None)
    allow[:, i_v] = can_allowance(c.speed_quantum_mps, c.speed_sigma_mps, k_sig) + extra[0]
    allow[:, i_w] = can_allowance(c.yaw_rate_quantum_rps, c.yaw_rate_sigma_rps, k_sig) + extra[1]
    log.debug("grid: %d steps over %.2f s, %d with GNSS", len(t), t[-1] - t[0], int(avail[:, j_east].sum()))
    return Grid(t=t, y=y, avail=avail, allow=allow, can_speed=can_speed, can_yaw_rate=can_yaw, frame=frame)


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else value


def _fix_sigmas(fixes: Sequence[GnssFix], settings: EstimationSettings) -> tuple[NDArray, NDArray]:
    """The fixes' 1-sigma errors (east, north), m (:func:`~sumhe.frontend.measurements.fix_sigmas`)."""
    return fix_sigmas(  # type: ignore[no-any-return]
        np.array([f.quality for f in fixes]),
        np.array([_or_nan(f.hdop) for f in fixes]),
        np.array([_or_nan(f.sigma_lon_m) for f in fixes]),
        np.array([_or_nan(f.sigma_lat_m) for f in fixes]),
        settings.gnss,
    )


def _nearest(t: NDArray[np.float64], tf: NDArray[np.float64], tol: float) -> NDArray[np.int64]:
    """Index of the grid step nearest to each time in ``tf``; -1 where farther than ``tol``."""
    k = np.clip(np.searchsorted(t, tf), 1, len(t) - 1)
    k = np.where(np.abs(t[k - 1] - tf) <= np.abs(t[k] - tf), k - 1, k)
    return np.where(np.abs(t[k] - tf) <= tol + 1e-9, k, -1)


def _angle_output(
    model: SuModel,
    settings: EstimationSettings,
    t: NDArray[np.float64],
    y: NDArray[np.float64],
    avail: NDArray[np.bool_],
    allow: NDArray[np.float64],
    fixes: list[GnssFix],
    can_speed: NDArray[np.float64],
    can_yaw: NDArray[np.float64],
    period: float,
) -> None:
    """Fill the azimuth output in place: xi of the antenna pair (su7) or the receiver's heading/course (su5).

    The allowance adds half a step of turning, ``h |omega| / 2``: with the paper's Euler steps the model's
    azimuth is the chord direction of the step, half a step behind the instantaneous one.
    """
    j = model.angle_outputs[0]
    h = np.concatenate([np.diff(t), [period]])
    turn = 0.5 * h * np.abs(np.nan_to_num(can_yaw))
    k_sig = settings.estimator.r_cap_sigmas
    if model.antennas == 2:
        both = avail[:, 0] & avail[:, 2]
        y[both, j] = antenna_azimuth(y[both, 0], y[both, 1], y[both, 2], y[both, 3])
        avail[both, j] = True
        allow[both, j] = (allow[both, 0] + allow[both, 2]) * math.sqrt(2) / settings.vehicle.antenna_distance_m + turn[
            both
        ]
        return
    k = _nearest(t, np.array([f.t for f in fixes]), 0.5 * period)
    for f, kk in zip(fixes, k, strict=True):
        if kk < 0:
            continue
        speed = f.speed_mps if f.speed_mps is not None else float(can_speed[kk])
        angle = azimuth_measurement(f.course_rad, f.heading_rad, speed, settings.gnss, f.heading_sigma_rad)
        if angle is not None:
            y[kk, j], avail[kk, j], allow[kk, j] = angle[0], True, k_sig * angle[1] + turn[kk]
