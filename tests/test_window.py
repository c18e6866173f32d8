"""The moving horizon's window policy and bookkeeping (sumhe.estimator.window) on synthetic GNSS sequences."""

from __future__ import annotations

import numpy as np
import pytest

from sumhe.config import load_config
from sumhe.errors import ConfigError
from sumhe.estimator.mhe.window import Plan, Window, outage_anchor, plan_window
from sumhe.settings import MheSettings

PERIOD = 0.1
POLICY = MheSettings(steps=20, steps_before=5, steps_after=4, max_steps=60, shrink_steps=2, max_merge=4)


def run(gps_pattern: list[bool], policy: MheSettings = POLICY) -> tuple[Window, list[int], list[int]]:
    """Append one step per flag (GNSS or not), apply each plan; the window, its lengths and GNSS epochs before the
    newest outage after every step."""
    win = Window(policy.max_steps + 1, n_states=1, n_outputs=1)
    lengths, kept_before = [], []
    for k, gps in enumerate(gps_pattern):
        win.append(k * PERIOD, np.zeros(1), np.array([gps]), np.ones(1), np.array([float(k)]))
        win.apply(plan_window(win.gps, win.t, PERIOD, policy))
        lengths.append(len(win))
        missing = np.flatnonzero(~win.gps)
        kept_before.append(int(win.gps[: missing[0]].sum()) if len(missing) else -1)
    return win, lengths, kept_before


def test_slides_at_its_normal_length_with_gnss() -> None:
    win, lengths, _ = run([True] * 50)
    assert lengths[:20] == list(range(1, 21))
    assert set(lengths[20:]) == {20}
    assert np.allclose(np.diff(win.t), PERIOD)
    assert win.x[-1, 0] == 49.0 and win.x[0, 0] == 30.0


def test_a_short_outage_fits_the_normal_window() -> None:
    _, lengths, _ = run([True] * 30 + [False] * 10 + [True] * 20)
    assert set(lengths[20:]) == {20}


def test_grows_through_an_outage_keeping_n_b_gnss_epochs() -> None:
    _, lengths, kept = run([True] * 30 + [False] * 40)
    # the outage is longer than N - N_B = 15 steps after 15 of its steps: from then on nothing is dropped
    assert lengths[30 + 14] == 20
    assert lengths[-1] == 5 + 40
    assert all(k == POLICY.steps_before for k in kept[30 + 16 :])
    assert lengths[30 + 16 :] == list(range(22, 46))


def test_shrinks_progressively_once_gnss_is_back_for_n_a_epochs() -> None:
    _, lengths, _ = run([True] * 30 + [False] * 40 + [True] * 30)
    assert lengths[69] == 45
    # N_A - 1 epochs after the return the window still grows; then it loses ``shrink`` steps per epoch (it drops
    # 1 + shrink, one is appended) down to N, and stays there
    assert lengths[70 : 70 + POLICY.steps_after - 1] == list(range(46, 46 + POLICY.steps_after - 1))
    after = lengths[70 + POLICY.steps_after - 1 :]
    assert after[: after.index(20)] == list(range(after[0], 20, -POLICY.shrink_steps))
    assert set(after[after.index(20) :]) == {20}


def test_coarsens_a_long_outage_to_n_max_and_keeps_the_anchor() -> None:
    win, lengths, kept = run([True] * 30 + [False] * 120)
    assert max(lengths) <= POLICY.max_steps
    assert lengths[-1] == POLICY.max_steps
    assert kept[-1] == POLICY.steps_before
    h = np.diff(win.t)
    assert h.max() <= POLICY.max_merge * PERIOD + 1e-9
    # the outage is coarsened behind its newest N steps, which are still at the GNSS period
    assert np.allclose(h[-(POLICY.steps - 1) :], PERIOD)
    assert np.all(h[POLICY.steps_before : POLICY.steps_before + 10] > PERIOD)
    assert win.t[-1] == pytest.approx(149 * PERIOD)
    assert win.t[-1] - win.t[POLICY.steps_before] > 11.5


def test_drops_the_oldest_steps_when_nothing_can_be_merged() -> None:
    policy = MheSettings(steps=20, steps_before=5, steps_after=4, max_steps=40, shrink_steps=2, max_merge=1)
    win, lengths, _ = run([True] * 30 + [False] * 80, policy)
    assert max(lengths) <= 40
    assert np.allclose(np.diff(win.t), PERIOD)
    assert not win.gps.any()


def test_outage_anchor() -> None:
    gps = np.array([True] * 10 + [False] * 3)
    assert outage_anchor(gps, POLICY) == 5
    assert outage_anchor(np.ones(10, dtype=bool), POLICY) is None
    assert outage_anchor(np.array([True] * 2 + [False] * 3), POLICY) == 0
    assert outage_anchor(np.array([True] * 10 + [False] * 3 + [True] * 4), POLICY) is None
    assert outage_anchor(np.array([True] * 10 + [False] * 3 + [True] * 3), POLICY) == 5


def test_window_container() -> None:
    win = Window(4, n_states=2, n_outputs=1)
    for k in range(4):
        win.append(float(k), np.array([k]), np.array([k % 2 == 0]), np.ones(1), np.array([k, -k]))
    with pytest.raises(ValueError, match="full"):
        win.append(9.0, np.zeros(1), np.zeros(1, dtype=bool), np.ones(1), np.zeros(2))
    win.offset[:, 0] = [0.0, 1.0, 2.0, 3.0]
    assert win.apply(Plan(drop=1, merge=(1,))) == [1]  # step 3 now follows step 1: its offset needs setting
    assert win.t.tolist() == [1.0, 3.0]
    assert win.offset[:, 0].tolist() == [1.0, 3.0]
    assert win.x[:, 1].tolist() == [-1.0, -3.0]
    assert win.gps.tolist() == [False, False]
    with pytest.raises(ValueError, match="not after"):
        win.append(3.0, np.zeros(1), np.zeros(1, dtype=bool), np.ones(1), np.zeros(2))
    win.append(4.0, np.zeros(1), np.zeros(1, dtype=bool), np.ones(1), np.zeros(2))
    assert win.offset[-1].tolist() == [0.0, 0.0]  # a new step has no offset
    assert win.apply(Plan(drop=1)) == []
    for k in range(2):
        win.append(5.0 + k, np.zeros(1), np.zeros(1, dtype=bool), np.ones(1), np.zeros(2))
    assert win.t.tolist() == [3.0, 4.0, 5.0, 6.0]
    assert win.apply(Plan(merge=(1, 2))) == [1]  # two neighbours merged away: one step spans them
    assert win.t.tolist() == [3.0, 6.0]
    win.clear()
    assert len(win) == 0


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("steps", 1),
        ("steps_before", 20),
        ("steps_before", -1),
        ("steps_after", -1),
        ("shrink_steps", -1),
        ("max_steps", 10),
        ("max_merge", 0),
    ],
)
def test_policy_rejects_bad_values(field: str, value: int) -> None:
    with pytest.raises(ValueError, match=field):
        MheSettings(**{**{"steps": 20, "steps_before": 5}, field: value})  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "value"),
    [("steps", 1), ("max_steps", 10), ("steps_before", 50), ("solver", "cplex"), ("gate_m", 0)],
)
def test_settings_reject_bad_mhe_values(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        MheSettings(**{field: value})  # type: ignore[arg-type]


def test_the_policy_is_the_mhe_table() -> None:
    config = load_config(overrides={"estimator.mhe.steps": 30, "estimator.mhe.steps_before": 7})
    p = config.estimation.estimator.mhe
    assert (p.steps, p.steps_before, p.max_steps) == (30, 7, 300)
    with pytest.raises(ConfigError, match=r"estimator\.mhe_steps: moved: set estimator\.mhe\.steps"):
        load_config(overrides={"estimator.mhe_steps": 30})
