"""The registered estimators as test parameters: one whose optional package is not installed is skipped, and the
skip says which package and extra it needs (``sumhe.estimator.registry.missing_requirement``)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import pytest

from sumhe.estimator.registry import estimator_names, missing_requirement


def estimator_params(names: Iterable[str] | None = None, live_only: bool = False) -> list[Any]:
    """``names`` (default: every registered one, ``live_only`` as :func:`estimator_names`) as ``pytest.param``s."""
    names = estimator_names(live_only=live_only) if names is None else names
    return [
        pytest.param(name, marks=pytest.mark.skipif(reason is not None, reason=reason or ""), id=name)
        for name in names
        for reason in [missing_requirement(name)]
    ]
