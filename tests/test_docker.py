"""The docker and systemd files stay consistent with the CLI and the repository (no Docker engine here)."""

import re
import shlex
import sys
from pathlib import Path

import pytest

from sumhe.cli import build_parser

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
DOCKER = REPO / "docker"


def _parses(argv: list[str]) -> None:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    assert args.command in argv


def _compose_commands() -> list[list[str]]:
    text = (DOCKER / "compose.yaml").read_text()
    return [[a.strip().strip('"') for a in m.split(",")] for m in re.findall(r"command:\s*\[(.*?)\]", text)]


def test_dockerfile_copies_only_what_exists_and_runs_a_real_command():
    text = (DOCKER / "Dockerfile").read_text()
    for line in text.splitlines():
        if line.startswith("COPY "):
            *sources, _dest = line.split()[1:]
            for src in sources:
                assert (REPO / src).exists(), f"Dockerfile copies missing {src}"
    assert re.search(r"^USER (?!root)\w+", text, re.M), "the image runs as a non-root user"
    entry = re.search(r'^ENTRYPOINT \["(\w+)"\]', text, re.M)
    cmd = re.search(r"^CMD (\[.*\])", text, re.M)
    assert entry and entry.group(1) == "sumhe" and cmd
    argv = [a.strip().strip('"') for a in cmd.group(1).strip("[]").split(",")]
    _parses(argv)
    config = argv[argv.index("--config") + 1]
    assert config.startswith("/etc/sumhe/") and (REPO / "configs" / Path(config).name).is_file()


def test_compose_commands_parse_and_configs_exist():
    commands = _compose_commands()
    assert len(commands) == 2
    for argv in commands:
        _parses(argv)
        config = argv[argv.index("--config") + 1]
        assert (REPO / "configs" / Path(config).name).is_file()
    text = (DOCKER / "compose.yaml").read_text()
    services = len(re.findall(r"^  \w+:$", text.split("volumes:")[0], re.M))
    hosts = len(re.findall(r"^\s+network_mode: host$", text, re.M))
    assert hosts == services == 2, "both containers use the host's network namespace, where CAN interfaces live"
    for step in ("modprobe vcan", "ip link add dev vcan0 type vcan", "NET_ADMIN"):
        assert step in text


def test_compose_player_and_daemon_meet_on_the_same_nmea_address():
    text = (DOCKER / "compose.yaml").read_text()
    served = re.search(r'"--nmea-tcp", "([\d.]+:\d+)"', text)
    read = re.search(r"SUMHE_GPS__PORT: socket://([\d.]+:\d+)", text)
    assert served and read and served.group(1) == read.group(1)


def test_systemd_unit_runs_a_real_command():
    text = (DOCKER / "sumhe.service").read_text()
    start = re.search(r"^ExecStart=(\S+) (.*)$", text, re.M)
    assert start and start.group(1).endswith("/sumhe")
    _parses(shlex.split(start.group(2)))
    assert "KillSignal=SIGTERM" in text and re.search(r"^User=(?!root)", text, re.M)


def test_lock_pins_every_runtime_dependency():
    lock = {
        re.split(r"[=<>~ ]", line, maxsplit=1)[0].lower().replace("_", "-"): line
        for line in (DOCKER / "requirements.lock").read_text().splitlines()
        if line and not line.startswith("#")
    }
    assert all("==" in line for line in lock.values()), "every line pinned with =="
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    for dep in deps:
        if "python_version" in dep:
            continue
        name = re.split(r"[=<>~;\[ ]", dep, maxsplit=1)[0].lower().replace("_", "-")
        assert name in lock, f"{name} is not pinned in docker/requirements.lock"


@pytest.mark.parametrize("name", ["Dockerfile", "compose.yaml", "sumhe.service"])
def test_docker_files_name_no_host_but_loopback(name):
    text = (DOCKER / name).read_text()
    for ip in re.findall(r"\b\d{1,3}(?:\.\d{1,3}){3}\b", text):
        assert ip.startswith("127."), f"{name} names {ip}"
