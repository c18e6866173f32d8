"""The quanta of the CAN signals the estimators read, from the DBC: a signal's scale in SI units.

A production car's yaw rate may come in steps of 0.244 deg/s where the reference DBC has 0.01 deg/s: the CAN
sensor model (``[sensors.can]``) takes the resolution of each signal from the DBC mapping unless it is set.
"""

from __future__ import annotations

import dataclasses

from cantools.database import Database
from cantools.database.can import Signal

from sumhe.config import Config
from sumhe.errors import ConfigError
from sumhe.io.can import load_dbc, si_factor

RESOLUTION_KEYS = {"speed": "speed_resolution_mps", "yaw_rate": "yaw_rate_resolution_rps"}
"""CAN quantity -> its resolution in :class:`~sumhe.settings.CanModel`."""


def signal_quanta(config: Config) -> dict[str, float]:
    """Quantity -> the SI quantum of its mapped DBC signal (|DBC scale x unit factor x mapping scale|), for the
    quantities of :data:`RESOLUTION_KEYS` the config maps; ConfigError naming the key if the DBC cannot be read or
    lacks the signal."""
    mapped = {q: spec for q, spec in config.can.signals.items() if q in RESOLUTION_KEYS}
    if not mapped:
        return {}
    dbs = [load_dbc(path, config.can.dbc_strict, config.can.dbc_max_mb) for path in config.dbc_paths]
    out = {}
    for quantity, spec in mapped.items():
        key = f"{config.source}: can.signals.{quantity}"
        quanta = []
        for name in spec.rates or (spec.signal,):  # an IMU's yaw rate: its rate signals' coarsest
            signal = _find_signal(dbs, spec.message, name)
            if signal is None:
                raise ConfigError(f"{key}: {spec.message}.{name} is not in the DBC")
            factor = si_factor(spec.unit if spec.unit is not None else signal.unit, quantity)
            if factor is not None:
                quanta.append(abs(float(signal.scale) * factor * spec.scale))
        if quanta:
            out[quantity] = max(quanta)
    return out


def _find_signal(dbs: list[Database], message: str, signal: str) -> Signal | None:
    """The signal ``message.signal`` of the first DBC that has it, None if none does."""
    for db in dbs:
        try:
            return db.get_message_by_name(message).get_signal_by_name(signal)
        except KeyError:
            continue
    return None


def with_signal_quanta(config: Config) -> Config:
    """``config`` with the CAN resolutions not set in ``[sensors.can]`` taken from the DBC (:func:`signal_quanta`)."""
    can = config.sensors.can
    unset = {q: key for q, key in RESOLUTION_KEYS.items() if getattr(can, key) is None}
    if not unset:
        return config
    quanta = signal_quanta(config)
    changes = {key: quanta[q] for q, key in unset.items() if q in quanta}
    if not changes:
        return config
    sensors = dataclasses.replace(config.sensors, can=dataclasses.replace(can, **changes))
    return dataclasses.replace(config, sensors=sensors)
