"""The estimators' small-matrix ``inv``/``solve``: numpy's results to the bit, with numpy's private LAPACK gufuncs
and with the public fallback where a numpy release has moved them."""

from __future__ import annotations

import contextlib
import importlib
import sys
import types

import numpy as np
import pytest

from sumhe.estimator import linalg


def _spd(n: int, seed: int) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


@pytest.fixture(params=["gufuncs", "fallback"])
def path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Both paths: numpy's private gufuncs (present in the numpy installed) and the public fallback."""
    if request.param == "fallback":
        monkeypatch.setattr(linalg, "_umath_linalg", None)
    else:
        assert linalg.gufuncs(), "this numpy has the private gufuncs: the fast path must be on"
    return str(request.param)


@pytest.mark.parametrize("n", [2, 5, 15])
def test_inv_and_solve_equal_numpy_to_the_bit(path: str, n: int) -> None:
    a = _spd(n, n)
    b = np.random.default_rng(n + 1).normal(size=n)
    m = np.random.default_rng(n + 2).normal(size=(n, 3))
    assert linalg.gufuncs() is (path == "gufuncs")
    assert np.array_equal(linalg.inv(a), np.linalg.inv(a))
    assert np.array_equal(linalg.solve(a, b), np.linalg.solve(a, b))
    assert np.array_equal(linalg.solve(a, m), np.linalg.solve(a, m))


def test_singular_raises_as_numpy(path: str) -> None:
    """The gufuncs' non-finite result comes with numpy's RuntimeWarning of an invalid value (once per place, as
    Python's warnings go), then numpy's own call raises."""
    a = np.ones((3, 3))

    def warned() -> contextlib.AbstractContextManager:
        return pytest.warns(RuntimeWarning, match="invalid value") if path == "gufuncs" else contextlib.nullcontext()

    with warned(), pytest.raises(np.linalg.LinAlgError):
        linalg.inv(a)
    with warned(), pytest.raises(np.linalg.LinAlgError):
        linalg.solve(a, np.ones(3))


@pytest.mark.parametrize("missing", ["module", "gufunc"])
def test_import_falls_back_when_numpy_moves_the_gufuncs(monkeypatch: pytest.MonkeyPatch, missing: str) -> None:
    """A numpy without ``numpy.linalg._umath_linalg`` (or without one of its gufuncs): the module still imports and
    uses the public calls."""
    import numpy.linalg

    private = numpy.linalg._umath_linalg  # type: ignore[attr-defined]
    if missing == "module":
        monkeypatch.setitem(sys.modules, private.__name__, None)  # None in sys.modules: the import raises ImportError
        monkeypatch.delattr(numpy.linalg, "_umath_linalg")
    else:
        moved = types.ModuleType(private.__name__)
        moved.inv = private.inv  # type: ignore[attr-defined]
        moved.solve = private.solve  # type: ignore[attr-defined]
        monkeypatch.setitem(sys.modules, private.__name__, moved)
        monkeypatch.setattr(numpy.linalg, "_umath_linalg", moved)
    try:
        reloaded = importlib.reload(linalg)
        assert not reloaded.gufuncs()
        a = _spd(4, 7)
        assert np.array_equal(reloaded.solve(a, np.arange(4.0)), np.linalg.solve(a, np.arange(4.0)))
    finally:
        monkeypatch.undo()
        importlib.reload(linalg)
    assert linalg.gufuncs()
