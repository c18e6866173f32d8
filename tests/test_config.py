import dataclasses
from pathlib import Path

import pytest

from sumhe.config import Config, load_config, parse_host_port, require_signals
from sumhe.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
REAL_DRIVE = REPO.parent / "shared" / "data" / "real_drives" / "canedge_obd_2021-07-26_a"
LOGGER_DBCS = {"canmod-gps.dbc"}
"""DBCs that ship with a logger and are found beside its logs (never copied into the repo)."""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


def test_every_example_config_loads():
    configs = sorted((REPO / "configs").glob("*.toml"))
    assert configs, "configs/ has example configs"
    for path in configs:
        cfg = load_config(path, env={})
        for name in cfg.can.dbc_files:
            if name in LOGGER_DBCS:
                with pytest.raises(ConfigError, match=r"can\.dbc: file not found: canmod-gps\.dbc \(looked in"):
                    cfg.resolve_path(name, "can.dbc")
                if REAL_DRIVE.is_dir():
                    beside = dataclasses.replace(cfg, log_dirs=(REAL_DRIVE,))
                    assert beside.resolve_path(name, "can.dbc") == REAL_DRIVE / name
            else:
                assert cfg.resolve_path(name, "can.dbc").is_file()


def test_defaults_are_socketcan_on_vcan0_on_linux(monkeypatch):
    monkeypatch.setattr("sys.platform", "linux")
    cfg = Config()
    assert cfg.can.channel == "vcan0"
    from sumhe.config import default_can_interface

    assert default_can_interface() == "socketcan"


def test_signal_mapping_string_and_table_forms(tmp_path):
    cfg = load_config(
        _write(
            tmp_path,
            '[can.signals]\nspeed = "SPEED.SPEED"\n'
            'yaw_rate = { signal = "KINEMATICS.YAW_RATE", scale = -1.0, unit = "deg/s" }\n',
        ),
        env={},
    )
    assert cfg.can.signals["speed"].name == "SPEED.SPEED"
    assert cfg.can.signals["yaw_rate"].scale == -1.0
    assert cfg.can.signals["yaw_rate"].unit == "deg/s"


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[can]\nbitrate = 'fast'\n", "can.bitrate"),
        ("[can]\nchanel = 'vcan0'\n", "can.chanel"),
        ("[cann]\nchannel = 'vcan0'\n", "cann"),
        ("[can.signals]\nspeed = 'SPEED'\n", "can.signals.speed"),
        ("[can.signals]\nvelocity = 'A.B'\n", "can.signals.velocity"),
        ("[can.signals]\nspeed = { signal = 'A.B', scale = 0 }\n", "can.signals.speed.scale"),
        ("[gps]\nbaudrate = -1\n", "gps.baudrate"),
        ("[gps]\nlatency_s = -0.1\n", "gps.latency_s"),
        ("[datum]\nmode = 'fixed'\n", "datum.lat"),
        ("[datum]\nmode = 'fixed'\nlat = 91.0\nlon = 0.0\n", "datum.lat"),
        ("[output]\nudp = ['localhost']\n", "output.udp: 'localhost' is not a host:port destination"),
        ("[output]\njson = ['localhost']\n", "output.json: 'localhost' is not a host:port destination"),
        ("[output]\nnmea = ['127.0.0.1:0']\n", "output.nmea"),
        ("[output]\nstatus_udp = 'x'\n", "output.status_udp"),
        ("[output]\nformats = ['xml']\n", "output.formats"),
        ("[output]\nudp = '127.0.0.1:1'\n", "output.udp"),
        ("[output]\nudp = ['127.0.0.1:1']\njson = ['127.0.0.1:2']\n", "output.udp: replaced by output.json"),
        ("[estimator]\nmodel = 'su9'\n", "estimator.model"),
        ("[sensors.can]\nspeed_rounding = 'down'\n", "sensors.can.speed_rounding"),
        ("[sensors.can]\nspeed_delay_s = 1.5\n", "sensors.can.speed_delay_s"),
        ("[estimator.mhe]\nfix_correlation_s = -1.0\n", "estimator.mhe.fix_correlation_s"),
        ("can = 3\n", "can"),
    ],
)
def test_errors_name_the_file_and_the_key(tmp_path, text, key):
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_config(path, env={})
    msg = str(err.value)
    assert str(path) in msg
    assert key in msg


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml", env={})
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(_write(tmp_path, "[can\n"), env={})


def test_missing_dbc_names_the_key(tmp_path):
    cfg = load_config(_write(tmp_path, "[can]\ndbc = ['dbc/obd2.dbc', 'no/such.dbc']\n"), env={})
    with pytest.raises(ConfigError, match=r"can\.dbc: file not found: no/such\.dbc"):
        _ = cfg.dbc_paths


def test_dbc_files_are_found_beside_the_logs_too(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "logger.dbc").write_text('VERSION ""\n')
    cfg = load_config(_write(tmp_path, "[can]\ndbc = ['dbc/obd2.dbc', 'logger.dbc']\n"), env={})
    assert cfg.can.dbc_files == ("dbc/obd2.dbc", "logger.dbc")
    with pytest.raises(ConfigError, match=r"logger\.dbc"):
        _ = cfg.dbc_paths
    paths = dataclasses.replace(cfg, log_dirs=(logs,)).dbc_paths
    assert paths[0].name == "obd2.dbc" and paths[0].is_file()
    assert paths[1] == logs / "logger.dbc"


def test_precedence_overrides_then_env_then_file(tmp_path):
    path = _write(tmp_path, "[can]\nchannel = 'can0'\nbitrate = 250000\n")
    cfg = load_config(path, env={"SUMHE_CAN__CHANNEL": "vcan1", "SUMHE_CAN__BITRATE": "500000"})
    assert (cfg.can.channel, cfg.can.bitrate) == ("vcan1", 500000)
    cfg = load_config(path, env={"SUMHE_CAN__CHANNEL": "vcan1"}, overrides={"can.channel": "vcan2"})
    assert cfg.can.channel == "vcan2"
    with pytest.raises(ConfigError, match="environment"):
        load_config(path, env={"SUMHE_NOPE__X": "1"})


def test_settings_are_frozen(tmp_path):
    cfg = load_config(_write(tmp_path, ""), env={})
    with pytest.raises(AttributeError):
        cfg.can.channel = "x"  # type: ignore[misc]


@pytest.mark.parametrize("text", ["127.0.0.1:5005", "[::1]:5005", "localhost:1"])
def test_parse_host_port_accepts(text):
    host, port = parse_host_port(text)
    assert port in (5005, 1) and host


@pytest.mark.parametrize("text", ["127.0.0.1", ":5005", "h:0", "h:70000", "h:x"])
def test_parse_host_port_rejects(text):
    with pytest.raises(ValueError):
        parse_host_port(text)


@pytest.mark.parametrize(
    ("env", "blamed", "key"),
    [
        (
            {"SUMHE_CAN__CHANEL": "vcan1"},
            "environment variable SUMHE_CAN__CHANEL",
            "can.chanel: unknown key (did you mean",
        ),
        ({"SUMHE_GPS__BAUDRATE": "fast"}, "environment variable SUMHE_GPS__BAUDRATE", "gps.baudrate"),
        ({"SUMHE_OUTPUT__JSON": '["localhost"]'}, "environment variable SUMHE_OUTPUT__JSON", "output.json"),
        ({"SUMHE_CAN__SIGNALS__SPEED": "X"}, "environment variable SUMHE_CAN__SIGNALS__SPEED", "can.signals.speed"),
        ({"SUMHE_CAN_CHANNEL": "vcan1"}, "environment variable SUMHE_CAN_CHANNEL", "SUMHE_CAN__CHANNEL"),
    ],
)
def test_errors_from_the_environment_blame_the_variable_not_the_file(tmp_path, env, blamed, key):
    path = _write(tmp_path, "[can]\nchannel = 'can0'\n")
    with pytest.raises(ConfigError) as err:
        load_config(path, env=env)
    msg = str(err.value)
    assert msg.startswith(blamed + ": ") and key in msg
    assert str(path) not in msg


def test_a_setting_in_the_environment_is_blamed_by_later_checks(tmp_path):
    cfg = load_config(_write(tmp_path, ""), env={"SUMHE_CAN__DBC": "no/such.dbc"})
    assert cfg.blame("can.dbc") == "environment variable SUMHE_CAN__DBC"
    assert cfg.blame("can.channel") == cfg.source
    with pytest.raises(ConfigError, match=r"^environment variable SUMHE_CAN__DBC: can\.dbc: file not found"):
        _ = cfg.dbc_paths
    cfg = load_config(None, env={}, overrides={"can.signals": {"speed": "A.B"}})
    assert cfg.blame("can.signals.speed") == "command line"


def test_speed_and_yaw_rate_are_required_with_the_key_named(tmp_path):
    path = _write(tmp_path, '[can.signals]\nspeed = "ESP_VEHICLE_SPEED.VEHICLE_SPEED"\n')
    with pytest.raises(ConfigError, match=rf"^{path}: can\.signals\.yaw_rate: not mapped"):
        require_signals(load_config(path, env={}))
    cfg = load_config(path, env={"SUMHE_CAN__SIGNALS__YAW_RATE": "ESP_YAW_RATE.YAW_RATE"})
    require_signals(cfg)
    assert cfg.can.signals["yaw_rate"].signal == "YAW_RATE"


def test_one_destination_list_per_format_and_the_old_keys_still_read(tmp_path, caplog):
    cfg = load_config(_write(tmp_path, '[output]\njson = ["127.0.0.1:5005"]\nnmea = ["[::1]:10110"]\n'), env={})
    assert cfg.output.formats == {"json": ("127.0.0.1:5005",), "nmea": ("[::1]:10110",)}
    assert load_config(None, env={}).output.formats == {"json": ("127.0.0.1:5005",)}
    old = _write(tmp_path, '[output]\nudp = ["127.0.0.1:1"]\nformats = ["nmea"]\n')
    cfg = load_config(old, env={})
    assert cfg.output.formats == {"nmea": ("127.0.0.1:1",)}
    assert (
        'output.udp and output.formats: replaced by one destination list per format; write nmea = ["127.0.0.1:1"]'
        in (caplog.text)
    )
