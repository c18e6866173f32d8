"""The yaw rate of a 3-axis IMU mounted any way: its angular rate about the up direction its accelerometer finds.

A CAN logger's own IMU (CSS Electronics' CANmod.gps, a telematics box's) is mounted where it fits: flat, on its side,
upside down, on a sloped dashboard. Which of its axes is vertical, and with which sign, differs from car to car, and
a config that names one axis (``can.signals.yaw_rate = "gnss_imu.AngularRateX"``) gives another car's roll or
pitch rate as its yaw rate. With the three angular rates and the three accelerations mapped
(``can.signals.yaw_rate = { message = ..., rates = [...], accelerations = [...] }``, :class:`sumhe.config.SignalSpec`)
the yaw rate is the component of the angular-rate vector along the up direction:

* up is the direction of the mean specific force of every sample so far: at rest an accelerometer reads gravity's
  reaction, +g along the axis that points up; a car's own accelerations (braking, turns) come and go and average
  out within minutes, and a drive starts at rest. The mean is taken once the samples point one way
  (:data:`COHERENCE`): a broken accelerometer gives no yaw rate, counted, instead of a wrong one;
* the component along it, for right-handed rate axes, is positive anticlockwise seen from above: the package's
  yaw-rate convention, whatever the mounting. The two lists name the same axes in the same order;
* where up is within :data:`AXIS_TILT_DEG` of one of the device's axes, that axis's rate alone (with its sign) is
  the yaw rate: so close, an accelerometer's offset (consumer MEMS parts specify zero-g offsets up to 40-80 mg:
  2-5 deg) cannot be told from a tilt, and the component would take in up to a sixth of the other two gyros'
  biases, which wander; the axis alone loses at most 2 % of the yaw rate's scale (at 11 deg, the band's edge), which
  the estimators' gain state (``sensors.can.yaw_rate_gain_max``, 15 %) learns.

Beyond that a tilt of the device in the car is taken out (the car's own attitude on the road, its grade and roll,
stays in, as in a yaw-rate sensor fixed to the body). An IMU whose accelerometer reads the other way (gravity as -g
up) or a left-handed rate triad gives the yaw rate with its sign turned: ``scale = -1``, as for a single signal; the
on-line check (:mod:`sumhe.frontend.sensor_check`) says so.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

COHERENCE = 0.8
"""The least ratio of the mean acceleration's magnitude to the mean magnitude at which the mean's direction is
taken for up: 1 at rest, 0.99 or more through the shared real drive (a car's horizontal accelerations come and go);
far below only when the readings point every way (a broken or unmapped accelerometer)."""
AXIS_TILT_DEG = 10.0
"""Up within this angle (deg) of one of the device's axes: the yaw rate is that axis's rate alone (module
docstring). With a band of :data:`AXIS_BAND_DEG` either way: the axis is taken once up comes within 9 deg and left
once it is beyond 11, so that a mounting near 10 deg does not switch back and forth as the mean settles (each switch
a step in the yaw rate's scale and bias)."""
AXIS_BAND_DEG = 1.0
_JOIN_COS = math.cos(math.radians(AXIS_TILT_DEG - AXIS_BAND_DEG))
_LEAVE_COS = math.cos(math.radians(AXIS_TILT_DEG + AXIS_BAND_DEG))
REPORT_AFTER = 1000
"""Samples after which how the IMU sits is logged (INFO: 10 s of a 100 Hz IMU), and again at each switch between its
axis alone and the rate about up."""


@dataclass(frozen=True, slots=True)
class Mounting:
    """How an IMU sits, as its accelerometer found it: ``up`` (a unit vector in its axes), whether the yaw rate is
    its nearest axis's rate alone (``on_axis``), and its signals (``rates``, ``accelerations``, axis by axis)."""

    up: tuple[float, float, float]
    on_axis: bool
    rates: tuple[str, ...]
    accelerations: tuple[str, ...]

    def describe(self) -> str:
        """One line: up in the accelerometer's axes, its tilt from the nearest axis, and the yaw rate taken."""
        nearest = max(range(3), key=lambda i: abs(self.up[i]))
        sign = "+" if self.up[nearest] > 0 else "-"
        tilt = math.degrees(math.acos(min(1.0, abs(self.up[nearest]))))
        parts = " ".join(f"{u:+.3f} {name}" for u, name in zip(self.up, self.accelerations, strict=True))
        rate = f"{sign}{self.rates[nearest]} alone" if self.on_axis else "the rate about up"
        return (
            f"the IMU's up: {parts} ({tilt:.1f} deg from {sign}{self.accelerations[nearest]}); the yaw rate is {rate}"
        )


class VerticalRate:
    """Yaw rates of one IMU (stateful: the running sum of its accelerations). ``rates`` and ``accelerations``: the
    signal names of its three axes, in the same order; ``name``: its key, for the log."""

    def __init__(self, rates: tuple[str, ...], accelerations: tuple[str, ...], name: str = "") -> None:
        self.rates, self.accelerations, self.name = rates, accelerations, name
        self._samples = 0
        self._x = self._y = self._z = 0.0
        """The sum of the accelerations (the signals' unit)."""
        self._norms = 0.0
        """The sum of their magnitudes."""
        self.on_axis = False
        """Whether the yaw rate is the nearest axis's rate alone (:data:`AXIS_TILT_DEG`)."""

    @property
    def signals(self) -> tuple[str, ...]:
        return self.rates + self.accelerations

    def __call__(self, values: Mapping[str, Any]) -> float | None:
        """The yaw rate of one sample (the rate signals' unit: the nearest axis's rate or the rate about up), its
        accelerations added to the mean first; NaN where an acceleration is not finite (nothing added); None while
        the mean points no one way."""
        a, b, c = self.accelerations
        ax, ay, az = float(values[a]), float(values[b]), float(values[c])
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        if not math.isfinite(norm):
            return math.nan
        self._x += ax
        self._y += ay
        self._z += az
        self._norms += norm
        size = self._size()
        if size is None:
            return None
        x, y, z = self._x, self._y, self._z
        p, q, r = self.rates
        nearest = max(abs(x), abs(y), abs(z))
        was = self.on_axis
        self.on_axis = nearest >= (_LEAVE_COS if was else _JOIN_COS) * size
        self._samples += 1
        if self._samples == REPORT_AFTER or (self.on_axis != was and self._samples > REPORT_AFTER):
            self._report()
        if self.on_axis:
            axis, along = (p, x) if nearest == abs(x) else (q, y) if nearest == abs(y) else (r, z)
            return float(values[axis]) if along > 0.0 else -float(values[axis])
        return (float(values[p]) * x + float(values[q]) * y + float(values[r]) * z) / size

    def up(self) -> tuple[float, float, float] | None:
        """The unit up vector in the device's axes, None while the mean points no one way (:data:`COHERENCE`)."""
        size = self._size()
        return None if size is None else (self._x / size, self._y / size, self._z / size)

    def mounting(self) -> Mounting | None:
        """How the IMU sits, as found so far; None while the mean points no one way."""
        up = self.up()
        return None if up is None else Mounting(up, self.on_axis, self.rates, self.accelerations)

    def _report(self) -> None:
        mounting = self.mounting()
        if mounting is not None:
            log.info("%s: %s (after %d samples)", self.name, mounting.describe(), self._samples)

    def _size(self) -> float | None:
        size = math.sqrt(self._x * self._x + self._y * self._y + self._z * self._z)
        return None if size == 0.0 or size < COHERENCE * self._norms else size
