"""Estimators by name: a registry with lazy imports (python-can's ``BACKENDS``), extended by entry points.

The service, the replay and the benchmark build whichever estimator the config names with
:func:`make_estimator` and never branch on which one runs. An entry is ``name: (module, class)``; the class
provides ``from_config(config) -> Estimator`` (see :class:`sumhe.estimator.base.Estimator`). Only the module of
the estimator asked for is imported. Other packages add estimators through the ``sumhe.estimators`` entry-point
group (``name = "package.module:Class"``); built-in names win.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
from importlib.metadata import entry_points
from typing import Any

from sumhe.config import Config
from sumhe.errors import ConfigError
from sumhe.estimator.base import Estimator
from sumhe.io.quanta import with_signal_quanta

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "sumhe.estimators"

ESTIMATORS: dict[str, tuple[str, str]] = {
    "mhe": ("sumhe.estimator.mhe", "MovingHorizonEstimator"),
    "su-batch": ("sumhe.estimator.su_batch", "SuBatch"),
    "dead-reckoning": ("sumhe.baseline.dead_reckoning", "DeadReckoning"),
    "ekf": ("sumhe.baseline.ekf", "Ekf"),
    "rts": ("sumhe.baseline.rts", "Rts"),
    "rts-batch": ("sumhe.baseline.rts", "RtsBatch"),
    "ukf": ("sumhe.baseline.ukf", "Ukf"),
    "pf": ("sumhe.baseline.particle", "ParticleFilter"),
    "imm": ("sumhe.baseline.imm", "Imm"),
    "mskf-em": ("sumhe.baseline.mskf_em", "MskfEm"),
    "sr-upf": ("sumhe.baseline.sr_upf", "SrUpf"),
    "gtsam-fls": ("sumhe.baseline.gtsam_fls", "GtsamFls"),
}
"""Built-in estimators: name -> (module, class). Adding one is one line here."""


REQUIRES: dict[str, tuple[str, str]] = {"gtsam-fls": ("gtsam", "peers")}
"""Built-in estimators that need an optional package: name -> (its import name, the extra that installs it)."""


def missing_requirement(name: str) -> str | None:
    """Why the estimator ``name`` cannot be built here (its optional package is not installed); None if it can."""
    need = REQUIRES.get(name)
    if need is None or importlib.util.find_spec(need[0]) is not None:
        return None
    return f"estimator {name!r} needs the optional package {need[0]}: pip install 'sumhe[{need[1]}]'"


def _plugins() -> dict[str, str]:
    """Estimators of other packages: name -> ``module:Class``."""
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name not in ESTIMATORS}


OFFLINE: frozenset[str] = frozenset({"su-batch", "rts-batch"})
"""Offline smoothers: they answer at the end of a recorded drive (``finish()``), never live."""


def estimator_names(live_only: bool = False, available_only: bool = False) -> tuple[str, ...]:
    """Every estimator name known (built-in first, then entry points); ``live_only`` leaves out the offline ones,
    ``available_only`` those whose optional package is not installed (:func:`missing_requirement`)."""
    names = (*ESTIMATORS, *sorted(_plugins()))
    return tuple(
        n
        for n in names
        if not (live_only and n in OFFLINE) and not (available_only and missing_requirement(n) is not None)
    )


def check_live(name: str) -> None:
    """ConfigError when ``name`` is an offline smoother, which a live service cannot run."""
    if name in OFFLINE:
        live = ", ".join(estimator_names(live_only=True))
        raise ConfigError(f"estimator.name: {name!r} smooths recorded drives (sumhe replay); live: {live}")


def estimator_class(name: str) -> Any:
    """The class registered under ``name`` (imported now); ConfigError listing the known names if none is."""
    if name in ESTIMATORS:
        reason = missing_requirement(name)
        if reason is not None:
            raise ConfigError(f"estimator.name: {reason}")
        module_name, class_name = ESTIMATORS[name]
    else:
        target = _plugins().get(name)
        if target is None:
            raise ConfigError(f"estimator.name: unknown estimator {name!r} (known: {', '.join(estimator_names())})")
        module_name, _, class_name = target.partition(":")
    try:
        return getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as e:
        raise ConfigError(f"estimator.name: cannot load estimator {name!r} from {module_name}: {e}") from e


def make_estimator(name: str, config: Config) -> Estimator:
    """Build the estimator ``name`` from the config (``[estimator]``, ``[vehicle]``, ``[sensors]``; the CAN
    resolutions not set there from the DBC signals mapped, :func:`~sumhe.io.quanta.with_signal_quanta`)."""
    estimator: Estimator = estimator_class(name).from_config(with_signal_quanta(config))
    log.debug("estimator %s built from %s", name, config.source)
    return estimator
