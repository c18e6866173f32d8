"""The offset of a receiver's heading from the azimuth of the motion, considered in a recursive filter's error
estimate (never estimated: the estimates do not change).

A receiver's heading (HDT/THS, the body axis of its antennas or of its IMU) is off the azimuth of the velocity the
shared model moves along by the mounting's and the sideslip's offset, constant over minutes. A filter that weighs
headings as that azimuth follows them, so its azimuth carries their offset into an outage, where it makes an error
across the track that grows linearly with the way moved since the newest position fix (before it, the fixes hold
the position). The offset's variance is the config's bound read as sigmas (:func:`heading_offset_variance`).

:class:`FollowsHeadings` keeps whether the newest azimuth measured was a heading (a course over ground is the velocity's
azimuth: no offset). :class:`ConsideredHeadingOffset` adds the position the estimate had at the newest position fix and
the covariance the offset adds since it (:func:`considered_heading_offset`), for the filters whose error estimate is a
covariance of their own beliefs (``sr-upf``); it takes the position at that fix as right and the azimuth as off
by the whole offset. ``mskf-em`` carries the offset as a Schmidt consider parameter in its stages' joint covariance
(:class:`~sumhe.baseline.mskf_em.MskfEm`), which also holds what the offset makes of the position at the fix: between
fixes a filter follows the headings, and the fixes pull it back only in part (on the shared real drive 0.4-3.9 m across
the track, 1-sigma, at the starts of the 60 s outages). The Kalman filters estimate the offset as a state
(:class:`~sumhe.baseline.ekf.OffsetFilter`), ``gtsam-fls`` as a variable of its graph
(:class:`~sumhe.baseline.gtsam_fls.GtsamFls`), ``pf`` as one more value of each particle
(:class:`~sumhe.baseline.particle.ParticleFilter`).
"""

from __future__ import annotations

import math
from functools import cached_property

import numpy as np

from sumhe.baseline.kinematics import PHI, POSITION, E, FloatArray, N
from sumhe.baseline.stream import Gate, RecursiveEstimator
from sumhe.frontend.stream import FixMeasurement
from sumhe.messages import GpsStatus
from sumhe.settings import EstimationSettings

OFFSET_CORRELATION_S = 1800.0
"""The correlation time (s) of a receiver heading's offset where a filter estimates it (:class:`~.ekf.Ekf`): a
mounting's offset is constant, a sideslip's and a GNSS/IMU module's heading filter's move it over tens of
minutes."""


def heading_offset_variance(settings: EstimationSettings) -> float:
    """The variance (rad^2) of the offset of a receiver's heading from the vehicle's azimuth (mounting, sideslip)
    a filter considers: its bound ``gnss.azimuth_offset_max_rad`` read as ``estimator.r_cap_sigmas`` sigmas, as the
    MHE reads every bound (0.03 rad and 4: 0.43 deg), none where the config has no offset
    (``estimator.azimuth_offset``)."""
    e = settings.estimator
    return (settings.gnss.azimuth_offset_max_rad / e.r_cap_sigmas) ** 2 if e.azimuth_offset else 0.0


def offset_step(dt: float, variance: float) -> tuple[float, float]:
    """A receiver heading's offset as a first-order Gauss-Markov process about 0 of stationary ``variance`` (rad^2)
    and correlation time :data:`OFFSET_CORRELATION_S`, over ``dt`` s: how much of it is kept, and the variance the
    step adds."""
    keep = math.exp(-dt / OFFSET_CORRELATION_S)
    return keep, (1.0 - keep * keep) * variance


def considered_heading_offset(n: int, moved: FloatArray, variance: float) -> FloatArray:
    """The covariance (n x n, the layout of :mod:`.kinematics`) a receiver's heading offset of ``variance``
    (rad^2) adds to a filter that follows the headings and has moved by ``moved`` (east, north; m) since its
    newest position fix: the offset is in its azimuth, and an azimuth error ``d`` moves the dead-reckoned position
    by ``d (north, -east)`` of the way moved (to first order, through turns too)."""
    r = np.zeros(n)
    r[E], r[N], r[PHI] = moved[1], -moved[0], 1.0
    return variance * np.outer(r, r)


class FollowsHeadings(RecursiveEstimator):
    """A recursive estimator that knows whether the newest azimuth it measured was a receiver's heading
    (``_heading``; False: a course over ground)."""

    _heading: bool = False

    def _begin(self, fix: FixMeasurement) -> None:
        self._heading = fix.heading
        super()._begin(fix)

    def _angle_update(self, fix: FixMeasurement, lag: float) -> None:
        self._heading = fix.heading
        super()._angle_update(fix, lag)


class UsesPositionFixes(RecursiveEstimator):
    """A recursive estimator told of each position fix it used (:meth:`_position_used`), where what it counts
    since the newest one starts again."""

    def _gated_update(
        self, kind: str, z: FloatArray, R: FloatArray, lag: float, gate: Gate, t: float, sigma: float
    ) -> GpsStatus:
        status = super()._gated_update(kind, z, R, lag, gate, t, sigma)
        if kind == POSITION and status == "ok":
            self._position_used(z)
        return status

    def _position_used(self, z: FloatArray) -> None:
        """A position fix ``z`` (east, north; m) used."""
        raise NotImplementedError


class ConsideredHeadingOffset(FollowsHeadings, UsesPositionFixes):
    """A filter whose error estimate considers a heading's offset (the module docstring): ``_anchor`` is where its
    estimate was (east, north; m) at the newest position fix it used (``_position_anchor``); a subclass adds
    :meth:`_considered` to its covariance and keeps ``_anchor`` among its ``snapshot_attrs``."""

    _anchor: FloatArray

    @cached_property
    def _offset_variance(self) -> float:
        """:func:`heading_offset_variance` of the filter's settings (rad^2)."""
        return heading_offset_variance(self.settings)

    def reset_state(self) -> None:
        self._anchor = np.zeros(2)
        super().reset_state()

    def _begin(self, fix: FixMeasurement) -> None:
        super()._begin(fix)
        self._anchor = np.array([fix.east_m, fix.north_m])

    def _position_used(self, z: FloatArray) -> None:
        """A position fix ``z`` used: the way moved is counted from there on (``_anchor``: :meth:`_position_anchor`)."""
        self._anchor = self._position_anchor(z)

    def _position_anchor(self, z: FloatArray) -> FloatArray:
        """Where the estimate is (east, north; m) just after the position fix ``z`` updated it: its mean's."""
        return self._mean()[[E, N]]

    def _considered(self, P: FloatArray, position: FloatArray) -> FloatArray:
        """``P`` with the heading's offset considered where the newest azimuth measured was a heading, at the
        estimate's ``position`` (east, north; m): :func:`considered_heading_offset` of the way moved since the
        newest position fix."""
        if not self._heading:
            return P
        return P + considered_heading_offset(len(P), position - self._anchor, self._offset_variance)
