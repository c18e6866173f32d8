"""The output bounds learned from the data: paper 000's MAP of a uniform noise's bound, on line.

The MHE's output bounds R start as the sensors' error allowances (``estimator.r_cap_sigmas`` sigmas of what the
receiver and the CAN sensors claim, :mod:`.outputs`). Real sensors break such claims: a receiver's course errs by
degrees where its speed sigma says a tenth of one, its Doppler speed jumps by a metre per second now and then, and
an allowance a measurement exceeds makes the window infeasible. For uniform noise the MAP estimate of its bound
given the residuals is their largest magnitude (the likelihood ``(2r)^-K`` falls with ``r`` as long as every
residual fits): so each output's bound is its allowance times a factor, the largest ratio of a residual to its
allowance seen over the last ``mhe.bound_history`` steps times ``mhe.bound_margin`` (never below 1: the sensors'
claims are the floor; at most ``mhe.bound_max_factor``). The residuals are those of the steps leaving the window,
where the smoothed trajectory has seen every measurement around them. A measurement that still exceeds its bound
makes the solve fail and be retried on widened bounds (the fault path, counted); the residuals of the widened
solution then raise the factors at once, so the same excess does not make the next window infeasible.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

BLOCK = 50
"""Residual ratios are kept as the maxima of blocks of this many (the history's maximum in O(history / BLOCK))."""


class OutputEnvelope:
    """Per output, the factor on its allowance: the largest residual-to-allowance ratio of the recent history times
    a margin, within [1, ``max_factor``] (module docstring)."""

    def __init__(self, n_outputs: int, history: int, margin: float, max_factor: float) -> None:
        self.margin, self.max_factor = margin, max_factor
        self._blocks: list[deque[float]] = [deque(maxlen=max(history // BLOCK, 1)) for _ in range(n_outputs)]
        self._block_peak = [0.0] * n_outputs
        """The largest of each output's blocks (0 before the first): updated as a block is added, not per epoch."""
        self._current = [0.0] * n_outputs
        self._count = [0] * n_outputs
        self.factor = np.ones(n_outputs)

    def observe(self, ratios: NDArray[np.float64]) -> None:
        """Take the residual-to-allowance ratios of some steps (steps x outputs; NaN where an output is missing)
        and update the factors (in plain floats: a few steps of a few outputs at every epoch)."""
        current, count = self._current, self._count
        for j, column in enumerate(ratios.T.tolist()):
            for value in column:
                if not math.isfinite(value):
                    continue
                current[j] = max(current[j], value)
                count[j] += 1
                if count[j] == BLOCK:
                    self._blocks[j].append(current[j])
                    self._block_peak[j] = max(self._blocks[j])
                    current[j], count[j] = 0.0, 0
            peak = max(self._block_peak[j], current[j])
            self.factor[j] = min(max(peak * self.margin, 1.0), self.max_factor)
