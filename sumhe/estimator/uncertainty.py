"""Error estimates of an estimate, as gpsd defines them (gpsd_json(5), TPV): 95 % confidence, metres, m/s, degrees.

Every estimator reports its own 1-sigma figures in a :class:`Spread` (the Kalman family from its covariance, the
particle filter from its particles' spread, dead reckoning from its growth model, the MHE from the covariance of
its window's newest state); :func:`gpsd_errors` turns them into what the sinks send, with a Gaussian error assumed:

* ``epx``/``epy``: the per-axis 95 % half-width (east = longitude, north = latitude): ``1.96 sigma``;
* ``eph``: the radius of the circle centred at the estimate that holds the 2-D error with probability 0.95 (for a
  circular error ``sqrt(chi2_2(0.95)) sigma = 2.45 sigma``; for an elliptic one the exact radius, found by
  :func:`radius_95`);
* ``eps``: ``1.96`` sigma of the speed; ``epd``: ``1.96`` sigma of the track (rad here, degrees at the edge);
* for NMEA GST: the 1-sigma error ellipse (semi-major, semi-minor, orientation of the semi-major axis clockwise
  from true north) and the per-axis sigmas.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from scipy.optimize import brentq
from scipy.special import ndtr

from sumhe.messages import ErrorEstimate

CONFIDENCE = 0.95
K1 = NormalDist().inv_cdf(0.5 + 0.5 * CONFIDENCE)
"""Sigmas of a 1-D 95 % interval (1.96)."""
K2 = math.sqrt(-2.0 * math.log1p(-CONFIDENCE))
"""Sigmas of a 2-D circular 95 % radius: the square root of the chi-square (2 dof) 95 % quantile (2.45)."""
_UNIT = np.linspace(-1.0, 1.0, 401)


@dataclass(frozen=True, slots=True)
class Spread:
    """1-sigma figures of an estimate: the position covariance (east variance, north variance, their covariance;
    m^2), the speed's sigma (m/s) and the azimuth's (rad)."""

    var_east_m2: float
    var_north_m2: float
    cov_en_m2: float
    sigma_speed_mps: float
    sigma_azimuth_rad: float

    @classmethod
    def from_covariance(cls, P: np.ndarray, east: int, north: int, speed: int, azimuth: int) -> Spread:
        """The figures of the rows ``east``, ``north``, ``speed`` and ``azimuth`` of a state covariance ``P``."""
        return cls(
            float(P[east, east]),
            float(P[north, north]),
            float(P[east, north]),
            math.sqrt(max(float(P[speed, speed]), 0.0)),
            math.sqrt(max(float(P[azimuth, azimuth]), 0.0)),
        )

    def ellipse(self) -> tuple[float, float, float]:
        """The 1-sigma error ellipse: semi-major (m), semi-minor (m), orientation of the semi-major axis (rad,
        clockwise from north, in [0, pi))."""
        a, b, c = self.var_east_m2, self.var_north_m2, self.cov_en_m2
        mean, half = 0.5 * (a + b), math.hypot(0.5 * (a - b), c)
        major, minor = math.sqrt(max(mean + half, 0.0)), math.sqrt(max(mean - half, 0.0))
        # the major axis direction (east, north) = (c, major^2 - a) or (major^2 - b, c); azimuth = atan2(east, north)
        orient = 0.5 * math.atan2(2.0 * c, b - a)
        return major, minor, orient % math.pi

    def grown(self, var_east_m2: float, var_north_m2: float) -> Spread:
        """The spread with independent position errors of these variances (m^2) added."""
        return Spread(
            self.var_east_m2 + var_east_m2,
            self.var_north_m2 + var_north_m2,
            self.cov_en_m2,
            self.sigma_speed_mps,
            self.sigma_azimuth_rad,
        )


def exact_radius_95(sigma_major_m: float, sigma_minor_m: float) -> float:
    """The radius (m) of the circle that holds a zero-mean 2-D Gaussian error with the given principal sigmas with
    probability 0.95: ``P(r) = E_x[2 Phi(sqrt(r^2 - s1^2 x^2) / s2) - 1 ; |s1 x| < r]`` (``x`` standard normal, the
    error along the major axis), integrated on a fixed grid and solved for ``P(r) = 0.95`` between the answers of
    a 1-D error (``1.96 s1``) and of a circular one (``2.45 s1``)."""
    s1, s2 = max(sigma_major_m, 0.0), max(sigma_minor_m, 0.0)
    if s1 <= 0.0:
        return 0.0
    if s2 <= 1e-3 * s1:
        return K1 * s1
    if s1 - s2 <= 1e-6 * s1:
        return K2 * s1

    def excess(r: float) -> float:
        x = _UNIT * (r / s1)
        inner = 2.0 * ndtr(np.sqrt(np.maximum(r * r - (s1 * x) ** 2, 0.0)) / s2) - 1.0
        return float(np.trapezoid(np.exp(-0.5 * x * x) * inner, x)) / math.sqrt(2.0 * math.pi) - CONFIDENCE

    lo, hi = K1 * s1, K2 * s1
    if excess(lo) >= 0.0 or excess(hi) <= 0.0:  # quadrature at the ends of the range: take the nearer end
        return lo if excess(lo) >= 0.0 else hi
    return float(brentq(excess, lo, hi, xtol=1e-4 * s1))


_RATIOS = np.linspace(0.0, 1.0, 201)
_RADII = np.array([exact_radius_95(1.0, q) for q in _RATIOS])


def radius_95(sigma_major_m: float, sigma_minor_m: float) -> float:
    """:func:`exact_radius_95` from a table over the ratio of the sigmas (interpolated: within 0.2 %; the
    estimates come at CAN rate)."""
    s1 = max(sigma_major_m, 0.0)
    if s1 <= 0.0:
        return 0.0
    return s1 * float(np.interp(min(max(sigma_minor_m, 0.0) / s1, 1.0), _RATIOS, _RADII))


def gpsd_errors(spread: Spread) -> ErrorEstimate:
    """gpsd's error figures of a spread (module docstring)."""
    major, minor, orient = spread.ellipse()
    sigma_east, sigma_north = math.sqrt(max(spread.var_east_m2, 0.0)), math.sqrt(max(spread.var_north_m2, 0.0))
    return ErrorEstimate(
        eph_m=radius_95(major, minor),
        epx_m=K1 * sigma_east,
        epy_m=K1 * sigma_north,
        eps_mps=K1 * spread.sigma_speed_mps,
        epd_rad=min(K1 * spread.sigma_azimuth_rad, math.pi),
        sigma_major_m=major,
        sigma_minor_m=minor,
        orient_rad=orient,
        sigma_east_m=sigma_east,
        sigma_north_m=sigma_north,
    )
