"""The MHE's gate: which fixes enter the window.

A fix whose distance to the prediction exceeds its position allowance (``r_cap_sigmas`` x its larger sigma) +
``estimator.mhe.gate_m`` + ``estimator.mhe.gate_drift`` x the distance driven since the last fix used (twice that
distance while no azimuth has been measured since the start: the prediction may point anywhere) is rejected, so one
multipath jump cannot widen the bounds; the first ``max(steps_before, 2)`` fixes are taken while no azimuth has
been measured (not after: at 1 Hz they are 20 s, and on the bench's realistic offroad drive of seed 9 one 23 m off,
taken so, held the window's solution, which must stay within its allowance, 10 m off for 42 s). The gate widens
with the distance driven, so after a long outage the first good fixes are taken. Two rules say the estimate, not
the fixes, is wrong (the estimator restarts at the newest fix): fixes not followed for ``GATE_RESET_S`` without a
break (rejected, or taken by a solution that stays farther from them than the gate's base radius), or
``REACQUIRE_FIXES`` rejected fixes in a row that agree with each other, either after an outage (their offsets from
the prediction on a straight line in time, :func:`~sumhe.estimator.base.on_a_line`), or within ``GATE_RESET_S`` of
the first fix taken after one when the jump from the fixes taken to them about undoes the jump from the outage's dead
reckoning to that fix, or within ``GATE_RESET_S`` of a restart when they about undo the restart's jump from the
prediction it gave up to its fix (:data:`REENTRY_CLOSER`; there the offsets must agree as they are).

The second case is a multipath episode that began with the outage's end: the wide gate had to take its first
fixes, the estimate followed them, and the good fixes that came next were rejected for up to ``GATE_RESET_S``
(measured on a realistic simulated offroad drive: 8 s of fixes 12 m off after a 30 s outage left the estimate 14 m
off for 25 s). The straight line: a prediction dead-reckoned through an outage on a wrong azimuth or speed scale
moves away from the fixes steadily. With offsets that had to agree as they are, a 1 Hz receiver's never did behind
a prediction that turned away (realistic simulated highway drive, seed 4: the azimuth 13 deg off when GNSS came
back, the offsets growing by 7 m a second, every fix rejected until the next outage, 85 s without a fix used and
1.3 km off); the Kalman peers' gate had the same rule for the same reason. The fixes not followed: after a 55 s
outage at 10 Hz (seed 13), a window of 300 merged steps that could not bend to fixes 30 m off took one in ten and
stayed 14-23 m from each, the gate rejected the rest, and each fix taken had started the rejections' clock and the
streak again: 34 s of fixes 23-38 m off, until the next outage. A restart is such a re-entry too: on the bench's
realistic offroad drive of seed 1, after its 30 s outage the first fix was taken, the next lay 12-13 m off for 8 s
and agreed, so the gate re-acquired on them, and the good fixes after them were refused for 33 s, the estimate 11-12 m
off, until the rule of ``GATE_RESET_S`` (now they undo the restart's jump: a restart at the fifth, 0.4 s after the
first).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from sumhe.estimator.base import on_a_line
from sumhe.frontend.stream import FixMeasurement
from sumhe.messages import GpsStatus
from sumhe.settings import EstimationSettings

log = logging.getLogger(__name__)

GATE_RESET_S = 30.0
"""Valid fixes not followed (rejected, or taken by a solution that stays away from them) for this long without a
break (longer than a multipath episode): the estimate is what is wrong; restart at the newest fix."""
REACQUIRE_FIXES = 5
"""After an outage, this many rejected fixes in a row that agree with each other (their offsets from the
prediction within the gate's base radius of their straight line in time) mean the prediction drifted, not the
fixes: restart at the newest fix (0.5 s at 10 Hz). Mid-drive, a consistent offset is more likely multipath:
``GATE_RESET_S`` applies."""
REACQUIRE_AFTER_M = 30.0
"""Distance driven without a fix used (m) from which a rejection streak counts as "after an outage"."""
REENTRY_CLOSER = 0.5
"""A streak of agreeing rejected fixes replaces the fixes taken at an outage's end when its jump from them (its mean
offset from the prediction less the last fix taken's from its solution) plus the first one's from the outage's dead
reckoning is at most this share of the latter: the episode's end undid its start. The streak's offset from the
prediction plus the first fix's had stood for the jumps, as if the estimate had moved exactly onto the fixes taken:
on a simulated highway drive whose first 8 s of fixes after a 20 s outage lay 12 m east, the estimate ran 1.3 m past
them, the sum missed by 5.1 against 4.2 m (3.9 m now: the dead reckoning's own error where they began), and every fix
was rejected until the next outage."""


class FixGate:
    """The gate's state over the stream (see the module docstring)."""

    def __init__(self, settings: EstimationSettings) -> None:
        self.settings = settings
        self.start(heading_known=False)

    def start(self, heading_known: bool, jump: tuple[float, np.ndarray] | None = None) -> None:
        """A (re)start at a fix used; ``heading_known``: it measured the azimuth; ``jump``: a restart's time and its
        fix's offset from the prediction given up (east, north; m), the re-entry onto the fixes that a streak may
        undo (:data:`REENTRY_CLOSER`: a restart onto a multipath episode)."""
        self.since_fix_m = 0.0
        self.heading_known = heading_known
        self.used_fixes = 1
        self._rejected_since: float | None = None
        self._offsets: list[tuple[float, np.ndarray]] = []
        self._after_outage = False
        self._outage_end = False
        self._radius = math.inf
        self._reentry = jump
        self._taken = (0.0, 0.0)

    def drove(self, distance_m: float) -> None:
        """The vehicle drove ``distance_m`` (m) since the previous epoch."""
        self.since_fix_m += distance_m

    def _base_radius(self, fix: FixMeasurement) -> float:
        s = self.settings
        return s.estimator.r_cap_sigmas * max(fix.sigma_east_m, fix.sigma_north_m) + s.estimator.mhe.gate_m

    def passes(self, fix: FixMeasurement, east_m: float, north_m: float) -> bool:
        """Whether ``fix`` passes, against the prediction at (``east_m``, ``north_m``)."""
        m = self.settings.estimator.mhe
        drift = m.gate_drift if self.heading_known else 2.0
        self._radius = self._base_radius(fix)
        radius = self._radius + drift * self.since_fix_m
        miss = math.hypot(fix.east_m - east_m, fix.north_m - north_m)
        if miss <= radius or (self.used_fixes < max(m.steps_before, 2) and not self.heading_known):
            if self.since_fix_m > REACQUIRE_AFTER_M:
                self._reentry = (fix.t, np.array([fix.east_m - east_m, fix.north_m - north_m]))
            return True
        log.debug("fix at %.2f rejected: %.1f m from the prediction (gate %.1f m)", fix.t, miss, radius)
        return False

    def locked_out(self, t: float) -> bool:
        """Whether fixes have been rejected for :data:`GATE_RESET_S` without a break."""
        return self._rejected_since is not None and t - self._rejected_since > GATE_RESET_S

    def reacquire(self, fix: FixMeasurement, east_m: float, north_m: float) -> bool:
        """Whether a rejected fix completes a streak that says the prediction is what is wrong (module docstring:
        after an outage, or against the fixes taken at its end); records the fix's offset from the prediction."""
        if not self._offsets:
            self._after_outage = self._outage_end or self.since_fix_m > REACQUIRE_AFTER_M
        self._offsets.append((fix.t, np.array([fix.east_m - east_m, fix.north_m - north_m])))
        if len(self._offsets) < REACQUIRE_FIXES:
            return False
        streak = self._offsets[-REACQUIRE_FIXES:]
        if self._after_outage:
            return on_a_line(streak, self._base_radius(fix))
        recent = np.array([offset for _, offset in streak])
        mean = recent.mean(axis=0)
        if float(np.max(np.hypot(*(recent - mean).T))) > self._base_radius(fix):
            return False
        if self._reentry is None or fix.t - self._reentry[0] > GATE_RESET_S:
            return False
        first = self._reentry[1]
        return float(np.hypot(*(first + mean - np.array(self._taken)))) <= REENTRY_CLOSER * float(np.hypot(*first))

    def done(self, t: float, status: GpsStatus, azimuth_used: bool, miss: tuple[float, float] = (0.0, 0.0)) -> None:
        """The epoch is solved: a fix used (``azimuth_used``: with its azimuth; ``miss``: its offset east and north (m)
        from the solution), or one more rejected. A fix used that the solution stays farther from than the gate's base
        radius was not followed (a window that cannot bend to the fixes after an outage): the rejection streak and its
        time go on, and the outage it ended still counts for :meth:`reacquire`."""
        if status == "ok":
            self._taken = miss
            followed = math.hypot(*miss) <= self._radius
            self._outage_end = not followed and (self._outage_end or self.since_fix_m > REACQUIRE_AFTER_M)
            self.since_fix_m = 0.0
            self.used_fixes += 1
            self.heading_known |= azimuth_used
            if followed:
                self._rejected_since = None
                self._offsets.clear()
                return
        if status != "outage" and self._rejected_since is None:
            self._rejected_since = t
