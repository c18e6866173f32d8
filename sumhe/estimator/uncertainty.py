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

from sumhe.floats import interp
from sumhe.messages import ErrorEstimate
from sumhe.records import quick_init

CONFIDENCE = 0.95
K1 = NormalDist().inv_cdf(0.5 + 0.5 * CONFIDENCE)
"""Sigmas of a 1-D 95 % interval (1.96)."""
K2 = math.sqrt(-2.0 * math.log1p(-CONFIDENCE))
"""Sigmas of a 2-D circular 95 % radius: the square root of the chi-square (2 dof) 95 % quantile (2.45)."""


@quick_init
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

    def scaled(self, factor: float) -> Spread:
        """The spread with the position covariance ``factor`` times as large (speed and azimuth as they are)."""
        return Spread(
            factor * self.var_east_m2,
            factor * self.var_north_m2,
            factor * self.cov_en_m2,
            self.sigma_speed_mps,
            self.sigma_azimuth_rad,
        )

    def grown(self, var_east_m2: float, var_north_m2: float, cov_en_m2: float = 0.0) -> Spread:
        """The spread with a position error of these variances and covariance (m^2) added."""
        return Spread(
            self.var_east_m2 + var_east_m2,
            self.var_north_m2 + var_north_m2,
            self.cov_en_m2 + cov_en_m2,
            self.sigma_speed_mps,
            self.sigma_azimuth_rad,
        )


def along(sigma_m: float, azimuth_rad: float) -> tuple[float, float, float]:
    """The position covariance (east variance, north variance, their covariance; m^2) of an error of ``sigma_m``
    (m, 1-sigma) along the azimuth ``azimuth_rad`` (rad, clockwise from north: east = sin, north = cos)."""
    east, north = sigma_m * math.sin(azimuth_rad), sigma_m * math.cos(azimuth_rad)
    return east * east, north * north, east * north


def exact_radius_95(sigma_major_m: float, sigma_minor_m: float) -> float:
    """The radius (m) of the circle that holds a zero-mean 2-D Gaussian error with the given principal sigmas with
    probability 0.95 (:func:`_unit_radii_95`)."""
    s1, s2 = max(sigma_major_m, 0.0), max(sigma_minor_m, 0.0)
    if s1 <= 0.0:
        return 0.0
    return s1 * float(_unit_radii_95(np.array([min(s2 / s1, 1.0)]))[0])


def _unit_radii_95(ratios: np.ndarray) -> np.ndarray:
    """The 95 % radii of zero-mean 2-D Gaussian errors of major sigma 1 and minor sigmas ``ratios`` (in [0, 1]).

    In polar form the error is ``rho (cos a, q sin a)`` with ``rho^2`` chi-square (2 dof) and ``a`` uniform,
    independent, so ``P(r) = E_a[1 - exp(-r^2 / (2 c(a)))]`` with ``c = cos^2 a + q^2 sin^2 a``: a smooth periodic
    mean, exact to rounding with the midpoint rule on :data:`_ANGLES`, and its derivative ``E_a[(r / c) exp(-r^2 /
    (2 c))]`` in closed form. Newton's method from the middle of ``[1.96, 2.45]`` (a 1-D error's answer, a circular
    one's) solves ``P(r) = 0.95`` for all ratios at once."""
    c = np.cos(_ANGLES) ** 2 + np.square(np.asarray(ratios, dtype=float))[:, None] * np.sin(_ANGLES) ** 2
    r = np.full(c.shape[0], 0.5 * (K1 + K2))
    for _ in range(_NEWTON_STEPS):
        tail = np.exp(-0.5 * r[:, None] ** 2 / c)
        step = (1.0 - CONFIDENCE - tail.mean(axis=1)) / (r[:, None] / c * tail).mean(axis=1)
        r = np.clip(r - step, K1, K2)
    return r


_ANGLES = (np.arange(512) + 0.5) * (0.5 * math.pi / 512)
"""Quadrature nodes of :func:`_unit_radii_95` over a quarter turn (the mean is symmetric in both axes)."""
_NEWTON_STEPS = 8
"""Newton steps of :func:`_unit_radii_95`: converged to rounding after five on every ratio in [0, 1]."""


_RATIOS = np.linspace(0.0, 1.0, 201)
_RADII = _unit_radii_95(_RATIOS)
_RATIO_LIST, _RADIUS_LIST = _RATIOS.tolist(), _RADII.tolist()


def radius_95(sigma_major_m: float, sigma_minor_m: float) -> float:
    """:func:`exact_radius_95` from a table over the ratio of the sigmas (interpolated: within 0.2 %; the
    estimates come at CAN rate)."""
    s1 = max(sigma_major_m, 0.0)
    if s1 <= 0.0:
        return 0.0
    return s1 * interp(min(max(sigma_minor_m, 0.0) / s1, 1.0), _RATIO_LIST, _RADIUS_LIST)


def gpsd_errors(spread: Spread) -> ErrorEstimate:
    """gpsd's error figures of a spread (module docstring)."""
    major, minor, orient = spread.ellipse()
    sigma_east, sigma_north = math.sqrt(max(spread.var_east_m2, 0.0)), math.sqrt(max(spread.var_north_m2, 0.0))
    # positional (eph, epx, epy, eps, epd, major, minor, orient, sigma east, north): 0.39 against 0.65 us by keywords
    return ErrorEstimate(
        radius_95(major, minor), K1 * sigma_east, K1 * sigma_north, K1 * spread.sigma_speed_mps,
        min(K1 * spread.sigma_azimuth_rad, math.pi), major, minor, orient, sigma_east, sigma_north
    )  # fmt: skip


INNOVATION_MEMORY_S = 300.0
"""Time constant (s) of :class:`InnovationScale`'s exponential forgetting of the growth scale: a few GNSS error
correlation times (it rests on one fix after each gap)."""
FIX_MEMORY_S = 20.0
"""Time constant (s) of the forgetting of the scale at a fix: an estimator's lag behind the fixes comes and goes
with the manoeuvres (a turn, a braking: 5-20 s), and a scale averaged over minutes spread it over the straight
stretches between them (with 300 s, 82 % of the EKF's errors within ``eph`` with GPS on the realistic drives; with
30 s, 90 %; with 30 s and :class:`~sumhe.estimator.base.Receiver` no longer counting the fixes' white error twice,
89.0 %, whose heavy tail the over-count had covered; with 20 s, the length of the longer manoeuvres, 91.2 %)."""
MIN_GROWTH_SCALE, MAX_GROWTH_SCALE = 1e-3, 1e5
"""The range of the growth scale (:class:`InnovationScale`): a growth the gaps' fixes found all but nil, one they
found wider than any estimator's own by orders of magnitude."""
GROWTH_PRIOR_SD = math.log(100.0)
"""The standard deviation of the growth scale's logarithm before any gap (:class:`InnovationScale`): the estimator's
own growth right within a factor of 100 (variance), a weak prior that only keeps gaps that say nothing of the
growth (a fix or two missed, whose innovation is all the fix's and the estimate's own error) from moving it."""
GAP_PERIODS = 2.5
"""A fix more than this many GNSS periods after the previous one used ends a gap (:class:`InnovationScale`)."""
OUTLIER_CAP = -math.log1p(-0.9999)
"""An innovation counts at most this many times its expected square (:class:`InnovationScale`): the 99.99 %
quantile of ``|nu|^2 / E|nu|^2`` for a 2-D Gaussian (``chi2_2(0.9999) / 2 = 9.2``), the probability of the peers'
innovation gate."""


class _Ratio:
    """A ratio of two sums that forget exponentially in time (time constant ``memory_s``)."""

    def __init__(self, memory_s: float) -> None:
        self.memory_s = memory_s
        self.t, self.num, self.den = math.nan, 0.0, 0.0

    def add(self, t: float, num: float, den: float) -> None:
        decay = math.exp(-max(t - self.t, 0.0) / self.memory_s) if math.isfinite(self.t) else 0.0
        self.t, self.num, self.den = t, decay * self.num + num, decay * self.den + den

    def at_least_one(self) -> float:
        """``num / den``, at least 1 (1 before any ``den``)."""
        return max(self.num / self.den, 1.0) if self.den > 0.0 else 1.0

    def mean(self, default: float) -> float:
        """``num / den`` (``default`` before any ``den``)."""
        return self.num / self.den if self.den > 0.0 else default


_LOG_SCALES = np.linspace(math.log(MIN_GROWTH_SCALE), math.log(MAX_GROWTH_SCALE), 241)
_SCALES = np.exp(_LOG_SCALES)


_SHARES = (np.arange(32) + 0.5) / 32
"""Midpoints of [0, 1] over which :class:`_ScaleLikelihood` averages an unknown share of an expected square (the
midpoint rule: the likelihood is smooth in the share)."""


class _ScaleLikelihood:
    """The log-likelihood of a variance scale ``s`` on a grid of ``ln s`` over [:data:`MIN_GROWTH_SCALE`,
    :data:`MAX_GROWTH_SCALE`], from 2-D errors of variance (trace) ``fixed + u unsure + s growth`` each, ``u`` an
    unknown share, uniform in [0, 1], summed with weights that forget exponentially in time (time constant
    ``memory_s``)."""

    def __init__(self, memory_s: float) -> None:
        self.memory_s = memory_s
        self.t = math.nan
        self.loglik = np.zeros_like(_LOG_SCALES)
        self.weight, self.weight2 = 0.0, 0.0
        self.estimate = 1.0

    def add(self, t: float, square: float, fixed: float, growth: float, prior: float, unsure: float = 0.0) -> None:
        """One error of square ``square`` (m^2) whose expected square is ``T = fixed + u unsure + s growth`` (m^2,
        traces; ``u`` unknown, uniform in [0, 1]): its 2-D Gaussian likelihood ``exp(-|nu|^2 / T) / T`` averaged
        over ``u`` (:data:`_SHARES`), its logarithm added; the estimate the maximum of the posterior under a
        log-normal prior at ``prior`` of :data:`GROWTH_PRIOR_SD` (refined between grid points by the parabola
        through the three nearest)."""
        decay = math.exp(-max(t - self.t, 0.0) / self.memory_s) if math.isfinite(self.t) else 0.0
        total = fixed + (_SHARES * unsure)[:, None] + _SCALES * growth
        each = -np.log(total) - square / total
        top = each.max(axis=0)
        self.t = t
        self.loglik = decay * self.loglik + top + np.log(np.exp(each - top).mean(axis=0))
        self.weight, self.weight2 = decay * self.weight + 1.0, decay * decay * self.weight2 + 1.0
        post = self.loglik - 0.5 * np.square((_LOG_SCALES - math.log(prior)) / GROWTH_PRIOR_SD)
        k = int(np.clip(np.argmax(post), 1, len(post) - 2))
        left, mid, right = post[k - 1 : k + 2]
        curve = left - 2.0 * mid + right
        step = 0.5 * (left - right) / curve if curve < 0.0 else 0.0
        log_s = _LOG_SCALES[k] + min(max(step, -1.0), 1.0) * (_LOG_SCALES[1] - _LOG_SCALES[0])
        self.estimate = math.exp(min(max(log_s, _LOG_SCALES[0]), _LOG_SCALES[-1]))

    @property
    def count(self) -> float:
        """The effective number of errors (Kish: ``(sum w)^2 / sum w^2`` of their forgetting weights)."""
        return self.weight**2 / self.weight2 if self.weight2 > 0.0 else 0.0


class InnovationScale:
    """On-line consistency scales of an estimator's own position covariance, from the innovations of the fixes it
    uses (covariance matching: Mehra 1972, Mohamed & Schwarz 1999).

    Before a fix is used, the estimator's estimate at the fix's time is a prediction whose own position covariance
    ``P`` (by the estimator's account) is the covariance ``P0`` it had at the previous fix used plus what it grew
    by since, ``G``. A fix's error is a slow offset the estimate shares (GNSS errors are correlated over minutes:
    the estimator follows it, and :class:`~sumhe.estimator.base.Receiver` adds it to every estimate) plus a fast,
    white part of variance ``W``; so the innovation ``nu = z - p`` has ``E|nu|^2 = tr P + W`` when the estimator's
    figures are right. ``W`` is what the innovations say of it: half the mean squared change of the residual (the
    fix less the estimate that used it) from one fix to the next (the estimate moves little in one period, the
    white errors of two fixes are
    independent; an upper bound, so the excess below errs low), at most the fix's own ``tr R``, ``tr R`` until two
    consecutive fixes were seen (a receiver whose errors are white, as the covariance matching of the papers
    assumes). Subtracting all of ``tr R`` instead took the slow offset, which the innovations cannot see, for the
    estimator's: an EKF lagging a receiver with correlated errors by metres kept a scale of 1 (81.6 % of its errors
    within ``eph`` with GPS on the realistic drives).

    Two scales make the figures right, each the ratio, over the recent fixes, of what ``|nu|^2 - W`` says to what
    the estimator said:

    * :attr:`scale`, of the covariance at a fix, from the fixes that follow the previous one within
      ``gap_periods`` GNSS periods; there the base class passes the residual of the estimate that used the fix
      and its own covariance (what ``eph`` describes: the estimate, not the prediction before it; 89.4 against
      89.9 % with GPS for the EKF on the realistic drives). A filter tuned for accuracy with little process noise,
      whose covariance says centimetres where it lags the fixes by metres, gets a large one. It forgets in
      ``fix_memory_s`` (20 s: :data:`FIX_MEMORY_S`). At least 1: below, the innovations' share of the fixes'
      slow error (which they cannot see, below) would be taken for a licence to shrink. That floor is the
      estimator's own statistics', not a considered parameter's (never estimated: the EKF's receiver heading
      offset, read from its bound): such an offset is no error of the fixes but a lag of the estimate behind them,
      which the innovations see whole, so the part of the covariance at a fix it makes is checked both ways, as the
      growth is (:meth:`at_fix_m2`). On the shared real drive (its fixes after 400 s) the EKF's covariance at its
      fixes said 9.6 m^2 across the track (0.3 m^2 without the offset) where the mean squared residual there was
      4.7 m^2 across (the fixes 1.5 m to the right on the mean: the offset's lag) and 2.9 m^2 along: a ratio of
      0.6-0.7, held at 1, left 98.9 % of the removed fixes of its 10 s outages within ``eph`` ([96.7-100] over the
      outages), 97.8 % without the floor on the offset's part ([95.5-100]);
    * :attr:`growth_scale`, of the growth since, from the fixes after a longer gap (missed fixes, outages), with the
      change of the innovation over the gap: the prediction's innovation less the residual of the estimate that used the
      fix before the gap, whose expected square is ``2 W + s tr G`` for a growth scale ``s``, plus the change of the
      fixes' slow error over the gap (below; the estimate carries its lag behind the fixes through the gap, and the
      lag cancels; the white errors of both fixes are left), or, where
      that residual is unknown (the estimator started over there), the prediction's innovation, whose expected square is
      ``scale tr P0 + W + s tr G`` plus that change. Against the prediction alone the lag at the gap's start counted
      by its expected square, the scale at a fix, which follows a manoeuvre or the first seconds of a drive only within
      ``fix_memory_s``: 8 s into a realistic drive, the MHE's scale at a fix still 1 and its residuals metres, a 0.3 s
      gap made the growth scale 1315 and the next 10 s outage's median ``eph`` 281 m against errors of 3 m. With the
      change, on the realistic drives, 97.9 against 98.0 % of the MHE's errors in outages within ``eph`` (3.07 against
      3.40 times the median error; with GPS 97.9 against 98.1 %), 95.0 against 97.9 % of the EKF's (2.57 against 3.49
      times), 81.8 against 89.0 % of the particle filter's (2.57 against 3.89 times; its gaps find 0.04 to 600 times its
      own growth); on the shared real drive the MHE's 91.8, 90.5 and 92.3 % against 91.2, 90.3 and 92.0 % (10, 30, 60 s
      outages), the EKF's 97.8, 94.1 and 82.8 against 94.0, 93.0 and 79.9 %, gtsam-fls's 97.8, 95.2 and 91.0 against
      95.6, 93.6 and 89.7 % (89.5 against 75.4 % in the realistic outages), the particle filter's 79.7, 84.4 and 82.9
      against 92.3, 83.9 and 77.5 % (it lags the real drive's fixes by 6-8 m and carries that lag through the gaps,
      which the old rule's growth scale, 7 to 70, had taken for growth; its error at the outage's start is then that
      lag, which ``scale tr P0`` describes only where its own trace is its recent mean: a ratio of sums, the scale
      is the mean squared residual over the mean own trace, and the particle filter's trace swings 100-fold, 0.03 to
      2.9 m^2 at the fixes before the outages, while its residuals stay metres; before 14 of the real drive's 19
      10 s outages ``scale tr P0`` was under the recent mean squared residual, two thirds of it at the median; what
      was tried against it and why it is not landed: docs/error-estimates.md). ``s`` is the maximum of the 2-D
      Gaussian likelihood of the gaps' changes (forgetting in ``memory_s``, on a grid of ``ln s`` over
      [:data:`MIN_GROWTH_SCALE`, :data:`MAX_GROWTH_SCALE`]) under a weak log-normal prior at :attr:`scale`
      (:data:`GROWTH_PRIOR_SD`), so the growth
      through an outage is checked against what the fixes at its end say; until a gap has been seen it is :attr:`scale`
      (an estimator found overconfident at its fixes is taken as overconfident in its growth: the EKF's first outage of
      a drive came before any gap; 79.7 against 82.2 % of its errors in outages within ``eph``). Both ways: after a long
      gap the growth dominates the innovation, and an estimator whose own growth is too wide is told so as one whose
      growth is too narrow is (the MHE, whose growth comes from its bounds read as sigmas, had 0.01-0.3 of it on the
      shared real drive, where, held at 1, its ``eph`` was 4.3-5.3 times its median error against the removed fixes). A
      likelihood, not a ratio of sums ``sum (|nu|^2 - scale tr P0 - W) / sum tr G``: a gap of a fix or two missed, whose
      growth is nothing beside the rest of the innovation, says nothing of ``s`` and leaves it where it was, where the
      ratio took its negative excess over a tiny growth for a scale at the floor (one such gap, then a 56 s outage of
      the EKF on a realistic highway drive with an ``eph`` of 5 m against errors to 31 m) or its positive one for a
      scale of 10^4. With it, on the realistic drives, 87.4 against 80.7 % of the EKF's errors in outages within ``eph``
      (2.8 against 2.4 times the median error), and 98.3 against 91.5 % of the MHE's (4.7 against 2.8 times: the floor
      had hidden that the MHE's own growth rises faster with time than its errors, which no one scale mends); on the
      shared real drive the MHE's 92.3, 90.5 and 92.2 % against 93.4, 89.0 and 89.9 % (10, 30, 60 s outages; 3.0, 2.8
      and 2.7 against 3.4, 2.7 and 2.5 times), the EKF's 91.2, 92.5 and 82.1 against 95.1, 93.0 and 78.0 %.

    The growth the scale applies to is the larger of the estimator's own and ``drift_m2``, what a drift of the CAN
    calibration as the config allows makes of it (:func:`drift_variance`, passed by the base class): a filter whose
    covariance hardly grows through an outage (the EKF tuned for accuracy: 4.3 to 5.0 m of ``eph`` over a 56 s
    outage of a realistic highway drive while its error reached 31 m) is then measured against a growth the
    sensors can make, not against nothing (79.2 against 80.7 % of the EKF's errors in outages within ``eph`` on
    the realistic drives; the MHE's own growth is larger, and its figures did not change).

    The change of the innovation over a gap holds, beside the growth and the white errors, the change of the fixes'
    slow error (``tr R - W`` each, what :class:`~sumhe.estimator.base.Receiver` adds to every estimate): the
    estimate carried the slow error of the fix before the gap into it, the fix after it has its own. With ``S0``
    and ``S`` those two fixes' slow variances that change's expected square is ``S0 + S - 2 rho sqrt(S0 S)`` =
    ``(sqrt S0 - sqrt S)^2 + 2 (1 - rho) sqrt(S0 S)``, ``(sqrt S0 - sqrt S)^2`` where the two are fully correlated,
    ``S0 + S`` where they are independent (taken as ``2 S``, the fix after the gap's twice, a fix of 7 m before the
    shared real drive's first outage, where the fixes after it said 1 m, had been taken for growth: dead reckoning's
    growth scale 5.4 after that 10 s outage, 3.9 now, its next one's ``eph`` 117.8 m, 99.5 m now, at its end against
    an error of 5.3 m; the rest is that outage's error, 15.5 m, beyond the fix's 7 m and its own growth's 4 m); how
    fast the slow error decorrelates (``rho`` over the gap) the innovations do not say, and a
    correlation time would be a constant no drive pins down, so ``rho`` is taken as unknown, uniform in [0, 1]: the
    likelihood of ``s`` is averaged over it (:class:`_ScaleLikelihood`), and the outlier cap counts its mean. A short
    gap (a fix or two missed, a 5 s outage), whose own growth is decimetres beside the metres by which the slow error
    moves, had taken that change for growth: 8 s into two realistic drives a 0.3 s gap made gtsam-fls's growth scale
    2834 and 3049 (on one, its ``eph`` over the 55 s outage that followed 47 times its error), and the MHE's growth
    scales of 16 and 26, learned from 10 and 30 s outages, widened a 55 s outage of two drives to 6.0 and 6.3 times
    its median error (5.4 and 4.9 times now). With it, on
    the realistic drives, 97.8 against 97.9 % of the MHE's errors in outages within ``eph`` (2.91 against 3.07 times
    the median error; with GPS 98.0 against 97.9 %, 2.93 against 2.97 times), the EKF's 94.8 against 95.0 % (2.32
    against 2.57 times), gtsam-fls's 77.5 against 89.5 % (the two drives' growth scales of thousands had held its
    long outages; 1.70 against 2.86 times), the particle filter's 98.1 against 98.2 % (2.89 against 3.02 times); on
    the shared real drive (10, 30, 60 s outages, against the removed fixes, which hold the slow error's change) the
    MHE's 90.1, 90.3 and 91.9 against 91.8, 90.5 and 92.3 %, the EKF's 98.9, 97.2 and 92.5 against 98.9, 97.4 and
    93.2 %, gtsam-fls's 98.4, 93.6 and 89.5 against 97.8, 95.2 and 91.0 %, the particle filter's 91.2, 86.4 and
    86.2 against 95.6, 90.8 and 86.3 %.

    A growth scale rests on few gaps, one fix each: its growth is taken :attr:`growth_spread` times, the factor of
    the predictive 95 % radius of a variance estimated from that many 2-D errors (6.3 after one gap, 1.1 after
    twenty). On the shared real drive (under the ratio of sums) it took the EKF's errors within ``eph`` from 91.8,
    88.3 and 80.1 % (10, 30, 60 s outages) to 95.1, 93.0 and 79.0 %, and the MHE's from 93.4, 87.9 and 87.1 % to
    93.4, 89.0 and 90.0 %.

    The fix's white part ``W`` is in the calibrated covariance at a fix (the scale is what the innovations say
    beyond it), so :class:`~sumhe.estimator.base.Receiver` adds only the rest of the fix's variance,
    ``tr R - W`` (:meth:`white_m2`), the slow offset that carries from fix to fix: adding all of ``tr R`` counted
    ``W`` twice (the MHE, which follows the fixes, had 98.3 % of its errors within ``eph`` with GPS on the
    realistic drives, 3.0 times its median error; 97.9 % and 2.7 times without; the EKF 90.4 and 91.2 %, with the
    scale at a fix forgetting in 20 s, not 30 s: :data:`FIX_MEMORY_S`).

    Robust to outliers and restarts: after a gap an innovation counts at most ``OUTLIER_CAP`` times the square the
    calibrated prediction expects (the growth scale rests on few fixes, one after each gap: an outlier the gate let
    through, or a filter's re-acquisition, moves it by a bounded step, not by its square; the scale at a fix
    averages hundreds of fixes, where one outlier weighs little and a cap slowed the learning of a real excess), and
    a fix the estimator restarted at is not fed at all (:meth:`~sumhe.estimator.base.StreamEstimator.push`: a
    prediction that was given up says nothing of the covariance of the one that follows). Before these guards a
    24 h soak ended with a growth scale of 247.5, fed by the far first fix after each of 15 gate restarts.

    The sums and the likelihood forget exponentially in time, so the scales follow a change of conditions; the rule is
    the same on every drive, from what each drive's own fixes say.
    """

    def __init__(
        self,
        memory_s: float = INNOVATION_MEMORY_S,
        gap_periods: float = GAP_PERIODS,
        fix_memory_s: float = FIX_MEMORY_S,
    ) -> None:
        if not memory_s > 0.0 or not fix_memory_s > 0.0:
            raise ValueError(f"memory_s, fix_memory_s: must be positive, got {memory_s!r}, {fix_memory_s!r}")
        self.memory_s, self.gap_periods, self.fix_memory_s = memory_s, gap_periods, fix_memory_s
        self.reset()

    def reset(self) -> None:
        self._fix = _Ratio(self.fix_memory_s)
        self._growth = _ScaleLikelihood(self.memory_s)
        self._white = _Ratio(self.memory_s)
        self._last: np.ndarray | None = None
        self._last_r = 0.0
        self._growth_spread = 1.0

    def add(
        self,
        t: float,
        nu: np.ndarray,
        trace_r: float,
        trace_p0: float,
        trace_g: float,
        periods: float,
        drift_m2: float = 0.0,
        residual: np.ndarray | None = None,
    ) -> None:
        """One used fix at ``t`` (s): its innovation ``nu`` (m, east and north) and the trace of its covariance
        ``trace_r``; the prediction's own position covariance as the trace at the previous fix used,
        ``trace_p0``, and the trace of the growth since, ``trace_g`` (m^2); ``periods``: GNSS periods since that
        fix; ``residual``: the fix less the estimate that used it (m; None: ``nu`` after a consecutive fix,
        unknown after a gap)."""
        consecutive = periods <= self.gap_periods
        start, self._last = self._last, residual if residual is not None or not consecutive else nu
        trace_r0, self._last_r = self._last_r, trace_r
        if consecutive and start is not None:
            change = nu - start
            self._white.add(t, 0.5 * float(change @ change), 1.0)
        white = self.white_m2(trace_r)
        if consecutive:
            self._fix.add(t, float(nu @ nu) - white, trace_p0 + trace_g)
        elif (growth := max(trace_g, drift_m2)) > 0.0:
            slow = max(trace_r - white, 0.0)
            slow0 = max(trace_r0 - white, 0.0) if start is not None else slow
            # the change of the fixes' slow errors, correlated 1 to 0: (sqrt S0 - sqrt S)^2 + (0 to 2) sqrt(S0 S)
            unsure = 2.0 * math.sqrt(slow * slow0)
            if start is not None:  # the change over the gap: the estimate's lag behind the fixes at its start cancels
                square = float((nu - start) @ (nu - start))
                fixed = 2.0 * white + (math.sqrt(slow0) - math.sqrt(slow)) ** 2
            else:
                square, fixed = float(nu @ nu), self.scale * trace_p0 + white
            expected = fixed + 0.5 * unsure + self.growth_scale * self.growth_spread * growth
            self._growth.add(t, min(square, OUTLIER_CAP * expected), fixed, growth, self.scale, unsure)
            self._growth_spread = _predictive(self._growth.count)

    def white_m2(self, trace_r: float) -> float:
        """The white part (trace, m^2) of the error of a fix of covariance trace ``trace_r``: half the mean squared
        change of the innovation from one fix to the next, at most ``trace_r`` (all of it until two consecutive
        fixes were seen)."""
        return min(self._white.mean(trace_r), trace_r)

    def skip(self) -> None:
        """A fix not fed (the estimator restarted there): the next one's innovation change is not the white
        errors'."""
        self._last = None

    @property
    def scale(self) -> float:
        """How many times the own position covariance at a fix is too small (>= 1)."""
        return self._fix.at_least_one()

    def at_fix_m2(self, trace_m2: float, considered_m2: float = 0.0) -> float:
        """The calibrated trace (m^2) of an own position covariance at a fix of trace ``trace_m2``, of which
        considered parameters make ``considered_m2``: what the innovations say of it, at least the trace less the
        considered part (:attr:`scale` times the trace where that part is nil; never negative)."""
        return max(self._fix.mean(1.0) * trace_m2, trace_m2 - considered_m2, 0.0)

    @property
    def growth_scale(self) -> float:
        """How many times its growth since a fix is too small (in [:data:`MIN_GROWTH_SCALE`,
        :data:`MAX_GROWTH_SCALE`]; :attr:`scale` until a gap has been seen)."""
        return self._growth.estimate if self._growth.weight > 0.0 else self.scale

    @property
    def growth_spread(self) -> float:
        """How many times the growth's variance must be taken for a 95 % radius that holds with the growth scale
        learned from few gaps (1 before any: the prior then is :attr:`scale`): the predictive 2-D error of a
        variance estimated from ``n`` independent 2-D errors is ``2 F(2, 2n)``-distributed in units of the
        estimate, so the 95 % radius is ``2 F_0.95(2, 2n) / chi2_2(0.95)`` times the Gaussian one (squared; n = 1:
        6.3, 3: 1.7, 20: 1.1)."""
        return self._growth_spread

    def calibrated(
        self,
        spread: Spread,
        at_fix: Spread | None,
        drift_m2: float = 0.0,
        considered_m2: float = 0.0,
    ) -> Spread:
        """An estimate's own spread with its position covariance scaled: ``scale P0 + growth_scale growth_spread
        (P - P0)`` (traces; the covariance keeps its shape; the first term :meth:`at_fix_m2`, of which considered
        parameters make ``considered_m2``), ``at_fix`` the own spread at the newest fix used (None: none yet, all
        of it is ``P0``)."""
        trace = spread.var_east_m2 + spread.var_north_m2
        if trace <= 0.0:
            return spread
        trace0 = min(at_fix.var_east_m2 + at_fix.var_north_m2, trace) if at_fix is not None else trace
        growth = self.growth_scale * self.growth_spread * max(trace - trace0, drift_m2)
        return spread.scaled((self.at_fix_m2(trace0, considered_m2) + growth) / trace)


def drift_variance(elapsed_s: float, speed_mps: float, bias_drift: float, scale_drift: float) -> float:
    """The variance (m^2, across plus along the track) of the dead-reckoning error ``elapsed_s`` s after a fix at
    ``speed_mps`` from the drift alone of a yaw-rate bias and a speed scale that were right at the fix: random
    walks of densities ``bias_drift`` (rad/s per square-root s) and ``scale_drift`` (1 per square-root s). The
    azimuth's error is the bias's integral (variance ``q^2 t^3 / 3``), the position's across the track its integral
    times the speed (``v^2 q^2 t^5 / 20``); along it, the scale's integral times the speed (``v^2 q^2 t^3 / 3``)."""
    t, v = max(elapsed_s, 0.0), speed_mps
    return v * v * (bias_drift**2 * t**5 / 20.0 + scale_drift**2 * t**3 / 3.0)


def _predictive(n: float) -> float:
    """``2 F_0.95(2, 2n) / chi2_2(0.95)`` (:attr:`InnovationScale.growth_spread`), in closed form: the F(2, m)
    distribution's quantile is ``(m / 2) ((1 - p)^(-2 / m) - 1)`` and ``chi2_2(p) = -2 ln(1 - p)`` (``K2^2``)."""
    return 2.0 * n * math.expm1(-math.log1p(-CONFIDENCE) / n) / (K2 * K2)
