"""Rauch-Tung-Striebel smoother: the EKF forward pass plus a backward pass over a sliding window.

Live, ``rts`` reports exactly what the EKF reports (the filtered newest state: a smoother cannot see the future).
For replays, :meth:`Rts.smoothed` runs the backward pass over the window kept (the last ``history_s`` seconds,
every predict step) and returns one smoothed estimate per estimate ``push`` returned in that window: the
forward-backward Kalman smoothing paper 001 compares its SU estimator with. Backward pass (mean only)::

    C_k = P_k|k F_k' (P_k+1|k)^-1
    x_k|N = x_k|k + C_k (x_k+1|N - x_k+1|k)

with ``F_k`` the Jacobian at ``x_k|k``, recomputed, on the state's block (``P``): the offset of a receiver's heading the
forward pass estimates (:class:`~sumhe.baseline.ekf.OffsetFilter`) is not smoothed. A re-acquisition or a heading set-up
resets the filter's prior; the smoother does not carry information back across such a step. A restart of the filter
(numerical failure, data gap, :meth:`reset`) empties the window. A late fix's re-run (:mod:`.stream`) drops the steps
after the state it restarts from and makes them anew; each estimate returned is tied to the step at its state's time,
which the re-run makes again.

:class:`RtsBatch` (``rts-batch``) is the offline form for replays: ``push`` returns nothing and ``finish()`` the
smoothed drive, as ``su-batch`` does.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from sumhe.baseline import kinematics as kin
from sumhe.baseline.ekf import Ekf
from sumhe.baseline.kinematics import OMEGA, PHI, E, FloatArray, N, V
from sumhe.estimator.base import StateEstimate
from sumhe.frontend.fixes import LocalFix
from sumhe.messages import CanSample
from sumhe.settings import EstimationSettings, NoiseSettings

HISTORY_S = 300.0
"""Default length of the smoothing window (s): ~1 kB per CAN speed sample, ~15 MB at 50 Hz."""


@dataclass(slots=True)
class _Step:
    """One predict step: the prior at ``t`` (``dt`` after the previous step) and, once closed, the posterior."""

    index: int
    t: float
    dt: float
    x_prior: FloatArray
    P_prior: FloatArray
    x_post: FloatArray | None = None
    P_post: FloatArray | None = None
    restart: bool = False


class Rts(Ekf):
    """EKF with a Rauch-Tung-Striebel backward pass over the last ``history_s`` seconds (``rts``)."""

    name = "rts"

    def __init__(
        self,
        settings: EstimationSettings | None = None,
        noise: NoiseSettings | None = None,
        history_s: float = HISTORY_S,
    ) -> None:
        if not history_s > 0:
            raise ValueError(f"history_s: must be a positive number of seconds (inf: all), got {history_s!r}")
        self.history_s = history_s
        super().__init__(settings, noise)

    @staticmethod
    def tuned(settings: EstimationSettings) -> NoiseSettings:
        """The noise of its table, ``[estimator.rts]``."""
        return settings.estimator.rts

    def smoothed(self, epochs_only: bool = False) -> list[StateEstimate]:
        """The estimates ``push`` returned within the window (only those of GNSS epochs with ``epochs_only``),
        smoothed with every sample seen since."""
        if not self._steps:
            return []
        steps = list(self._steps)
        xs: list[FloatArray] = [self.x] * len(steps)
        for i in range(len(steps) - 2, -1, -1):
            cur, nxt = steps[i], steps[i + 1]
            assert cur.x_post is not None and cur.P_post is not None  # closed by the next step
            if nxt.restart:
                xs[i] = cur.x_post
                continue
            F = kin.step_jacobian(cur.x_post, nxt.dt)
            C = cur.P_post @ F.T @ np.linalg.pinv(nxt.P_prior, hermitian=True)
            xs[i] = kin.wrap_state(cur.x_post + C @ kin.state_difference(xs[i + 1], nxt.x_prior))
        times = [s.t for s in steps]
        out = []
        for t_step, est, epoch in self._reports:
            if epochs_only and not epoch:
                continue
            k = max(bisect.bisect_right(times, t_step) - 1, 0)
            step, x = steps[k], xs[k]
            if est.t != step.t:
                x = kin.step(x, est.t - step.t)
            out.append(
                dataclasses.replace(
                    est,
                    east_m=float(x[E]),
                    north_m=float(x[N]),
                    azimuth_rad=float(x[PHI] % (2.0 * math.pi)),
                    speed_mps=float(x[V]),
                    yaw_rate_rps=float(x[OMEGA]),
                )
            )
        return out

    def _reset_filter(self) -> None:
        super()._reset_filter()
        self._steps: deque[_Step] = deque()
        self._reports: deque[tuple[float, StateEstimate, bool]] = deque()
        """Each estimate returned, with the time of the step it was made at (the state's then)."""

    def _start(self, x0: FloatArray, P0: FloatArray) -> None:
        super()._start(x0, P0)
        self._steps.append(_Step(0, self._t_state, 0.0, self.x.copy(), self.P.copy(), restart=True))

    def _step(self, dt: float) -> None:
        last = self._steps[-1]
        last.x_post, last.P_post = self.x.copy(), self.P.copy()
        super()._step(dt)
        t = self._t_state + dt
        self._steps.append(_Step(last.index + 1, t, dt, self.x.copy(), self.P.copy()))
        oldest = self._history.oldest_t if self._history is not None else math.inf  # where a re-run may go back to
        while self._steps[0].t < min(t - self.history_s, oldest):
            self._steps.popleft()
        while self._reports and self._reports[0][0] < self._steps[0].t:
            self._reports.popleft()

    def _snapshot(self) -> object:
        return super()._snapshot(), self._steps[-1].index, self._steps[-1].restart

    def _restore(self, state: object) -> None:
        """The filter's state, and the steps as they were: those made since are dropped."""
        assert isinstance(state, tuple)
        own, index, restart = state
        super()._restore(own)
        while self._steps[-1].index > index:
            self._steps.pop()
        self._steps[-1].restart = restart

    def _inflate(self, kind: str, nu: FloatArray, R: FloatArray) -> None:
        super()._inflate(kind, nu, R)
        self._steps[-1].restart = True

    def _init_heading(self, phi: float, sigma: float) -> None:
        super()._init_heading(phi, sigma)
        self._steps[-1].restart = True

    def _on_report(self, estimate: StateEstimate, epoch: bool) -> None:
        self._reports.append((self._steps[-1].t, estimate, epoch))

    def _window(self) -> int:
        return len(self._steps)


class RtsBatch(Rts):
    """Offline RTS smoothing of a whole recorded drive (``rts-batch``), the peer of ``su-batch``.

    ``push`` runs the EKF and returns nothing; :meth:`finish` returns the smoothed estimates of every GNSS epoch
    (fixes and outage epochs) of the drive. The window is the whole drive: memory grows by ~1 kB per CAN speed
    sample (~200 MB per hour at 50 Hz).
    """

    name = "rts-batch"

    def __init__(
        self,
        settings: EstimationSettings | None = None,
        noise: NoiseSettings | None = None,
        history_s: float = math.inf,
    ) -> None:
        super().__init__(settings, noise, history_s)

    def push(self, sample: LocalFix | CanSample) -> list[StateEstimate]:
        """Feed one sample; nothing is returned before :meth:`finish`."""
        super().push(sample)
        return []

    def finish(self) -> list[StateEstimate]:
        """The smoothed estimates of the drive's GNSS epochs (call once, at the end of the drive)."""
        return self.smoothed(epochs_only=True)
