"""The moving horizon's window: which steps it keeps (the policy) and their data (the bookkeeping).

The window is a time-ordered list of steps (one per GNSS epoch, outage epochs included), oldest first. After each
new step is appended, :func:`plan_window` decides what to drop; :meth:`Window.apply` does it.

Policy (paper 001 sec. 6: the data must be present at both ends of a window, so its length varies while GNSS is
missing; ``docs/mhe.md``), with the numbers of ``[estimator.mhe]`` (:class:`~sumhe.settings.MheSettings`):

* normally the window holds the newest ``steps`` (N) steps and slides by one step per epoch;
* while GNSS is out, and until ``steps_after`` (N_A) GNSS epochs have come back, the window keeps at least
  ``steps_before`` (N_B) GNSS epochs from before the newest outage: it stops sliding and grows instead (while the
  outage is shorter than N - N_B steps the N newest steps already hold them, and nothing changes);
* at most ``max_steps`` (N_max) steps: beyond, steps without GNSS older than the newest N are removed, which
  merges two steps into one of the summed length (the state noise bounds scale with the step length; the
  estimator keeps what the removed step's CAN data added as an offset of the merged transition), two equal
  steps first (so steps are 1, 2, 4, ... periods long), the shortest merged step first and the oldest first among
  equals, so the outage is coarsened behind its newest N steps, which stay at the GNSS period; a merged step is
  at most ``max_merge`` nominal periods long. Only when no step can be merged are the oldest steps dropped;
* when the window may shrink again it drops ``1 + shrink_steps`` of its oldest steps per epoch (it shrinks back
  progressively, by ``shrink_steps`` per epoch, not in one jump).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sumhe.settings import MheSettings

MERGE_TOL = 1e-6
EQUAL_STEPS = 0.25
"""Two steps whose lengths differ by less than this fraction of the shorter are of equal length."""


@dataclass(frozen=True, slots=True)
class Plan:
    """What to do with the window after a step was appended: drop the ``drop`` oldest steps, then remove the
    steps ``merge`` (indices after the drop, ascending) to coarsen it."""

    drop: int = 0
    merge: tuple[int, ...] = ()


def outage_anchor(gps: NDArray[np.bool_], policy: MheSettings) -> int | None:
    """Index of the oldest step the newest outage needs kept (its N_B-th GNSS epoch before it; 0 if fewer are
    left), or None when there is no outage in the window or GNSS has been back for N_A epochs."""
    if gps.all():  # no outage (nearly every epoch): one call, not the two of the general form
        return None
    missing = np.flatnonzero(~gps)
    end = int(missing[-1])
    if len(gps) - 1 - end >= policy.steps_after:
        return None
    gps_before = np.flatnonzero(gps[:end])
    start = int(gps_before[-1]) + 1 if len(gps_before) else 0
    if policy.steps_before == 0:
        return start
    if len(gps_before) < policy.steps_before:
        return 0
    return int(gps_before[-policy.steps_before])


def _merge_choice(gps: NDArray[np.bool_], t: NDArray[np.float64], cap: float, fine: int) -> int | None:
    """The step whose removal coarsens the window best, None if none may go. A step may go if it has no GNSS, is
    not one of the newest ``fine`` steps and merges its two neighbouring steps into one no longer than ``cap``;
    preferred are steps between two steps of equal length (the outage's steps then stay 1, 2, 4, ... periods
    long, which pack best), then the shortest merged step, then the oldest."""
    if len(t) < 3:
        return None
    h = np.diff(t)
    merged = h[1:] + h[:-1]
    ok = ~gps[1:-1] & (merged <= cap)
    ok[max(0, len(t) - 1 - fine) :] = False
    if not ok.any():
        return None
    unequal = np.abs(h[1:] - h[:-1]) > EQUAL_STEPS * np.minimum(h[1:], h[:-1])
    candidates = np.flatnonzero(ok)
    order = np.lexsort((candidates, merged[candidates], unequal[candidates]))
    return int(candidates[order[0]]) + 1


def plan_window(gps: NDArray[np.bool_], t: NDArray[np.float64], period: float, policy: MheSettings) -> Plan:
    """The plan for a window whose steps are at times ``t`` (s) and have GNSS where ``gps`` (newest last).

    ``period`` is the nominal step (s). See the module docstring for the rules.
    """
    n = len(gps)
    keep_from = max(0, n - policy.steps)
    anchor = outage_anchor(gps, policy)
    if anchor is not None:
        keep_from = min(keep_from, anchor)
    drop = min(keep_from, 1 + policy.shrink_steps)
    if n - drop <= policy.max_steps:
        return Plan(drop=drop)
    gps_kept, t_kept = gps[drop:].copy(), t[drop:].copy()
    cap = policy.max_merge * period * (1.0 + MERGE_TOL)
    removed: list[int] = []
    index = np.arange(len(t_kept))
    while len(t_kept) > policy.max_steps:
        i = _merge_choice(gps_kept, np.round(t_kept / period, 6) * period, cap, policy.steps)
        if i is None:
            break
        removed.append(int(index[i]))
        gps_kept, t_kept, index = np.delete(gps_kept, i), np.delete(t_kept, i), np.delete(index, i)
    extra = len(t_kept) - policy.max_steps
    if extra > 0:
        # nothing left to merge: drop the oldest steps (the arrival box carries what they knew)
        first = int(index[extra])
        return Plan(drop=drop + first, merge=tuple(sorted(i - first for i in removed if i > first)))
    return Plan(drop=drop, merge=tuple(sorted(removed)))


class Window:
    """The steps of the horizon, oldest first, in preallocated arrays (views of the first ``len`` rows).

    Per step: time ``t`` (s), outputs ``y`` (n; the model's output units), ``avail`` (which outputs are present),
    ``allow`` (each output's error allowance, its unit), the trajectory ``x`` (m states: the current estimate,
    or the prediction for a step not solved yet) and ``offset`` (m): the known part of the transition into the
    step beyond the model's (the CAN data's motion beyond one model step, :mod:`.preintegration`, or after a merge,
    see :meth:`apply`) and ``q_step`` (m; NaN where unknown): the bound on the state noise of the transition into the
    step that the CAN data's errors leave. ``gps_column`` is the output that says a step has GNSS.
    """

    def __init__(self, capacity: int, n_states: int, n_outputs: int, gps_column: int = 0) -> None:
        self.capacity = capacity
        self.gps_column = gps_column
        self._t = np.zeros(capacity)
        self._y = np.zeros((capacity, n_outputs))
        self._avail = np.zeros((capacity, n_outputs), dtype=bool)
        self._allow = np.ones((capacity, n_outputs))
        self._x = np.zeros((capacity, n_states))
        self._offset = np.zeros((capacity, n_states))
        self._q_step = np.full((capacity, n_states), np.nan)
        self.n = 0

    def __len__(self) -> int:
        return self.n

    @property
    def t(self) -> NDArray[np.float64]:
        return self._t[: self.n]

    @property
    def y(self) -> NDArray[np.float64]:
        return self._y[: self.n]

    @property
    def avail(self) -> NDArray[np.bool_]:
        return self._avail[: self.n]

    @property
    def allow(self) -> NDArray[np.float64]:
        return self._allow[: self.n]

    @property
    def x(self) -> NDArray[np.float64]:
        return self._x[: self.n]

    @property
    def offset(self) -> NDArray[np.float64]:
        return self._offset[: self.n]

    @property
    def q_step(self) -> NDArray[np.float64]:
        return self._q_step[: self.n]

    @property
    def gps(self) -> NDArray[np.bool_]:
        """Steps with a GNSS position."""
        return self._avail[: self.n, self.gps_column]

    def clear(self) -> None:
        self.n = 0

    def append(self, t: float, y: NDArray, avail: NDArray, allow: NDArray, x: NDArray) -> None:
        """Add the newest step; ValueError if the window is full or ``t`` is not after the newest step."""
        if self.n >= self.capacity:
            raise ValueError(f"window full ({self.capacity} steps)")
        if self.n and not t > self._t[self.n - 1]:
            raise ValueError(f"step at {t!r} s is not after the newest step at {self._t[self.n - 1]!r} s")
        i = self.n
        self._t[i], self._y[i], self._avail[i], self._allow[i], self._x[i] = t, y, avail, allow, x
        self._offset[i] = 0.0
        self._q_step[i] = np.nan
        self.n += 1

    def apply(self, plan: Plan) -> list[int]:
        """Drop the oldest ``plan.drop`` steps, then remove the steps ``plan.merge``; the indices (after) of the
        steps whose previous step changed by a merge: their transitions now span the merged steps, and the owner of
        the model sets their offsets. A merged transition's CAN noise bound is the sum of its parts'."""
        arrays = (self._t, self._y, self._avail, self._allow, self._x, self._offset, self._q_step)
        if plan.drop:
            k = min(plan.drop, self.n)
            for a in arrays:
                a[: self.n - k] = a[k : self.n]
            self.n -= k
        if plan.merge:
            for i in plan.merge:
                if i + 1 < self.n:
                    self._q_step[i + 1] += self._q_step[i]
            keep = np.ones(self.n, dtype=bool)
            keep[list(plan.merge)] = False
            n = int(keep.sum())
            for a in arrays:
                a[:n] = a[: self.n][keep]
            self.n = n
        return sorted({i - rank for rank, i in enumerate(plan.merge)})
