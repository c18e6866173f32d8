"""Settings by component: the tables, nested keys from file and environment, old keys refused, CAN quanta from
the DBC."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sumhe.config import Config, load_config
from sumhe.errors import ConfigError
from sumhe.estimator.registry import make_estimator
from sumhe.io.quanta import signal_quanta, with_signal_quanta
from sumhe.settings import CanModel, EstimationSettings, NoiseSettings, with_changes
from sumhe.settings.moved import MOVED
from sumhe.settings.peers import EKF_TUNED
from sumhe.settings.sensors import FALLBACK_SPEED_RESOLUTION_MPS, FALLBACK_YAW_RATE_RESOLUTION_RPS

from canframes import TOYOTA_DBC

DEG = math.pi / 180.0
KMH = 1.0 / 3.6


def _config(tmp_path: Path, text: str) -> Config:
    path = tmp_path / "c.toml"
    path.write_text(text)
    return load_config(path, env={})


def test_tables_by_component(tmp_path: Path) -> None:
    cfg = _config(
        tmp_path,
        "[vehicle]\nmax_speed_mps = 40.0\n"
        "[sensors.gnss]\nuere_m = 2.5\n[sensors.can]\ndelay_s = 0.03\n"
        "[estimator.mhe]\nsteps = 80\n[estimator.batch]\nwindow_s = 20.0\n"
        "[estimator.ekf]\ngps_scale = 3.0\n[estimator.pf]\nparticles = 50\n[estimator.pf.noise]\npos_rw = 0.01\n"
        "[estimator.imm]\nsojourn_turn_s = 1.5\n[estimator.imm.turn]\nyaw_rate_rw = 0.05\n",
    )
    s = cfg.estimation
    assert s.vehicle.max_speed_mps == 40.0 and s.gnss.uere_m == 2.5 and s.can.delay_s == 0.03
    assert s.estimator.mhe.steps == 80 and s.estimator.mhe.steps_before == 20
    assert s.estimator.batch.window_s == 20.0
    # a peer's table changes only the keys it names: the rest keep their tuned values
    assert s.estimator.ekf.gps_scale == 3.0 and s.estimator.ekf.pos_rw == EKF_TUNED.pos_rw
    assert s.estimator.pf.particles == 50 and s.estimator.pf.noise.pos_rw == 0.01
    assert s.estimator.pf.noise.scale_rw == EstimationSettings().estimator.pf.noise.scale_rw
    assert s.estimator.imm.sojourn_s[1] == 1.5 and s.estimator.imm.turn.yaw_rate_rw == 0.05


def test_nested_keys_from_the_environment_and_the_command_line(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text("[estimator.mhe]\nsteps = 80\n")
    cfg = load_config(path, env={"SUMHE_ESTIMATOR__MHE__STEPS": "60", "SUMHE_SENSORS__CAN__DELAY_S": "0.01"})
    assert cfg.estimator.mhe.steps == 60 and cfg.sensors.can.delay_s == 0.01
    cfg = load_config(path, env={}, overrides={"estimator.mhe.steps": 70})
    assert cfg.estimator.mhe.steps == 70


@pytest.mark.parametrize(("old", "new"), sorted(MOVED.items()))
def test_old_keys_are_refused_naming_the_new_key(tmp_path: Path, old: str, new: str) -> None:
    section, key = old.split(".")
    with pytest.raises(ConfigError) as err:
        _config(tmp_path, f"[{section}]\n{key} = 1\n")
    assert old in str(err.value) and new.split(" ")[0] in str(err.value)


def test_old_keys_from_the_environment_are_refused_too() -> None:
    with pytest.raises(ConfigError, match=r"estimator\.mhe_steps: moved: set estimator\.mhe\.steps"):
        load_config(env={"SUMHE_ESTIMATOR__MHE_STEPS": "40"})


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[estimator.mhe]\nsteps = 1\n", "estimator.mhe.steps"),
        ("[estimator.mhe]\nsolver = 'cplex'\n", "estimator.mhe.solver"),
        ("[estimator.batch]\noverlap_s = 40.0\n", "estimator.batch.overlap_s"),
        ("[estimator.ekf]\ngate_prob = 2.0\n", "estimator.ekf.gate_prob"),
        ("[estimator.pf]\nparticles = 3\n", "estimator.pf.particles"),
        ("[estimator.pf.noise]\npos_rw = -1.0\n", "estimator.pf.noise.pos_rw"),
        ("[estimator]\nmhe = 3\n", "estimator.mhe"),
        ("[vehicle]\nmax_speed_mps = 0\n", "vehicle.max_speed_mps"),
        ("[sensors.gnss]\nuere = 1.0\n", "sensors.gnss.uere"),
        ("[sensors.can]\nspeed_scale_max = 1.5\n", "sensors.can.speed_scale_max"),
        ("[sensors.can]\nyaw_rate_resolution_rps = 0.0\n", "sensors.can.yaw_rate_resolution_rps"),
    ],
)
def test_bad_values_name_the_nested_key(tmp_path: Path, text: str, key: str) -> None:
    with pytest.raises(ConfigError) as err:
        _config(tmp_path, text)
    assert key in str(err.value)


def test_with_changes_replaces_nested_fields_and_validates() -> None:
    s = with_changes(EstimationSettings(), {"estimator.mhe.steps": 30, "can.delay_s": 0.02})
    assert s.estimator.mhe.steps == 30 and s.can.delay_s == 0.02 and s.estimator.mhe.max_steps == 300
    with pytest.raises(ValueError, match="steps"):
        with_changes(s, {"estimator.mhe.steps": 1})
    with pytest.raises(AttributeError, match=r"mhe\.stepz"):
        with_changes(s, {"estimator.mhe.stepz": 3})
    assert Config.of(s).estimation == s


def test_noise_settings_refuse_negative_or_non_finite_values() -> None:
    for field in ("pos_rw", "course_rad"):
        for value in (-1.0, math.nan):
            with pytest.raises(ValueError, match=field):
                NoiseSettings(**{field: value})


# ---- CAN quanta from the DBC -------------------------------------------------------------------------------------


def _toyota(tmp_path: Path, extra: str = "", yaw_scale: float = 1.0) -> Config:
    (tmp_path / TOYOTA_DBC.name).write_bytes(TOYOTA_DBC.read_bytes())
    return _config(
        tmp_path,
        f'[can]\ndbc = "{TOYOTA_DBC.name}"\ndbc_strict = false\n'
        f'signals.speed = "SPEED.SPEED"\n'
        f'signals.yaw_rate = {{ signal = "KINEMATICS.YAW_RATE", scale = {yaw_scale} }}\n{extra}',
    )


def test_resolutions_default_to_the_dbc_signals_scale(tmp_path: Path) -> None:
    quanta = signal_quanta(_toyota(tmp_path, yaw_scale=-1.0))
    assert quanta["yaw_rate"] == pytest.approx(0.244 * DEG)  # the production car's quantum, sign flip or not
    assert quanta["speed"] == pytest.approx(0.01 * KMH)
    can = with_signal_quanta(_toyota(tmp_path)).sensors.can
    assert can.yaw_rate_quantum_rps == pytest.approx(0.244 * DEG)
    assert can.speed_quantum_mps == pytest.approx(0.01 * KMH)
    est = make_estimator("ekf", _toyota(tmp_path))
    assert est.settings.can.yaw_rate_quantum_rps == pytest.approx(0.244 * DEG)  # type: ignore[attr-defined]


def test_a_resolution_set_explicitly_wins_over_the_dbc(tmp_path: Path) -> None:
    config = _toyota(tmp_path, "[sensors.can]\nyaw_rate_resolution_rps = 0.001\n")
    can = with_signal_quanta(config).sensors.can
    assert can.yaw_rate_quantum_rps == 0.001
    assert can.speed_quantum_mps == pytest.approx(0.01 * KMH)


def test_without_a_mapping_the_fallback_resolutions_hold() -> None:
    assert with_signal_quanta(Config()) == Config()
    can = CanModel()
    assert (can.speed_quantum_mps, can.yaw_rate_quantum_rps) == (
        FALLBACK_SPEED_RESOLUTION_MPS,
        FALLBACK_YAW_RATE_RESOLUTION_RPS,
    )
