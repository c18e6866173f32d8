"""Config edge cases (issue 15, item 5): nesting 10,000 deep in a file or a ``SUMHE_*`` variable, a huge or binary
file as the DBC; each a one-line error naming the key or file, exit 1, no traceback (``sumhe`` in a subprocess)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from sumhe.config import MAX_DEPTH, load_config
from sumhe.errors import ConfigError, printable

REPO = Path(__file__).resolve().parents[1]
DEEP = 10_000


def sumhe(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sumhe", *args],
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", **(env or {})},
        capture_output=True,
        text=True,
        timeout=120,
    )


def assert_one_clean_error(result: subprocess.CompletedProcess[str], *parts: str) -> None:
    assert result.returncode == 1
    assert "Traceback" not in result.stderr and "RecursionError" not in result.stderr
    (line,) = [x for x in result.stderr.splitlines() if x.startswith("error: ")]
    assert all(p in line for p in parts), line
    assert "\x1b" not in result.stderr and "\x07" not in result.stderr


@pytest.mark.parametrize("opener, closer", [("[", "]"), ("{a = ", "}")])
def test_a_file_nested_10000_deep_names_the_line_and_key(tmp_path, opener, closer):
    config = tmp_path / "deep.toml"
    config.write_text(f'[can]\nchannel = "vcan0"\nbitrate = {opener * DEEP}1{closer * DEEP}\n')
    result = sumhe("replay", "drive.log", "--config", str(config))
    assert_one_clean_error(result, str(config), "line 3: bitrate: nested more than")


def test_an_environment_variable_nested_10000_deep_names_the_variable_and_key():
    result = sumhe(
        "replay", "drive.log", "--config", str(REPO / "configs" / "default.toml"),
        env={"SUMHE_CAN__E2E": "[" * DEEP + "]" * DEEP},
    )  # fmt: skip
    assert_one_clean_error(result, "environment variable SUMHE_CAN__E2E: can.e2e: nested more than")


def test_nesting_the_parser_survives_is_still_limited_with_the_key(tmp_path):
    config = tmp_path / "deep.toml"
    config.write_text("[output]\njson = " + "[" * (MAX_DEPTH + 2) + "]" * (MAX_DEPTH + 2) + "\n")
    with pytest.raises(ConfigError, match=r"deep.toml: output.json: nested more than 16"):
        load_config(config, env={})
    with pytest.raises(ConfigError, match=r"SUMHE_CAN__SIGNALS: can.signals.a.a.a"):
        load_config(None, env={"SUMHE_CAN__SIGNALS": "{a=" * 20 + "1" + "}" * 20})


def test_a_50_mb_file_as_the_dbc_is_refused_unread(tmp_path):
    dbc = tmp_path / "huge.dbc"
    with dbc.open("wb") as f:
        f.truncate(50_000_000)
    config = tmp_path / "c.toml"
    config.write_text(f"[can]\ndbc = '{dbc}'\n[can.signals]\nspeed = 'A.B'\nyaw_rate = 'A.C'\n")
    result = sumhe("candump", str(tmp_path / "drive.log"), "--config", str(config))
    assert_one_clean_error(result, f"{dbc}: 50.0 MB, larger than can.dbc_max_mb = 32 MB")
    with pytest.raises(ConfigError, match=r"can\.dbc_max_mb: must be positive"):
        load_config(None, env={"SUMHE_CAN__DBC_MAX_MB": "0"})


def test_a_binary_dbc_error_escapes_terminal_control_characters(tmp_path):
    dbc = tmp_path / "binary.dbc"
    dbc.write_bytes(b"BO_ \x1b[2J\x1b]0;owned\x07\x00\xff" + os.urandom(4000))
    config = tmp_path / "c.toml"
    config.write_text(f"[can]\ndbc = '{dbc}'\n[can.signals]\nspeed = 'A.B'\nyaw_rate = 'A.C'\n")
    result = sumhe("candump", str(tmp_path / "drive.log"), "--config", str(config))
    assert_one_clean_error(result, f"{dbc}: not a valid CAN database", r"\x1b[2J")


def test_printable_escapes_c0_and_c1_controls_and_cuts():
    assert printable("a\x1b[31mb\x9bc\nd") == r"a\x1b[31mb\x9bc\nd"
    assert printable("é°x") == "é°x"
    assert printable("x" * 300, 10) == "x" * 10 + "..."
