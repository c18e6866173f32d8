"""Validation of settings dataclasses: each helper raises ValueError naming the field (no I/O, no imports)."""

from __future__ import annotations

import math


def one_of(obj: object, name: str, allowed: tuple[str, ...]) -> None:
    """``obj.name`` is one of ``allowed``."""
    value = getattr(obj, name)
    if value not in allowed:
        raise ValueError(f"{name}: must be one of {', '.join(allowed)}, got {value!r}")


def positive(obj: object, *names: str) -> None:
    """Each ``obj.name`` is a positive finite number."""
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, int | float) and 0 < value < math.inf):
            raise ValueError(f"{name}: must be a positive finite number, got {value!r}")


def non_negative(obj: object, *names: str) -> None:
    """Each ``obj.name`` is a finite number >= 0."""
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, int | float) and 0 <= value < math.inf):
            raise ValueError(f"{name}: must be >= 0 and finite, got {value!r}")


def at_least(obj: object, minimum: int, *names: str) -> None:
    """Each ``obj.name`` is at least ``minimum``."""
    for name in names:
        value = getattr(obj, name)
        if value < minimum:
            raise ValueError(f"{name}: must be >= {minimum}, got {value!r}")
