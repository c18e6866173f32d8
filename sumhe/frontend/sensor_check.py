"""The CAN yaw rate's and speed's mapping checked on line against the receiver: a sign, an axis or a unit the config
got wrong is said once, at ERROR, naming the key to change.

Other cars' configs get a sensor's convention wrong: an OEM's yaw rate clockwise-positive, a logger's IMU mounted
another way, a speed in mph read as km/h. The estimators cannot tell a wrong sign from a bad fix: with the yaw
rate's sign flipped on the shared real drive the MHE ran 13.6 / 63.9 / 481.6 m off in three 30 s outages and said
only that it kept rejecting fixes and restarting. :class:`SensorCheck` gathers, as the drive goes, the evidence
``sumhe calibrate`` fits offline (:mod:`sumhe.calibration`), with the same functions
(:mod:`sumhe.frontend.alignment`):

* the yaw rate: the rate of the receiver's azimuth between consecutive fixes (its heading, else its course over
  ground above ``MIN_SPEED_MPS``) against the CAN yaw rate over the same interval (:func:`course_lag`), over the
  last :data:`WINDOW_S`; fitted once the azimuth has turned :data:`MIN_TURN_RAD` there, and again after each
  further :data:`REFIT_TURN_RAD` (a drive that does not turn costs no fit), until the yaw-rate scale (true = scale
  x CAN) is told :data:`CHECK_SIGMAS` standard errors from the bounds: the sign flipped (a scale within
  -:data:`YAW_SCALE_PLAUSIBLE`), not this car's yaw rate (a scale of about 0: another axis; or beyond the bounds:
  a unit), or this car's yaw rate; then its gain (CAN = gain x true + bias) and its bias, each until told within
  or outside the estimators' bounds, ``1 +- sensors.can.yaw_rate_gain_max`` (a single axis of an IMU tilted from
  up, a scale a little off) and ``+- sensors.can.yaw_rate_bias_max_rps`` (an uncalibrated gyro's zero-rate
  offset: consumer MEMS parts are rated at 1-20 deg/s), by as many standard errors (:func:`within`); the check ends
  when both are told. A stop tells the bias sooner: the mean of its CAN yaw rates, judged when the car drives off
  (:meth:`SensorCheck._watch_stop`; the fits take the azimuth's 180 deg);
* the speed: the scale of the receiver's speed over ground against the CAN speed, from the fits of the time-offset
  learner (:class:`~sumhe.frontend.alignment.ClockLearner`, every 10 s over 300 s): the CAN speed's scale (CAN = k
  x true, what the estimators' speed-scale state bounds) outside ``1 +- sensors.can.speed_scale_max`` by
  :data:`CHECK_SIGMAS` standard errors and half a CAN speed quantum over the mean speed (a truncated speed reads up
  to that much low): a unit, or a scale a little off;
* the speed's rounding (``sensors.can.speed_rounding``), where the quantum is coarse (at least
  :data:`~sumhe.settings.sensors.COARSE_QUANTUM_MPS`): how much the CAN speed, as the front-end takes it, reads low
  on the mean, fitted beside the scale by the same fits (:attr:`~sumhe.frontend.alignment.LagFit.reads_low`), once
  it tells none (as configured) from half a quantum either way (the other rounding) by :data:`CHECK_SIGMAS`
  (:func:`rounding_wrong`). An OBD-II speed comes in whole km/h, truncated on many cars: it reads 0.14 m/s low on
  the mean, which a speed-scale state takes up only at the speed it learned it at (at 5 m/s after 15 m/s, 0.09
  m/s: 5.6 m in a minute). On the shared real drive the fits said 0.10 +- 0.02 m/s from 339 s after its first fix
  (``sumhe calibrate``: half its 1 km/h, 0.139 m/s).

Each finding is logged once, at ERROR (the rounding's at WARNING: a calibration, not a mapping gone wrong), with the
config key, the fitted value and its standard error, and counted (``yaw_rate_sign_flipped``,
``yaw_rate_not_following``, ``yaw_rate_gain_outside``, ``yaw_rate_bias_outside``, ``speed_scale_outside``,
``speed_rounding_wrong``: the estimator's ``stats()``, which ``sumhe replay`` prints and the daemon's status line
carries). The fallbacks: a flipped sign is unambiguous (the scale's magnitude plausible, 5 standard errors from it):
from the verdict on the front-end turns the yaw rate round (:attr:`SensorCheck.factor`) and the estimator starts
over at that fix afresh (``Epoch.fresh``: its CAN states, output bounds and consistency scales were learned from the
wrong sign); on the shared real drive with ``scale = -1`` the MHE's 10/30 s outages after it came out at 2.22/3.26 m
(2.42/3.60 mapped right; 128/143 m as mapped). A gain out of bounds is undone the same way, the yaw rate multiplied
by the fitted scale (the estimators' gain state takes up what is left of it, within its bounds): a gain the state
cannot reach had the MHE fail its solves and lose the fixes (a simulated town drive read at 0.7 of its yaw rate: 51
m off 20 s into an outage, 1.41 m with the yaw rate undone, 1.93 m mapped right); so is a speed scale out of bounds
(the same drive's speed read as 1.609 of it: the MHE 68 m off in that outage, 1.95 m undone), and a bias out of
bounds, the bias a stop or the fits measured taken off (its yaw rate reading 2.3 deg/s more: 14 m, 1.90 m undone). A
yaw rate that does not follow or a rounding other than configured has no one correction: the estimators keep running
on the config as it is, and their estimates through outages stay as wrong as it until it is changed. (The rounding
corrected from the verdict on was tried: the speed scale the estimators had learned was then off at once, and on the
shared drive the EKF's 10 s outages after it came out worse, 1.63 / 1.17 / 1.16 m at 510 / 630 / 750 s -> 6.25 /
3.23 / 2.87 m; ``docs/error-estimates.md``.)
"""

from __future__ import annotations

import logging
import math
from collections import deque

import numpy as np

from sumhe.frontend.alignment import CHORD_S, MIN_PAIRS, MIN_SPEED_MPS, LagFit, TimeSeries, course_lag, row_array
from sumhe.frontend.can import CanBuffer
from sumhe.frontend.fixes import LocalFix
from sumhe.frontend.measurements import chord_azimuth
from sumhe.frontend.standstill import StopWatch, bias_at_rest
from sumhe.frontend.tally import Tally
from sumhe.settings import EstimationSettings
from sumhe.settings.sensors import COARSE_QUANTUM_MPS

WINDOW_S = 600.0
"""The yaw-rate evidence is the last this many seconds of fixes and CAN yaw rates."""
MIN_TURN_RAD = math.radians(180.0)
"""The azimuth must have turned this much within the window before the yaw rate is judged."""
REFIT_TURN_RAD = math.radians(90.0)
"""The yaw rate is fitted again after the azimuth turned this much more (without a verdict)."""
TURN_STEP_S = 1.0
"""The azimuth's turning is summed over steps of at least this long (s; up to twice it), where its noise adds
little (0.8 deg a step for a course at 5 m/s with 0.05 m/s of Doppler noise)."""
CHECK_SIGMAS = 5.0
"""A verdict needs the fitted scale this many standard errors from the bound it is judged against."""
YAW_SCALE_PLAUSIBLE = (0.5, 2.0)
"""A yaw-rate scale (true = scale x CAN) outside these is not this car's yaw rate as mapped (another axis, or a
unit: deg/s read as rad/s is 57x), as ``sumhe calibrate`` says of it."""
CHECK_LAGS_S = np.round(np.arange(-1.0, 1.0001, 0.1), 6)
"""The lags (s) of the azimuth behind the CAN yaw rate tried: the fit needs the scale at the best, not the lag to a
hundredth."""
CHORD_JITTER = 0.9
"""A chord may be this much shorter than ``CHORD_S[0]``: a 1 Hz receiver's stamps jitter by tens of ms, and its
chords would otherwise span two periods, too far apart to pair (:func:`course_lag`'s ``max_gap_s``)."""
MIN_SPEED_FIXES = 100
"""The speed's scale is judged from fits of at least this many moving fixes."""
ROUNDING_AFTER_S = 300.0
"""The speed's rounding is judged from this far into the data (s) on."""


GAIN_OUTSIDE = (
    "the CAN yaw rate reads %.3f x the receiver's azimuth rate, outside 1 +- sensors.can.yaw_rate_gain_max = %g: %s; "
    "check can.signals.yaw_rate (its scale? a single axis of an IMU tilted from up reads the cosine of the tilt: map "
    "its three rates and accelerations; sumhe calibrate measures it). Until then it is multiplied by %.3f on line from "
    "here, and the estimator starts over at this fix (what it estimated before turned too %s through outages)"
)
"""The log line of a yaw-rate gain outside the bounds (its gain, the bound, the fit, the factor, too what)."""
BIAS_OUTSIDE = (
    "the CAN yaw rate reads %.2f deg/s where the car turns none, outside +- sensors.can.yaw_rate_bias_max_rps = %g "
    "rad/s: %s; set sensors.can.yaw_rate_bias_max_rps to cover it (a gyro's zero-rate offset, which wanders with "
    "temperature; sumhe calibrate measures it). Until then %.4f rad/s is taken off it on line from here, and the "
    "estimator starts over at this fix (what it estimated before turned %s through outages)"
)
"""The log line of a yaw-rate bias outside the bounds (the bias in deg/s, the bound, the fit, the bias taken off,
which way)."""


def yaw_verdict(scale: float, std: float) -> str | None:
    """What a fitted yaw-rate scale (true = scale x CAN) with standard error ``std`` says: ``"follows"`` (this car's
    yaw rate, its sign right), ``"sign_flipped"``, ``"not_following"``, or None while the evidence is too weak
    (:data:`CHECK_SIGMAS`, :data:`YAW_SCALE_PLAUSIBLE`)."""
    if not (math.isfinite(scale) and math.isfinite(std)):
        return None
    lo, hi = YAW_SCALE_PLAUSIBLE
    a, b = scale - CHECK_SIGMAS * std, scale + CHECK_SIGMAS * std
    if lo < a and b < hi:
        return "follows"
    if -hi < a and b < -lo:
        return "sign_flipped"
    if (-lo < a and b < lo) or a > hi or b < -hi:
        return "not_following"
    return None


def within(off: float, std: float, bound: float) -> bool | None:
    """Whether an estimate ``off`` from where it should be, with standard error ``std``, lies within ``+- bound``
    of it by :data:`CHECK_SIGMAS` standard errors (True), outside it by as many (False), or neither yet (None)."""
    if not (math.isfinite(off) and math.isfinite(std)):
        return None
    spread = CHECK_SIGMAS * std
    if abs(off) + spread < bound:
        return True
    return False if abs(off) - spread > bound else None


def speed_scale_outside(fit: LagFit, scale_max: float, quantum_mps: float) -> float | None:
    """The CAN speed's scale (CAN = k x true) of a fit of the receiver's speed over ground against it
    (:func:`~sumhe.frontend.alignment.speed_lag`) when it lies outside ``1 +- scale_max`` by :data:`CHECK_SIGMAS`
    standard errors and half a ``quantum_mps`` over the mean speed (a truncated CAN speed reads up to that much
    low), else None."""
    if not (fit.scale > 0 and math.isfinite(fit.scale_std) and fit.level > 0):
        return None
    k = 1.0 / fit.scale
    k_std = fit.scale_std / fit.scale**2
    margin = scale_max + 0.5 * quantum_mps / fit.level + CHECK_SIGMAS * k_std
    return k if abs(k - 1.0) > margin else None


def rounding_wrong(low: float, std: float, wrong: float) -> bool | None:
    """Whether a CAN speed that reads ``low`` (m/s) low on the mean with standard error ``std`` is made whole
    quanta the other way than configured: True where it reads ``wrong`` low (half a quantum: a truncated speed taken
    as rounded; minus half a quantum: a rounded one taken as truncated), False where it reads as configured (0 low),
    once the fit tells the two apart by :data:`CHECK_SIGMAS` (their log-likelihood ratio at least ``CHECK_SIGMAS^2 /
    2``, as an estimate ``CHECK_SIGMAS`` standard errors from the midpoint between them gives) and lies within
    ``CHECK_SIGMAS`` standard errors or a quarter quantum of the one it favours (on simulated drives with 10 Hz fixes
    the fits came up to 5 standard errors from the truth); None while the evidence is too weak, or fits neither."""
    if not (math.isfinite(low) and 0 < std < math.inf):
        return None
    ratio = wrong * (low - 0.5 * wrong) / (std * std)
    if abs(ratio) < 0.5 * CHECK_SIGMAS**2:
        return None
    centre = wrong if ratio > 0 else 0.0
    return ratio > 0 if abs(low - centre) <= max(CHECK_SIGMAS * std, 0.5 * abs(wrong)) else None


class SensorCheck:
    """The on-line check of the CAN yaw rate and speed against the receiver (see the module docstring), for one
    estimator's front-end: :meth:`add_yaw` per CAN yaw rate, :meth:`add_fix` per valid fix (times on the CAN
    clock), :meth:`check_speed` with the time-offset learner's newest fit; findings go to ``tally`` (a
    :class:`~sumhe.frontend.tally.Tally`)."""

    def __init__(self, settings: EstimationSettings, tally: Tally) -> None:
        self.settings = settings
        self.tally = tally
        self.yaw_done = False
        """The verdicts on the yaw rate were reached: nothing more is gathered."""
        self.gain_ok: bool | None = None
        """Whether the yaw rate's gain lies within the estimators' bounds, None until told."""
        self.bias_ok: bool | None = None
        """Whether the yaw rate's bias lies within the estimators' bounds, None until told (by a fit, or a stop)."""
        self._followed = False
        """A fit found the yaw rate this car's, its sign right: fits that say otherwise later are taken as noise."""
        self.factor = {"speed": 1.0, "yaw_rate": 1.0}
        """What the front-end multiplies each CAN quantity by (less its :attr:`offset`): the yaw rate -1 once its
        sign is found flipped, the fitted scale (true = scale x (CAN - bias)) once its gain is found outside the
        bounds; the speed the fitted scale once found outside the bounds; else 1."""
        self.offset = {"speed": 0.0, "yaw_rate": 0.0}
        """What the front-end takes off each CAN quantity before :attr:`factor`: the yaw rate's fitted bias once
        found outside the bounds, else 0."""
        self.speed_done = False
        can = settings.can
        self.rounding_done = can.speed_quantum_mps < COARSE_QUANTUM_MPS
        """The CAN speed's rounding is judged, or its quantum is too fine to tell: no more judged."""
        self._speed_fit: LagFit | None = None
        self.clear()

    def clear(self) -> None:
        """Forget the evidence gathered (a clock jump); the verdicts stay (the config did not change)."""
        self._yaw = TimeSeries()
        self._fixes: deque[tuple[float, float, float, float]] = deque()
        self._turns: deque[tuple[float, float]] = deque()
        self._turned = 0.0
        """The azimuth's turning (rad) in :attr:`_turns`, the window's."""
        self._turned_total = 0.0
        self._fitted_at = -math.inf
        self._anchor: tuple[float, float] | None = None
        self._chord_start: tuple[float, float, float] | None = None
        self._t0 = math.nan
        self._stops = StopWatch()
        self._fix_t = math.nan
        """The previous valid fix's time (s): the step a standstill is watched over ends at the next one."""

    def add_yaw(self, t: float, yaw_rps: float) -> None:
        """A CAN yaw rate (s on the CAN clock, rad/s as mapped)."""
        if not self.yaw_done:
            self._yaw.append(t, yaw_rps)

    def add_fix(self, fix: LocalFix, speed_mps: float, can: CanBuffer) -> None:
        """A valid fix (its time on the CAN clock) and its speed (m/s: over ground, else the CAN's; NaN if
        neither), with the front-end's CAN samples (a standstill since the fix before, :meth:`_watch_stop`). Its
        azimuth: its heading (with ``sensors.gnss.use_heading``), else its course over ground, else the course from
        the position :data:`CHORD_S` before (:meth:`_chord`)."""
        if self.yaw_done:
            return
        t = fix.t
        if math.isnan(self._t0):
            self._t0 = t
        if self.bias_ok is None and self.factor["yaw_rate"] == 1.0:
            self._watch_stop(can, t)
        heading = math.nan if fix.heading_rad is None or not self.settings.gnss.use_heading else fix.heading_rad
        course = math.nan if fix.course_rad is None else fix.course_rad
        if not (math.isfinite(heading) or math.isfinite(course)):
            t, course = self._chord(t, fix.east_m, fix.north_m)
            if not math.isfinite(course):
                return
        self._fixes.append((t, heading, course, speed_mps))
        self._turn(t, heading if math.isfinite(heading) else course, speed_mps)
        t_min = t - WINDOW_S
        while self._fixes[0][0] < t_min:
            self._fixes.popleft()
        while self._turns and self._turns[0][0] < t_min:
            self._turned -= self._turns.popleft()[1]
        self._yaw.trim(t_min - 2.0, keep=2)
        if self._turned >= MIN_TURN_RAD and self._turned_total >= self._fitted_at + REFIT_TURN_RAD:
            self._fitted_at = self._turned_total
            self._judge_yaw(t)

    def _watch_stop(self, can: CanBuffer, t: float) -> None:
        """Collect the CAN yaw rates (as mapped: no correction applied yet) of a standstill between the fix before
        and ``t``; when the car drives off, judge the bias by what the stop measured
        (:func:`~sumhe.frontend.standstill.bias_at_rest`, its bound at :data:`CHECK_SIGMAS`): a car at rest does not
        turn, so a stop tells the bias in seconds where the fits need the azimuth to turn 180 deg."""
        t0, self._fix_t = self._fix_t, t
        if math.isnan(t0):
            return
        settings = self.settings
        since = self._stops.since
        stop = self._stops.step(can, t0, t, 0.5 * settings.can.speed_quantum_mps, settings.can.max_gap_s)
        if stop is None:
            return
        bias = bias_at_rest(stop, settings.can, CHECK_SIGMAS, settings.estimator.mhe.rest_bias_rps)
        if bias is None:
            return
        mean, bound = bias
        bias_max = settings.can.yaw_rate_bias_max_rps
        if abs(mean) + bound < bias_max:
            self.bias_ok = True
        elif abs(mean) - bound > bias_max:
            self.bias_ok = False
            self.offset["yaw_rate"] = mean
            found = (
                f"the mean of {stop.n} CAN yaw rates at a standstill of {t0 - since:.0f} s, {mean:.4f} +- "
                f"{bound:.4f} rad/s ({CHECK_SIGMAS:g} standard errors and half a quantum), {t0 - self._t0:.0f} s "
                "into the data"
            )
            args = (math.degrees(mean), bias_max, found, mean, "left" if mean > 0 else "right")
            self.tally.count("yaw_rate_bias_outside", BIAS_OUTSIDE, *args, level=logging.ERROR)

    def _chord(self, t: float, east_m: float, north_m: float) -> tuple[float, float]:
        """The middle time (s) and azimuth (rad) of the chord from the fix :data:`CHORD_S` before (its first to
        second element in seconds) to this one, or ``(t, NaN)`` where none ends here: a receiver that sends no
        course or heading still turns with its positions (thinned: 10 Hz positions' noise swamps a 0.1 s chord)."""
        start = self._chord_start
        if start is not None and t - start[0] < CHORD_JITTER * CHORD_S[0]:
            return t, math.nan
        self._chord_start = (t, east_m, north_m)
        if start is None or t - start[0] > CHORD_S[1]:
            return t, math.nan
        chord = chord_azimuth(east_m - start[1], north_m - start[2], 0.0, t - start[0], 0.0)
        return 0.5 * (t + start[0]), math.nan if chord is None else chord[0]

    def _turn(self, t: float, azimuth: float, speed_mps: float) -> None:
        """Sum the azimuth's turning over steps of :data:`TURN_STEP_S` to 2 x it while moving."""
        if not (math.isfinite(azimuth) and abs(speed_mps) > MIN_SPEED_MPS):
            self._anchor = None
            return
        anchor = self._anchor
        if anchor is None or t - anchor[0] > 2.0 * TURN_STEP_S:
            self._anchor = (t, azimuth)
        elif t - anchor[0] >= TURN_STEP_S:
            turn = abs(math.remainder(azimuth - anchor[1], math.tau))
            self._turns.append((t, turn))
            self._turned += turn
            self._turned_total += turn
            self._anchor = (t, azimuth)

    def _judge_yaw(self, t: float) -> None:
        f = row_array(self._fixes)
        heading = np.count_nonzero(np.isfinite(f[:, 1])) >= MIN_PAIRS
        azimuth, source = (f[:, 1], "heading") if heading else (f[:, 2], "course (over ground, or between positions)")
        fit = course_lag(f[:, 0], azimuth, f[:, 3], *self._yaw.columns(), CHECK_LAGS_S, speed_weighted=not heading)
        if fit is None:
            return
        verdict = yaw_verdict(fit.scale, fit.scale_std)
        if verdict is None or (verdict != "follows" and self._followed):
            return  # once it followed, a fit that says otherwise is the noise's
        found = (
            f"scale {fit.scale:.3f} +- {fit.scale_std:.3f}, bias {fit.offset:.4f} +- {fit.offset_std:.4f} rad/s (true "
            f"= scale x (CAN - bias)) from the receiver's {source} over {fit.n} pairs of fixes, "
            f"{math.degrees(self._turned):.0f} deg turned, {t - self._t0:.0f} s into the data"
        )
        if verdict == "follows":
            self._followed = True
            self._judge_calibration(fit, found)
            if self.gain_ok is None or self.bias_ok is None:
                return
        self.yaw_done = True
        self._yaw, self._fixes, self._turns = TimeSeries(), deque(), deque()
        can = self.settings.can
        if verdict == "follows" and self.gain_ok and self.bias_ok:
            self.tally.log.info(
                "%s: the CAN yaw rate follows the receiver's azimuth, its gain within 1 +- "
                "sensors.can.yaw_rate_gain_max = %g and its bias within +- sensors.can.yaw_rate_bias_max_rps = %g: %s",
                self.tally.name,
                can.yaw_rate_gain_max,
                can.yaw_rate_bias_max_rps,
                found,
            )
        elif verdict == "sign_flipped":
            self.factor["yaw_rate"] = -1.0
            self.tally.count(
                "yaw_rate_sign_flipped",
                "the CAN yaw rate turns against the receiver's azimuth: %s; set scale = -1 (times the scale it has) in "
                "can.signals.yaw_rate (left turns must read positive). Until then its sign is turned round on line "
                "from here, and the estimator starts over at this fix (what it estimated before turned the wrong way "
                "through outages)",
                found,
                level=logging.ERROR,
            )
        elif verdict == "not_following":
            self.tally.count(
                "yaw_rate_not_following",
                "the CAN yaw rate does not follow the receiver's azimuth: %s; check can.signals.yaw_rate (another axis "
                "of the sensor? an IMU's three rates and accelerations map to the rate about up; its unit, or "
                "scale?). The estimates run on the config as it is: through outages "
                "their heading is wrong",
                found,
                level=logging.ERROR,
            )

    def _judge_calibration(self, fit: LagFit, found: str) -> None:
        """The gain and the bias of a yaw rate that follows the azimuth, each judged once against the estimators'
        bounds (:func:`within`); one outside is undone from here (:attr:`factor`, :attr:`offset`)."""
        can = self.settings.can
        if self.gain_ok is None:
            self.gain_ok = within(1.0 / fit.scale - 1.0, fit.scale_std / fit.scale**2, can.yaw_rate_gain_max)
            if self.gain_ok is False:
                self.factor["yaw_rate"] = fit.scale
                way = "little" if fit.scale > 1.0 else "much"
                args = (1.0 / fit.scale, can.yaw_rate_gain_max, found, fit.scale, way)
                self.tally.count("yaw_rate_gain_outside", GAIN_OUTSIDE, *args, level=logging.ERROR)
        if self.bias_ok is None:
            self.bias_ok = within(fit.offset, fit.offset_std, can.yaw_rate_bias_max_rps)
            if self.bias_ok is False:
                self.offset["yaw_rate"] = fit.offset
                way = "left" if fit.offset > 0 else "right"
                args = (math.degrees(fit.offset), can.yaw_rate_bias_max_rps, found, fit.offset, way)
                self.tally.count("yaw_rate_bias_outside", BIAS_OUTSIDE, *args, level=logging.ERROR)

    def check_speed(self, fit: LagFit | None, t: float) -> None:
        """Judge the CAN speed's rounding and scale by ``fit``, the time-offset learner's newest fit (once each), at
        ``t`` (s, CAN clock)."""
        if (self.speed_done and self.rounding_done) or fit is None or fit is self._speed_fit:
            return
        self._speed_fit = fit
        if math.isnan(self._t0):
            self._t0 = t
        if fit.n < MIN_SPEED_FIXES:
            return
        if not self.rounding_done and t - self._t0 >= ROUNDING_AFTER_S:
            self._judge_rounding(fit, t)
        if not self.speed_done:
            self._judge_scale(fit, t)

    def _judge_rounding(self, fit: LagFit, t: float) -> None:
        can = self.settings.can
        q, truncate = can.speed_quantum_mps * self.factor["speed"], can.speed_rounding == "truncate"
        wrong = rounding_wrong(fit.reads_low, fit.reads_low_std, -0.5 * q if truncate else 0.5 * q)
        if wrong is None:
            return
        self.rounding_done = True
        found = (
            f"it reads {fit.reads_low:.3f} +- {fit.reads_low_std:.3f} m/s low on the mean against the receiver's "
            f"speed over ground ({fit.n} fixes, {t - self._t0:.0f} s into the data)"
        )
        if not wrong:
            self.tally.log.info(
                "%s: the CAN speed is made whole %.3g m/s as sensors.can.speed_rounding = %r says: %s",
                self.tally.name,
                q,
                can.speed_rounding,
                found,
            )
            return
        self.tally.count(
            "speed_rounding_wrong",
            "the CAN speed is %s to whole %.3g m/s, not %s: %s; set sensors.can.speed_rounding = %r (sumhe "
            "calibrate measures it). The estimates run on the config as it is: through outages their distance may "
            "drift by up to %.2g m a second",
            "rounded" if truncate else "truncated",
            q,
            "truncated" if truncate else "rounded",
            found,
            "round" if truncate else "truncate",
            0.5 * q,
        )

    def _judge_scale(self, fit: LagFit, t: float) -> None:
        can = self.settings.can
        k = speed_scale_outside(fit, can.speed_scale_max, can.speed_quantum_mps)
        if k is None:
            return
        self.speed_done = True
        self.factor["speed"] = fit.scale
        self.tally.count(
            "speed_scale_outside",
            "the CAN speed reads %.3f +- %.3f x the receiver's speed over ground (%d fixes, %.0f s into the data), "
            "outside 1 +- sensors.can.speed_scale_max = %g: check can.signals.speed (its unit, or scale: mph read "
            "as km/h is 0.621x, km/h as mph 1.609x; sumhe calibrate measures it). Until then it is multiplied by "
            "%.3f on line from here, and the estimator starts over at this fix (what it estimated before ran %s "
            "through outages)",
            k,
            fit.scale_std / fit.scale**2,
            fit.n,
            t - self._t0,
            can.speed_scale_max,
            fit.scale,
            "short" if fit.scale > 1.0 else "long",
            level=logging.ERROR,
        )
