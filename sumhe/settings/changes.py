"""Changing nested settings: ``with_changes(s, {"estimator.mhe.steps": 80, "can.delay_s": 0.02})``."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

T = TypeVar("T")


def with_changes(settings: T, changes: Mapping[str, Any]) -> T:
    """A copy of the frozen dataclass ``settings`` with the fields at the dotted paths of ``changes`` replaced
    (validated again on the way up); AttributeError naming a path that does not exist."""
    top: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for path, value in changes.items():
        node: Any = settings
        for name in path.split("."):
            if not (dataclasses.is_dataclass(node) and hasattr(node, name)):
                raise AttributeError(f"{type(settings).__name__} has no setting {path!r}")
            node = getattr(node, name)
        head, _, rest = path.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            top[head] = value
    for head, sub in nested.items():
        top[head] = with_changes(getattr(settings, head), sub)
    return dataclasses.replace(settings, **top)  # type: ignore[type-var]
