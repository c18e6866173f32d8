"""The ground truth of a simulated drive, and its CSV file ``truth.csv``.

Columns (SI, angles in rad): ``t`` (Unix s, the clock of the CAN and NMEA receive times), ``lat``/``lon``
(deg, WGS84) and ``east``/``north`` (m from the datum) of antenna 1 = the rear-axle centre, ``azimuth``
(clockwise from north, [0, 2 pi)), ``speed`` (m/s), ``yaw_rate`` (rad/s, anticlockwise positive), ``accel``
(m/s^2, longitudinal), ``steering`` (road-wheel angle, rad, left positive), and the extra states the sensors
carry: ``speed_scale`` (CAN speed / true speed) and ``yaw_rate_bias`` (rad/s, added to the CAN yaw rate);
with two antennas also ``lat2``/``lon2``/``east2``/``north2`` of antenna 2.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

_FORMATS = {
    "t": "%.4f",
    "lat": "%.9f",
    "lon": "%.9f",
    "east": "%.4f",
    "north": "%.4f",
    "azimuth": "%.6f",
    "speed": "%.4f",
    "yaw_rate": "%.6f",
    "accel": "%.4f",
    "steering": "%.6f",
    "speed_scale": "%.6f",
    "yaw_rate_bias": "%.8f",
    "lat2": "%.9f",
    "lon2": "%.9f",
    "east2": "%.4f",
    "north2": "%.4f",
}
_SECOND_ANTENNA = ("lat2", "lon2", "east2", "north2")


@dataclass(frozen=True, eq=False)
class Truth:
    """Equal-length arrays of the true state (see the module docstring for names and units)."""

    t: FloatArray
    lat: FloatArray
    lon: FloatArray
    east: FloatArray
    north: FloatArray
    azimuth: FloatArray
    speed: FloatArray
    yaw_rate: FloatArray
    accel: FloatArray
    steering: FloatArray
    speed_scale: FloatArray
    yaw_rate_bias: FloatArray
    lat2: FloatArray | None = None
    lon2: FloatArray | None = None
    east2: FloatArray | None = None
    north2: FloatArray | None = None

    def __post_init__(self) -> None:
        for name, value in self.columns().items():
            if np.shape(value) != np.shape(self.t):
                raise ValueError(f"{name}: expected the shape of t {np.shape(self.t)}, got {np.shape(value)}")

    def __len__(self) -> int:
        return len(self.t)

    def columns(self) -> dict[str, FloatArray]:
        """The arrays present, by column name, in file order."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None}

    @functools.cached_property
    def _unwrapped_azimuth(self) -> FloatArray:
        """The azimuth unwrapped, once per truth: a drive's whole array, which :meth:`at` called sample by sample
        had unwrapped again at every call (a 140 s drive's 14 000 calls: 50 s)."""
        return np.unwrap(self.azimuth)

    def at(self, t: ArrayLike) -> Truth:
        """Linear interpolation at times ``t`` (Unix s; clamped to the first/last sample); the azimuth is
        interpolated unwrapped and wrapped back to [0, 2 pi). Returns arrays of the shape of ``t``."""
        tq = np.asarray(t, dtype=float)
        out: dict[str, FloatArray] = {}
        for name, value in self.columns().items():
            if name == "azimuth":
                out[name] = np.mod(np.interp(tq, self.t, self._unwrapped_azimuth), 2.0 * math.pi)
            else:
                out[name] = np.interp(tq, self.t, value)
        return Truth(**out)


def write_truth(truth: Truth, path: Path) -> None:
    """Write ``truth.csv`` (fixed decimals per column: the same truth gives the same bytes)."""
    columns = truth.columns()
    table = np.column_stack(list(columns.values()))
    np.savetxt(
        path, table, fmt=[_FORMATS[name] for name in columns], delimiter=",", header=",".join(columns), comments=""
    )


def load_truth(path: str | Path) -> Truth:
    """Read a ``truth.csv`` back; ValueError naming the file when it is unreadable, a column is missing, a value
    is not a number, there are no rows or time does not increase."""
    p = Path(path)
    try:
        header, _, rows = p.read_text(encoding="utf-8").partition("\n")
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"{p}: cannot read truth: {e}") from e
    names = header.strip().split(",")
    known = {f.name for f in dataclasses.fields(Truth)}
    missing = known - set(_SECOND_ANTENNA) - set(names)
    if missing:
        raise ValueError(f"{p}: missing truth columns: {', '.join(sorted(missing))}")
    if not rows.strip():
        raise ValueError(f"{p}: no truth rows")
    try:
        table = np.loadtxt(io.StringIO(rows), delimiter=",", ndmin=2)
    except ValueError as e:
        raise ValueError(f"{p}: cannot read truth: {e}") from e
    if table.shape[1] != len(names):
        raise ValueError(f"{p}: {table.shape[1]} values per row but {len(names)} columns in the header")
    columns = {name: table[:, i] for i, name in enumerate(names) if name in known}
    if np.any(np.diff(columns["t"]) <= 0):
        raise ValueError(f"{p}: t must be strictly increasing")
    return Truth(**columns)
