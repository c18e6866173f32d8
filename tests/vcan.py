"""Test helpers: whether this kernel has SocketCAN and an up vcan interface (the CI virtual machine has both;
``.ci/vcan`` sets ``SUMHE_TEST_VCAN=required``, which makes the SocketCAN tests fail instead of skipping)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest


def kernel_has_socketcan() -> bool:
    """A raw CAN socket can be created (``socket.AF_CAN`` exists in Python whether or not the kernel has it)."""
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (AttributeError, OSError):
        return False
    return True


def vcan_up(name: str = "vcan0") -> bool:
    flags = Path(f"/sys/class/net/{name}/flags")
    return kernel_has_socketcan() and flags.is_file() and int(flags.read_text(), 16) & 0x1 == 1


def needs_vcan0() -> pytest.MarkDecorator:
    """Skip (with the reason) where vcan0 is not up; where ``SUMHE_TEST_VCAN=required``, run regardless: the test
    then fails if vcan0 is missing, so the CI virtual machine cannot pass by skipping."""
    required = os.environ.get("SUMHE_TEST_VCAN") == "required"
    return pytest.mark.skipif(
        not required and not vcan_up(),
        reason="needs SocketCAN (AF_CAN) and an up vcan0; this kernel has none (.ci/vcan runs it in a VM)",
    )
