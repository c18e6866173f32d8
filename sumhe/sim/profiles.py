"""Simulator profiles: ``kind`` (the defaults: today's drives) and ``realistic`` (every real-car error drawn).

A profile turns (seed, a few fixed fields) into concrete :class:`SimSettings`: the ``realistic`` profile draws
each error of :data:`REALISTIC` from its range with a random stream of its own (``default_rng([seed,
PROFILE_STREAM])``: the drive's own streams stay independent), always all of them in the same order, so a
fixed field changes no other draw. The drawn values are the settings, so ``scenario.toml`` holds them all and
regenerates the drive without drawing again. The ranges cover what real sensors do (docs/simulator.md gives
each one's evidence); they are not fitted to one recording.

For the benchmarks: ``profile_settings("realistic", seed=N, scenario="urban", outages=((60, 10),))`` or
``simulate_profile(...)`` for the drive itself.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from sumhe.sim.drive import Drive, simulate
from sumhe.sim.settings import SimSettings

PROFILE_STREAM = 0x5EA1
"""Second entropy word of the profile's random stream (the first is the seed)."""


@dataclass(frozen=True, slots=True)
class Uniform:
    """A value drawn uniformly from [low, high]."""

    low: float
    high: float

    def draw(self, rng: np.random.Generator) -> float:
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True, slots=True)
class Choice:
    """One of ``options``, with probabilities ``weights`` (equal when empty)."""

    options: tuple[Any, ...]
    weights: tuple[float, ...] = ()

    def draw(self, rng: np.random.Generator) -> Any:
        p = np.array(self.weights) / sum(self.weights) if self.weights else None
        value = self.options[int(rng.choice(len(self.options), p=p))]
        return float(value) if isinstance(value, float) else value


Range = Uniform | Choice

REALISTIC: dict[str, Range | Any] = {
    # GNSS clock and latency
    "gps_time_offset_s": Uniform(-0.3, 0.3),
    "gps_clock_drift_ppm": Uniform(-80.0, 80.0),
    "gps_latency_s": Uniform(0.04, 0.35),
    "gps_latency_jitter_s": Uniform(0.01, 0.06),
    "gps_rate_hz": Choice((1.0, 5.0, 10.0), (0.4, 0.2, 0.4)),
    "gps_drop_rate": Uniform(0.0, 0.05),
    # GNSS position and velocity errors
    "gps_error": "walk",
    "gps_error_m": Uniform(0.5, 2.0),
    "gps_walk_tau_s": Uniform(10.0, 120.0),
    "multipath_per_min": Uniform(0.0, 1.0),
    "multipath_min_m": 2.0,
    "multipath_max_m": 15.0,
    "gps_outliers_per_min": Uniform(0.5, 4.0),
    "gps_outlier_m": Uniform(1.5, 5.0),
    "gps_velocity_sigma_mps": Uniform(0.03, 0.2),
    "gps_velocity_tau_s": Uniform(0.5, 3.0),
    # NMEA
    "gps_nmea_hdop": Choice((False, True)),
    "gps_nmea_gst": Choice((False, True), (0.8, 0.2)),
    "gps_talker": Choice(("GP", "GN")),
    # geometry
    "antenna_forward_m": Uniform(-0.5, 2.5),
    "antenna_left_m": Uniform(-0.4, 0.4),
    "thrust_angle_deg": Uniform(-1.0, 1.0),
    "sideslip_deg_per_mps2": Uniform(0.05, 0.4),
    # CAN sensors
    "speed_scale": Uniform(0.985, 1.03),
    "speed_noise_mps": Uniform(0.01, 0.05),
    "yaw_rate_bias_dps": Uniform(-0.6, 0.6),
    "yaw_rate_bias_drift_dps": Uniform(0.0, 0.05),
    "yaw_rate_scale": Uniform(0.9, 1.1),
    "yaw_rate_noise_dps": Uniform(0.05, 0.3),
    "can_sensor_delay_s": Uniform(0.01, 0.08),
    # CAN layout and sources
    "can_layout": "production",
    "speed_source": Choice(("broadcast", "obd"), (0.7, 0.3)),
    "yaw_rate_quantum_dps": Choice((0.01, 0.1, 0.244, 0.25)),
    "speed_quantum_kmh": Choice((0.01, 0.05, 0.1)),
    "obd_rate_hz": Choice((1.0, 2.0, 4.0), (0.2, 0.6, 0.2)),
    "obd_delay_s": Uniform(0.0, 0.3),
    "obd_rounding": Choice(("round", "floor")),
    "imu_sign": Choice((1, -1)),
    # host timestamps
    "can_poll_max_s": Uniform(0.004, 0.02),
    "can_ecu_jitter_s": Uniform(0.0001, 0.002),
    "can_burst_per_min": Uniform(0.0, 6.0),
}
"""The ``realistic`` profile: each SimSettings field's range (a plain value is fixed)."""

PROFILES: dict[str, Mapping[str, Range | Any]] = {"kind": {}, "realistic": REALISTIC}
"""Profile name -> the fields it draws or fixes; ``kind`` leaves every field at its default."""


def profile_settings(profile: str = "realistic", seed: int = 0, **fixed: Any) -> SimSettings:
    """The settings of one drive of ``profile`` (``kind`` or ``realistic``) for ``seed``; ``fixed`` fields
    (scenario, duration_s, outages, ...) are set as given, overriding any draw. ValueError naming a bad name."""
    if profile not in PROFILES:
        raise ValueError(f"profile: unknown {profile!r} (known: {', '.join(PROFILES)})")
    known = {f.name for f in dataclasses.fields(SimSettings)}
    for name in fixed:
        if name not in known or name in ("profile", "seed"):
            raise ValueError(f"{name}: not a settings field a profile can fix")
    rng = np.random.default_rng([seed, PROFILE_STREAM])
    drawn: dict[str, Any] = {}
    for name, spec in PROFILES[profile].items():
        drawn[name] = spec.draw(rng) if isinstance(spec, Uniform | Choice) else spec
    if "outages" in fixed:
        fixed["outages"] = tuple(tuple(o) for o in fixed["outages"])
    extra = {"profile": profile} if profile != "kind" else {}
    return SimSettings(seed=seed, **{**drawn, **extra, **fixed})


def simulate_profile(profile: str = "realistic", seed: int = 0, **fixed: Any) -> Drive:
    """``simulate(profile_settings(profile, seed, **fixed))``: e.g. ``simulate_profile("realistic", 3,
    scenario="highway", outages=((60.0, 30.0),))``."""
    return simulate(profile_settings(profile, seed, **fixed))
