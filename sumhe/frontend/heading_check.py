"""A receiver's headings checked against the CAN yaw rate (:class:`HeadingCheck`).

A GNSS + IMU module sends a heading from its first fixes on, before its filter has settled: the shared real drive's
headings jumped by 5-10 deg from one second to the next in its first minute while the car drove straight (and lay
5-11 deg off the line of its positions); from its fourth minute on they were 0.2-0.5 deg rms off that line. The module
rates them (2-40 deg, then 0.2-1 deg), but a config may not map that rating, and other receivers send none. Weighed
at the configured ``heading_sigma_rad`` (0.29 deg there), such headings teach an estimator a yaw-rate gain, bias and
lever arm that it then forgets only slowly: that drive's MHE carried a gain of 1.03, learned in its first minute,
into an outage at 270 s and ended it 25 m off after 60 s.

The check needs no rating: a heading's change from the fix before (at most :data:`PAIR_MAX_S` back) is the CAN yaw
rate's turn in between (:func:`turn_excess_rad`), but for the yaw rate's bias and gain error
(``sensors.can.yaw_rate_bias_max_rps``, ``yaw_rate_gain_max``), the turn the fixes' time error (:data:`TIME_ERROR_S`)
makes where the yaw rate changes, and the two headings' configured noise (:data:`NOISE_SIGMAS` of
``sensors.gnss.heading_sigma_rad``). What the change exceeds that by is the headings' error (half its square each:
the difference of two white errors has twice their variance). The squares are averaged over time (forgotten in
:data:`FORGET_S`); a heading then weighs at least at their root mean square, or at its own fix's error where that
is larger (:meth:`HeadingCheck.sigma_rad`; the front-end counts each heading so weighed down, ``headings_off``).
Headings that agree leave the sigma as it was, and the mean square decays.

A heading steadily off the road (no jumps to see) is not the check's: beyond the receiver's mounting offset, which
the estimators learn, it is their gate's (the MHE's hard bound on headings, the filters' innovation gates). The
course of the positions was tried as a second check here (the chord between fixes 20 m apart on a straight road
against the headings' mean): on the shared real drive it changed the outages' mean errors by 0.01 m, and on the
simulator's two-antenna drives its allowance for the fixes' fix-to-fix noise (0.3 m) was exceeded at 4 sigma.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sumhe.settings import CanModel, GnssModel

PAIR_MAX_S = 3.0
"""The longest time (s) between the two fixes of a check."""
TIME_ERROR_S = 0.5
"""The fixes' time error (s) allowed against the CAN clock: the GNSS time offset before it is learned (0.36 s on the
shared real drive)."""
NOISE_SIGMAS = 2.0
"""The headings' configured noise allowed, in sigmas of their difference."""
FORGET_S = 20.0
"""The time (s) in which the errors found are forgotten (exponentially)."""


def turn_excess_rad(
    turn_rad: float, yaw_turn_rad: float, yaw_change_rps: float, dt_s: float, gnss: GnssModel, can: CanModel
) -> float:
    """How far (rad, >= 0) a heading's change ``turn_rad`` (clockwise) over ``dt_s`` differs from the CAN yaw rate's
    turn ``yaw_turn_rad`` (anticlockwise) in between, beyond the yaw rate's bias and gain error, the turn a time
    error of :data:`TIME_ERROR_S` makes where the yaw rate changed by ``yaw_change_rps`` over the pair, and
    :data:`NOISE_SIGMAS` of the two headings' configured noise."""
    differ = abs(math.remainder(turn_rad + yaw_turn_rad, math.tau))
    allowed = (
        can.yaw_rate_bias_max_rps * dt_s
        + can.yaw_rate_gain_max * abs(yaw_turn_rad)
        + TIME_ERROR_S * abs(yaw_change_rps)
        + NOISE_SIGMAS * math.sqrt(2.0) * gnss.heading_sigma_rad
    )
    return max(differ - allowed, 0.0)


@dataclass(frozen=True, slots=True)
class HeadingFix:
    """A fix's heading: ``t`` (s, CAN clock), ``heading_rad`` (clockwise from north) and the CAN yaw rate there
    (``yaw_rps``: rad/s, anticlockwise; None without one)."""

    t: float
    heading_rad: float
    yaw_rps: float | None


class HeadingCheck:
    """The recent headings' errors beyond what the sensors allow (module docstring): fed every usable fix with a
    heading in time order (:meth:`add`); :meth:`sigma_rad` is the least sigma a heading weighs at now."""

    def __init__(self, gnss: GnssModel, can: CanModel) -> None:
        self.gnss = gnss
        self.can = can
        self.before: HeadingFix | None = None
        """The fix checked last."""
        self._mean_square = 0.0
        self._t = -math.inf
        self._now = 0.0
        """The newest fix's own error (rad)."""

    def add(self, fix: HeadingFix, yaw_turn_rad: float | None) -> None:
        """A fix with a heading; ``yaw_turn_rad``: the CAN yaw rate's turn (rad, anticlockwise) since the fix
        before (:attr:`before`; None without CAN data in between)."""
        before, self.before = self.before, fix
        self._now = 0.0
        if (
            before is None
            or yaw_turn_rad is None
            or fix.yaw_rps is None
            or before.yaw_rps is None
            or not 0.0 < fix.t - before.t <= PAIR_MAX_S
        ):
            return
        dt = fix.t - before.t
        excess = turn_excess_rad(
            fix.heading_rad - before.heading_rad, yaw_turn_rad, fix.yaw_rps - before.yaw_rps, dt, self.gnss, self.can
        )
        variance = 0.5 * excess * excess
        keep = math.exp(-(fix.t - self._t) / FORGET_S) if math.isfinite(self._t) else 0.0
        self._mean_square = keep * self._mean_square + (1.0 - keep) * variance
        self._t = fix.t
        self._now = math.sqrt(variance)

    def sigma_rad(self, t: float) -> float:
        """The least 1-sigma (rad) of a heading at ``t`` (s): the newest fix's error, or the recent ones' root mean
        square, forgotten since the last check, whichever is larger; 0 while the headings agree."""
        keep = math.exp(-(t - self._t) / FORGET_S) if t > self._t else 1.0
        return max(self._now, math.sqrt(keep * self._mean_square))
