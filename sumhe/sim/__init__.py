"""Drive simulator: seeded scenarios -> truth + CAN frames (candump -L) + NMEA, in the formats replay reads.

``simulate(SimSettings(...))`` returns a :class:`Drive` in memory; ``write_drive(drive, dir)`` writes
``drive.log``, ``drive.nmea``, ``truth.csv`` and ``scenario.toml``; ``load_truth`` reads ``truth.csv`` back.
The demo drive shipped with the package is in :func:`bundled_drive_dir`. ``profile_settings(profile, seed,
**fixed)`` / ``simulate_profile(...)`` give a drive of the ``kind`` or ``realistic`` profile
(:mod:`sumhe.sim.profiles`).
"""

from sumhe.sim.drive import Drive, bundled_drive_dir, simulate, write_drive
from sumhe.sim.profiles import PROFILES, profile_settings, simulate_profile
from sumhe.sim.settings import SimSettings, load_settings
from sumhe.sim.truth import Truth, load_truth

__all__ = [
    "PROFILES",
    "Drive",
    "SimSettings",
    "Truth",
    "bundled_drive_dir",
    "load_settings",
    "load_truth",
    "profile_settings",
    "simulate",
    "simulate_profile",
    "write_drive",
]
