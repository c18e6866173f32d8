"""Synthetic windows for the SU estimator tests: a vehicle on a circle (or a straight line), exactly.

Closed form for constant speed v and yaw rate omega (anticlockwise positive, so the azimuth falls):
``phi(t) = phi0 - omega t``, ``east = (v/omega)(cos phi - cos phi0)``, ``north = -(v/omega)(sin phi - sin phi0)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sumhe.geo import LocalFrame
from sumhe.messages import CanSample, GnssFix, Sample

FRAME = LocalFrame(50.0755, 14.4378, 250.0)
T0 = 1000.0


@dataclass(frozen=True)
class Motion:
    """Constant-turn motion (SI): speed v, yaw rate omega, initial azimuth phi0, antenna distance d."""

    v: float = 10.0
    omega: float = 0.2
    phi0: float = 0.3
    d: float = 1.0

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """East, north (m) of antenna 1 and azimuth (rad) at ``t`` s after the start."""
        phi = self.phi0 - self.omega * t
        if abs(self.omega) < 1e-12:
            return self.v * t * math.sin(self.phi0), self.v * t * math.cos(self.phi0), phi
        k = self.v / self.omega
        return k * (np.cos(phi) - math.cos(self.phi0)), -k * (np.sin(phi) - math.sin(self.phi0)), phi


def window(
    motion: Motion = Motion(),
    duration_s: float = 3.0,
    outage: tuple[float, float] | None = None,
    gps_noise_m: float = 0.0,
    bias_rps: float = 0.0,
    scale: float = 1.0,
    antennas: int = 1,
    seed: int = 0,
) -> list[Sample]:
    """Fixes at 10 Hz (none inside ``outage`` = (start, end) s) and CAN speed/yaw rate at 50 Hz, time-ordered.

    GNSS noise is uniform within +-``gps_noise_m`` per axis; the CAN speed is ``scale * v``, the CAN yaw
    rate ``omega + bias_rps``; fixes carry course, speed and a GST sigma of ``max(noise / sqrt 3, 5 mm)``.
    """
    rng = np.random.default_rng(seed)
    t_fix = np.round(np.arange(0.0, duration_s + 1e-9, 0.1), 6)
    if outage is not None:
        t_fix = t_fix[(t_fix < outage[0]) | (t_fix > outage[1])]
    east, north, phi = motion.at(t_fix)
    sigma = max(gps_noise_m / math.sqrt(3.0), 0.005)
    out: list[Sample] = []
    for ant in range(1, antennas + 1):
        e = east - (ant - 1) * motion.d * np.sin(phi) + rng.uniform(-1, 1, len(t_fix)) * gps_noise_m
        n = north - (ant - 1) * motion.d * np.cos(phi) + rng.uniform(-1, 1, len(t_fix)) * gps_noise_m
        geo = FRAME.to_geodetic(e, n, FRAME.alt0_m)
        for k, t in enumerate(t_fix):
            out.append(
                GnssFix(
                    t=T0 + float(t),
                    time_utc=None,
                    lat_deg=float(geo[k, 0]),
                    lon_deg=float(geo[k, 1]),
                    alt_m=0.0,
                    quality=4,
                    valid=True,
                    speed_mps=motion.v,
                    course_rad=float(phi[k] % (2 * math.pi)) if ant == 1 else None,
                    sigma_lat_m=sigma,
                    sigma_lon_m=sigma,
                    antenna=ant,
                )
            )
    for t in np.arange(0.0, duration_s + 1e-9, 0.02):
        out.append(CanSample(T0 + float(t), "speed", scale * motion.v))
        out.append(CanSample(T0 + float(t) + 0.001, "yaw_rate", motion.omega + bias_rps))
    return sorted(out, key=lambda s: s.t)


def truth(motion: Motion, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """East, north (m) of antenna 1 at service times ``t`` (s)."""
    east, north, _ = motion.at(np.asarray(t) - T0)
    return east, north
