"""Settings of the estimation components as frozen, validated dataclasses (no I/O: :mod:`sumhe.config` loads them
from TOML and the environment). Below both the config loader and the estimators, so neither imports the other
for them."""

from sumhe.settings.changes import with_changes
from sumhe.settings.estimators import (
    BatchSettings,
    EstimationSettings,
    EstimatorSettings,
    MheSettings,
)
from sumhe.settings.peers import GtsamSettings, ImmSettings, MskfSettings, NoiseSettings, ParticleSettings, UpfSettings
from sumhe.settings.sensors import CanModel, GnssModel, SensorSettings, VehicleSettings

__all__ = [
    "BatchSettings",
    "CanModel",
    "EstimationSettings",
    "EstimatorSettings",
    "GnssModel",
    "GtsamSettings",
    "ImmSettings",
    "MheSettings",
    "MskfSettings",
    "NoiseSettings",
    "ParticleSettings",
    "SensorSettings",
    "UpfSettings",
    "VehicleSettings",
    "with_changes",
]
