"""Settings of the estimators (the ``[estimator]`` table of the config)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class EstimatorSettings:
    """Which estimator runs and with which vehicle model."""

    name: str = "mhe"
    model: str = "su5"

    def __post_init__(self) -> None:
        if self.model not in ("su5", "su7"):
            raise ValueError("model: must be 'su5' or 'su7'")
