"""The docker and systemd files stay consistent with the CLI, the configs and the repository.

The Docker engine does not run on this machine (nor in CI), so nothing here builds an image or starts a container:
these tests read the files (compose with PyYAML) and check what a build or a start would rely on.
"""

import re
import shlex
import sys
from pathlib import Path

import pytest
import yaml

from sumhe.cli import build_parser
from sumhe.config import load_config, parse_host_port

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


def _compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def _dockerfile() -> list[str]:
    """Instructions with continuation lines joined."""
    return [line for line in (DOCKER / "Dockerfile").read_text().replace("\\\n", " ").splitlines() if line.strip()]


def test_dockerfile_copies_only_what_exists_and_uses_every_copy():
    """Every COPY's destination is used by a later instruction, or it goes into the directory pip installs and
    carries only what building the package reads (pyproject.toml, the readme it names, the package)."""
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    build_inputs = {"pyproject.toml", pyproject["project"]["readme"], "sumhe"}
    lines = _dockerfile()
    installed = {m for line in lines for m in re.findall(r"pip install --no-deps (\S+)", line)}
    assert installed, "the image installs the package"
    for k, line in enumerate(lines):
        if not line.startswith("COPY "):
            continue
        *sources, dest = line.split()[1:]
        for src in sources:
            assert (REPO / src).exists(), f"Dockerfile copies missing {src}"
        later = " ".join(lines[k + 1 :])
        if re.search(rf"{re.escape(dest.rstrip('/'))}(/|\s|\"|$)", later):
            continue  # used by name
        into_build = any(dest.rstrip("/") == d or dest.startswith(d + "/") for d in installed)
        assert into_build and set(sources) <= build_inputs, f"unused: {line}"


def test_dockerfile_runs_a_real_command_as_a_user_in_a_directory_it_owns():
    text = "\n".join(_dockerfile())
    user = re.search(r"^USER (\w+)$", text, re.M)
    assert user and user.group(1) != "root", "the image runs as a non-root user"
    useradd = re.search(rf"useradd (.*) {user.group(1)}\b", text)
    assert useradd and "--create-home" in useradd.group(1)
    home = re.search(r"--home-dir (\S+)", useradd.group(1)).group(1)
    workdirs = re.findall(r"^WORKDIR (\S+)$", text, re.M)
    assert workdirs[-1] == home, "the working directory is the user's own home (writable)"
    entry = re.search(r'^ENTRYPOINT \["(\w+)"\]', text, re.M)
    cmd = re.search(r"^CMD (\[.*\])", text, re.M)
    assert entry and entry.group(1) == "sumhe" and cmd
    argv = [a.strip().strip('"') for a in cmd.group(1).strip("[]").split(",")]
    _parses(argv)
    config = argv[argv.index("--config") + 1]
    assert config.startswith("/etc/sumhe/") and (REPO / "configs" / Path(config).name).is_file()


def test_compose_never_pulls_the_image_it_builds():
    services = _compose()["services"]
    built = {s["image"] for s in services.values() if "build" in s}
    assert built == {"sumhe:local"}
    for name, s in services.items():
        if s.get("image") in built and "build" not in s:
            assert s.get("pull_policy") == "never", f"{name} would try to pull {s['image']}"


def test_compose_commands_parse_and_every_container_is_on_the_host_network():
    services = _compose()["services"]
    assert set(services) == {"sumhe", "player", "listener"}
    for name, s in services.items():
        _parses(s["command"])
        assert s["network_mode"] == "host", f"{name}: CAN interfaces live in the host's network namespace"
        if "--config" in s["command"]:
            assert (REPO / "configs" / Path(s["command"][s["command"].index("--config") + 1]).name).is_file()
    text = (DOCKER / "compose.yaml").read_text()
    for step in ("modprobe vcan", "ip link add dev vcan0 type vcan", "ip link set up vcan0", "NET_ADMIN"):
        assert step in text


def _daemon_config(service: dict):
    argv = service["command"]
    env = {k: str(v) for k, v in service.get("environment", {}).items()}
    return load_config(REPO / "configs" / Path(argv[argv.index("--config") + 1]).name, env=env)


def test_compose_listener_listens_where_the_daemon_sends_json():
    services = _compose()["services"]
    config = _daemon_config(services["sumhe"])
    listen = services["listener"]["command"]
    assert listen[0] == "listen"
    assert set(listen[1:]) and set(listen[1:]) <= set(config.output.json)


def test_compose_player_and_daemon_meet_on_the_same_nmea_address():
    services = _compose()["services"]
    player = services["player"]["command"]
    served = player[player.index("--nmea-tcp") + 1]
    config = _daemon_config(services["sumhe"])
    assert config.gps.port == f"socket://{served}"
    assert parse_host_port(served) not in [parse_host_port(d) for d in config.output.json]


def test_systemd_unit_installs_from_the_checkout_creates_its_user_and_brings_can_up_from_the_config():
    text = (DOCKER / "sumhe.service").read_text()
    start = re.search(r"^ExecStart=(\S+) (.*)$", text, re.M)
    assert start and start.group(1).endswith("/sumhe")
    argv = shlex.split(start.group(2))
    _parses(argv)
    config = argv[argv.index("--config") + 1]
    pre = re.search(r"^ExecStartPre=\+(\S+) (.*)$", text, re.M)
    assert pre and pre.group(1) == start.group(1), "CAN bring-up by the same sumhe, as root ('+')"
    pre_argv = shlex.split(pre.group(2))
    _parses(pre_argv)
    assert pre_argv[0] == "can-up" and pre_argv[pre_argv.index("--config") + 1] == config, "from the same config"
    user = re.search(r"^User=(\w+)$", text, re.M).group(1)
    assert user != "root" and re.search(rf"^#\s+useradd .*\b{user}$", text, re.M), "the install steps create it"
    install = re.findall(r"^#\s+(.*pip install .*)$", text, re.M)
    assert install and all(re.search(r"pip install (/|\.)", line) for line in install), "from a checkout or wheel"
    venv = re.search(r"^#\s+python3 -m venv (\S+)$", text, re.M).group(1)
    assert start.group(1) == f"{venv}/bin/sumhe"
    copied = re.search(rf"^#\s+install .* (configs/\S+) {re.escape(config)}", text, re.M)
    assert copied and (REPO / copied.group(1)).is_file(), "the installed config is one of configs/"
    workdir = re.search(r"^WorkingDirectory=(\S+)$", text, re.M).group(1)
    assert workdir in re.search(r"^ReadWritePaths=(.*)$", text, re.M).group(1)
    assert "KillSignal=SIGTERM" in text and "Restart=on-failure" in text


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
