"""``sumhe can-up --config FILE [--dry-run]``: bring up the SocketCAN interface the config names (needs root).

For ``can.interface = "socketcan"``: a ``vcan*`` channel is created if missing (``modprobe vcan``, ``ip link add dev
CH type vcan``) and set up; any other channel (a real adapter) must exist, and is (re)started at ``can.bitrate``
with bus-off auto-recovery (``restart-ms``). Other interfaces (pcan, kvaser, virtual, ...) need nothing here. The
systemd unit runs this before the daemon, so the bus settings live in one place, the config. ``--dry-run`` prints
the commands without running them.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
from pathlib import Path

from sumhe.config import load_config
from sumhe.errors import SourceError
from sumhe.io.can_source import link_commands

SYS_NET = Path("/sys/class/net")


def link_state(channel: str, sys_net: Path = SYS_NET) -> tuple[bool, bool]:
    """(the interface exists, it is up) from sysfs."""
    flags = sys_net / channel / "flags"
    if not flags.is_file():
        return False, False
    return True, bool(int(flags.read_text(), 16) & 0x1)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", required=True, help="TOML config; its [can] is brought up")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    s = config.can
    if s.interface != "socketcan":
        print(f"can.interface {s.interface!r}: nothing to bring up (SocketCAN only)", file=sys.stderr)
        return 0
    exists, up = link_state(s.channel)
    real = not s.channel.startswith("vcan")
    if real and s.bitrate is None:
        raise config.error("can.bitrate", f"needed to bring up {s.channel} (e.g. bitrate = 500000)")
    if real and not exists:
        raise SourceError(f"{s.channel}: no such interface: plug in the adapter and load its driver (gs_usb, ...)")
    commands = link_commands(s.channel, s.bitrate or 0, exists, up)
    if not commands:
        print(f"{s.channel} is up: nothing to do", file=sys.stderr)
    for cmd in commands:
        print(shlex.join(cmd), flush=True)
        if args.dry_run:
            continue
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise SourceError(f"{shlex.join(cmd)} failed: {done.stderr.strip() or done.returncode}")
    return 0
