"""GNSS epochs in time: the receiver's period, the delay of fixes behind the CAN data, the epochs it missed.

One rule for every estimator (and the batch grid): the nominal period is the mean of the intervals between
epochs that lie within 50 % of their median (the mean of consecutive intervals cancels the receive-time jitter;
the median test leaves outage gaps out), from at least two intervals (two fixes around an outage say nothing of
the period), else the GNSS model's ``period_s``. Silence longer than 1.5 periods, measured on the fix clock (the
newest CAN time minus the largest recent delay of fixes behind the CAN data: a live service takes each sample as
it arrives, so a fix comes after the CAN samples of its latency, with jitter, and one later than the typical
fix must not find its epoch declared missed), is a missed epoch every period, once the
stream has shown its period (two intervals): before, a 1 Hz receiver's second fix would come after ten epochs
"missed" at the default 0.1 s and be dropped as back in time, and its period never measured.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Iterable

PERIOD_HISTORY = 32
"""Intervals (and fix delays) remembered."""
MAX_PERIOD_S = 5.0
"""Intervals longer than this are gaps, not periods."""
MISSED_AFTER_PERIODS = 1.5
"""Silence of this many periods is a missed epoch."""


def nominal_period(intervals: Iterable[float], default: float) -> float:
    """The GNSS period (s) of ``intervals`` between epochs (see the module docstring); ``default`` from fewer than
    two."""
    d = [float(x) for x in intervals if 0 < x <= MAX_PERIOD_S]
    if len(d) < 2:
        return default
    median = statistics.median(d)
    regular = [x for x in d if abs(x - median) <= 0.5 * median]
    return statistics.fmean(regular) if regular else median


def bad_epoch_time(t: object, last_epoch: float | None) -> tuple[str, str, tuple[float, ...]] | None:
    """Why a GNSS epoch at ``t`` cannot be taken, as (counter, log message, message args), or None when it can:
    a non-finite time, or a time not after the previous epoch's."""
    if not (isinstance(t, int | float) and math.isfinite(t)):
        return "bad_samples", "GNSS epoch with a non-finite time", ()
    if last_epoch is not None and t <= last_epoch:
        return "dropped_backwards", "GNSS epoch %.3f s back in time dropped", (last_epoch - t,)
    return None


class EpochClock:
    """The stream's GNSS timing: the nominal period, the fixes' largest recent delay behind the CAN data, the last
    epoch."""

    def __init__(self, default_period_s: float) -> None:
        self.default_period_s = default_period_s
        self._intervals: deque[float] = deque(maxlen=PERIOD_HISTORY)
        self._delays: deque[float] = deque(maxlen=PERIOD_HISTORY)
        self._last_real: float | None = None
        self.period_s = default_period_s
        self.delay_s = 0.0
        self.last_epoch: float | None = None
        """The time of the last epoch handed out (a fix or a missed one)."""

    def observe(self, t: float, newest_can: float) -> None:
        """A fix's epoch at ``t`` (s) while the newest CAN data is at ``newest_can``: period and delay."""
        self._real(t)
        self._delay(t, newest_can)

    def observe_late(self, t: float, newest_can: float, max_delay_s: float) -> bool:
        """Whether a fix at ``t`` (s), whose epoch was already handed out, came after the last fix (its epoch was
        declared missed before it came; else it is a duplicate, also of such a fix). Its delay behind the CAN data
        (up to ``max_delay_s``) is then learned, so the epochs after it wait for their fixes (else a receiver whose
        fixes begin to come later than before would find every epoch declared missed, for good), and its interval
        from the fix before (the receiver's period)."""
        if self._last_real is None or t <= self._last_real:
            return False
        if newest_can - t <= max_delay_s:
            self._delay(t, newest_can)
        self._real(t)
        return True

    def _real(self, t: float) -> None:
        if self._last_real is not None and 0.0 < t - self._last_real <= MAX_PERIOD_S:
            self._intervals.append(t - self._last_real)
            self.period_s = nominal_period(self._intervals, self.default_period_s)
        self._last_real = t

    def _delay(self, t: float, newest_can: float) -> None:
        if newest_can > t:
            self._delays.append(newest_can - t)
            self.delay_s = max(self._delays)

    def missed_due(self, t_fix_clock: float) -> bool:
        """Whether an epoch is missed by ``t_fix_clock`` (s): :meth:`missed` would give one."""
        last = self.last_epoch
        return (
            last is not None and t_fix_clock - last > MISSED_AFTER_PERIODS * self.period_s and len(self._intervals) >= 2
        )

    def missed(self, t_fix_clock: float) -> list[float]:
        """Times of the epochs GNSS missed up to ``t_fix_clock`` (s), each a period after the last; they become the
        last epoch."""
        out: list[float] = []
        while self.missed_due(t_fix_clock) and self.last_epoch is not None:
            self.last_epoch += self.period_s
            out.append(self.last_epoch)
        return out
