"""quick_init and replace: the same records as the dataclass's own __init__ and ``dataclasses.replace``, still frozen,
and refused where they do not fit."""

from __future__ import annotations

import dataclasses
import inspect
import pickle

import pytest

from sumhe.estimator.base import StateEstimate
from sumhe.frontend.fixes import LocalFix
from sumhe.messages import CanSample, Estimate
from sumhe.records import quick_init, replace


@dataclasses.dataclass(frozen=True, slots=True)
class _Plain:
    a: float
    b: str = "x"
    c: int | None = None


_Quick = quick_init(dataclasses.make_dataclass("_Quick", [("a", float), ("b", str, "x"), ("c", "int | None", None)],
                                               frozen=True, slots=True))  # fmt: skip


def test_same_signature_and_values() -> None:
    def params(cls: type) -> list[tuple[str, object]]:
        return [(p.name, p.default) for p in inspect.signature(cls).parameters.values()]

    assert params(_Quick) == params(_Plain)
    for args, kwargs in [((1.0,), {}), ((1.0, "y"), {"c": 3}), ((), {"a": 2.0, "c": 4})]:
        assert dataclasses.astuple(_Quick(*args, **kwargs)) == dataclasses.astuple(_Plain(*args, **kwargs))
    with pytest.raises(TypeError):
        _Quick()  # type: ignore[call-arg]


def test_still_frozen_and_replaceable() -> None:
    s = CanSample(1.0, "speed", 2.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.value = 3.0  # type: ignore[misc]
    assert dataclasses.replace(s, value=3.0) == CanSample(1.0, "speed", 3.0)
    assert pickle.loads(pickle.dumps(s)) == s
    e = Estimate(1.0, 2.0, 3.0, 50.0, 14.0, 200.0, 0.1, 5.0, 0.0, "ok", "mhe")
    assert (e.window, e.error, e.hdop) == (0, None, None)
    assert StateEstimate(1.0, 2.0, 3.0, 0.1, 5.0, 0.0, "ok", "can").spread is None


def test_refuses_what_it_does_not_fit() -> None:
    @dataclasses.dataclass(frozen=True)
    class NoSlots:
        a: float

    @dataclasses.dataclass(slots=True)
    class NotFrozen:
        a: float

    @dataclasses.dataclass(frozen=True, slots=True)
    class Factory:
        a: list[float] = dataclasses.field(default_factory=list)

    @dataclasses.dataclass(frozen=True, slots=True)
    class Post:
        a: float

        def __post_init__(self) -> None:
            pass

    @dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
    class KeywordOnly:
        a: float

    for cls in (NoSlots, NotFrozen, Factory, Post, KeywordOnly):
        with pytest.raises(ValueError):
            quick_init(cls)
        with pytest.raises(ValueError):
            replace(cls(a=1.0), a=2.0)  # type: ignore[call-arg]


def test_replace_as_dataclasses_replace() -> None:
    fix = LocalFix(1.0, True, 2.0, 3.0, hdop=0.9, speed_mps=None)
    for changes in [{}, {"t": 1.5}, {"t": 2.0, "valid": False, "hdop": None}, {"fix": None, "frame": None}]:
        new = replace(fix, **changes)
        assert type(new) is LocalFix and new is not fix
        assert dataclasses.astuple(new) == dataclasses.astuple(dataclasses.replace(fix, **changes))
    plain = _Plain(1.0, "y", 3)
    assert replace(plain, c=None) == _Plain(1.0, "y", None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        replace(fix, t=3.0).t = 4.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        replace(fix, nope=1.0)
