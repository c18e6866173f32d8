"""The plain-float twins of numpy's routines give numpy's bits."""

import numpy as np

from sumhe.floats import interp
from sumhe.model.su import integrate_odometry, odometry_end


def _same(a: float, b: float) -> bool:
    return (a == b and np.signbit(a) == np.signbit(b)) or (np.isnan(a) and np.isnan(b))


def test_interp_gives_numpys_bits_inside_beyond_at_knots_and_for_nan() -> None:
    rng = np.random.default_rng(7)
    for trial in range(400):
        k = int(rng.integers(1, 10))
        xp = np.sort(np.round(rng.uniform(0.0, 1.0, k), 2))  # repeated knots too
        fp = rng.normal(size=k)
        if trial % 5 == 0:
            fp[rng.integers(0, k)] = np.inf
        for x in [*rng.uniform(-0.2, 1.2, 6), *xp, np.nan, -0.0]:
            assert _same(interp(float(x), xp.tolist(), fp.tolist()), float(np.interp(x, xp, fp))), (x, xp, fp)


def test_numpys_interp_of_a_grid_is_interp_at_each_point() -> None:
    # the MHE's step motion interpolates a grid at once with numpy (sumhe.estimator.mhe.preintegration)
    rng = np.random.default_rng(9)
    for trial in range(300):
        k = int(rng.integers(1, 10))
        xp = np.sort(np.round(rng.uniform(0.0, 1.0, k), 2)).tolist()  # repeated knots too
        fp = rng.normal(size=k)
        if trial % 5 == 0:
            fp[rng.integers(0, k)] = np.inf
        grid = sorted([*rng.uniform(-0.2, 1.2, int(rng.integers(1, 12))).tolist(), *xp[: trial % 4]])
        got = np.interp(grid, xp, fp.tolist()).tolist()
        expected = [interp(x, xp, fp.tolist()) for x in grid]
        assert all(_same(a, b) for a, b in zip(got, expected, strict=True)), (grid, xp, fp)


def test_odometry_end_is_the_last_point_of_integrate_odometry_to_the_bit() -> None:
    rng = np.random.default_rng(8)
    for trial in range(300):
        n = int(rng.integers(2, 40))
        t = 1.7e9 + np.cumsum(rng.uniform(0.001, 0.05, n))
        v, w = rng.uniform(-2.0, 40.0, n), rng.normal(0.0, 0.5, n)
        start = (*rng.normal(0.0, 100.0, 2), -0.0 if trial % 4 == 0 else float(rng.normal(0.0, 3.0)))
        expected = [float(z[-1]) for z in integrate_odometry(t, v, w, *start)]
        got = odometry_end(t.tolist(), v.tolist(), w.tolist(), *start)
        assert all(_same(a, b) for a, b in zip(got, expected, strict=True))
