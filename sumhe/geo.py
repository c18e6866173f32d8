"""WGS84 geodetic <-> local east/north/up, exact (through ECEF), with no zones or boundaries.

The local frame is tangent to the ellipsoid at a datum; east = x, north = y, up = z, metres.
Round trips are exact to well below a millimetre anywhere within hundreds of kilometres of the datum.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_EP2 = (WGS84_A**2 - WGS84_B**2) / WGS84_B**2


class _Maths(NamedTuple):
    """The functions the geodetic conversions need, from numpy (arrays) or math (floats: ~10x faster one by one)."""

    atan2: Callable[..., Any]
    hypot: Callable[..., Any]
    sin: Callable[..., Any]
    cos: Callable[..., Any]
    sqrt: Callable[..., Any]
    degrees: Callable[..., Any]
    radians: Callable[..., Any]


_NUMPY = _Maths(np.arctan2, np.hypot, np.sin, np.cos, np.sqrt, np.degrees, np.radians)
_MATH = _Maths(math.atan2, math.hypot, math.sin, math.cos, math.sqrt, math.degrees, math.radians)


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike) -> NDArray[np.float64]:
    """WGS84 latitude, longitude (deg) and ellipsoidal height (m) -> ECEF x, y, z (m), stacked last."""
    lat, lon, h = (np.asarray(v, dtype=float) for v in (lat_deg, lon_deg, alt_m))
    return np.stack(np.broadcast_arrays(*_ecef(lat, lon, h, _NUMPY)), axis=-1)


def _ecef(lat_deg: Any, lon_deg: Any, h: Any, m: _Maths) -> tuple[Any, Any, Any]:
    """:func:`geodetic_to_ecef` on arrays (``m`` = numpy) or floats (``m`` = math): ECEF x, y, z (m)."""
    lat, lon = m.radians(lat_deg), m.radians(lon_deg)
    sl, cl = m.sin(lat), m.cos(lat)
    n = WGS84_A / m.sqrt(1.0 - WGS84_E2 * sl * sl)
    x = (n + h) * cl * m.cos(lon)
    y = (n + h) * cl * m.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sl
    return x, y, z


def ecef_to_geodetic(xyz: ArrayLike) -> NDArray[np.float64]:
    """ECEF (m, stacked last) -> latitude, longitude (deg), height (m), stacked last.

    Bowring's closed-form start refined by two Newton-like iterations: sub-micrometre at road heights.
    """
    p_xyz = np.asarray(xyz, dtype=float)
    return np.stack(_geodetic(p_xyz[..., 0], p_xyz[..., 1], p_xyz[..., 2], _NUMPY), axis=-1)


def _geodetic(x: Any, y: Any, z: Any, m: _Maths) -> tuple[Any, Any, Any]:
    """:func:`ecef_to_geodetic` on arrays (``m`` = numpy) or floats (``m`` = math)."""
    lon = m.atan2(y, x)
    p = m.hypot(x, y)
    theta = m.atan2(z * WGS84_A, p * WGS84_B)
    lat = m.atan2(z + WGS84_EP2 * WGS84_B * m.sin(theta) ** 3, p - WGS84_E2 * WGS84_A * m.cos(theta) ** 3)
    for _ in range(2):
        h = _height(p, z, lat, m)
        n = WGS84_A / m.sqrt(1.0 - WGS84_E2 * m.sin(lat) ** 2)
        lat = m.atan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    return m.degrees(lat), m.degrees(lon), _height(p, z, lat, m)


def _height(p: Any, z: Any, lat: Any, m: _Maths) -> Any:
    """Height above the ellipsoid (m) at distance ``p`` from the axis, ``z`` along it, latitude ``lat`` (rad).

    ``p cos(lat) + z sin(lat) - a sqrt(1 - e2 sin^2 lat)`` is exact and stable everywhere; the textbook
    ``p / cos(lat) - N`` loses all accuracy near the poles (km of error within a metre of the axis).
    """
    sl, cl = m.sin(lat), m.cos(lat)
    return p * cl + z * sl - WGS84_A * m.sqrt(1.0 - WGS84_E2 * sl * sl)


def _one_point(a: object, b: object, c: object) -> bool:
    """Whether :meth:`LocalFrame.to_geodetic` (``a, b, c`` = east, north, up) and :meth:`LocalFrame.to_enu`
    (latitude, longitude, height) take their plain-float path for these arguments."""
    return type(a) is float and type(b) is float and isinstance(c, float | int)


@dataclass(frozen=True)
class LocalFrame:
    """A local east/north/up frame tangent to WGS84 at (lat0_deg, lon0_deg, alt0_m)."""

    lat0_deg: float
    lon0_deg: float
    alt0_m: float = 0.0
    _origin: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    _rot: NDArray[np.float64] = field(init=False, repr=False, compare=False)
    _rows: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)
    """Rows of the rotation and the origin as floats (the one-point path, :meth:`point_to_geodetic`)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lat0_deg) and -90.0 <= self.lat0_deg <= 90.0):
            raise ValueError(f"lat0_deg: not a latitude: {self.lat0_deg!r}")
        if not (math.isfinite(self.lon0_deg) and -180.0 <= self.lon0_deg <= 180.0):
            raise ValueError(f"lon0_deg: not a longitude: {self.lon0_deg!r}")
        lat, lon = math.radians(self.lat0_deg), math.radians(self.lon0_deg)
        sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        rot = np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])
        object.__setattr__(self, "_origin", geodetic_to_ecef(self.lat0_deg, self.lon0_deg, self.alt0_m))
        object.__setattr__(self, "_rot", rot)
        object.__setattr__(self, "_rows", (*map(tuple, rot.tolist()), tuple(self._origin.tolist())))

    def point_to_geodetic(self, east_m: float, north_m: float, up_m: float = 0.0) -> tuple[float, float, float]:
        """:meth:`to_geodetic` of one point as plain floats, the same bits: the path of every estimate, where the
        array and its three conversions back took half of the 2.5 us. Numbers not of type ``float`` (numpy's) take
        :meth:`to_geodetic`'s array path, as they do there."""
        if not _one_point(east_m, north_m, up_m):
            lat_deg, lon_deg, alt_m = self.to_geodetic(east_m, north_m, up_m).tolist()
            return lat_deg, lon_deg, alt_m
        (ex, ey, ez), (nx, ny, nz), (ux, uy, uz), (ox, oy, oz) = self._rows
        e, n, u = east_m, north_m, float(up_m)
        x, y, z = e * ex + n * nx + u * ux + ox, e * ey + n * ny + u * uy + oy, e * ez + n * nz + u * uz + oz
        lat, lon, alt = _geodetic(x, y, z, _MATH)
        return lat, lon, alt

    def to_enu(self, lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike = 0.0) -> NDArray[np.float64]:
        """Geodetic (deg, deg, m) -> east, north, up (m), stacked last. One point of plain floats (every fix) is
        carried to ECEF in floats, the same bits (numpy's set-up on 0-d arrays: 10.4 -> 1.8 us a fix)."""
        if _one_point(lat_deg, lon_deg, alt_m):
            ecef = np.array(_ecef(lat_deg, lon_deg, alt_m, _MATH))
        else:
            ecef = geodetic_to_ecef(lat_deg, lon_deg, alt_m)
        return (ecef - self._origin) @ self._rot.T

    def to_geodetic(self, east_m: ArrayLike, north_m: ArrayLike, up_m: ArrayLike = 0.0) -> NDArray[np.float64]:
        """East, north, up (m) -> latitude, longitude (deg), height (m), stacked last."""
        if _one_point(east_m, north_m, up_m):  # one estimate
            return np.array(self.point_to_geodetic(east_m, north_m, up_m))  # type: ignore[arg-type]
        enu = np.stack(np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (east_m, north_m, up_m))), -1)
        return ecef_to_geodetic(enu @ self._rot + self._origin)
