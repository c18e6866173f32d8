"""The autouse leak check of ``conftest.py`` detects what it claims to."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading

import can
from conftest import leaks, snapshot


def test_a_bus_a_socket_a_thread_and_a_child_left_open_are_found() -> None:
    before = snapshot()
    bus = can.Bus(interface="virtual", channel="leak-check")
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait, name="leak-check-thread")
    thread.start()
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        found = leaks(before, grace_s=0.2)
        assert any("virtual channel 'leak-check'" in f for f in found)
        assert any(f.startswith("socket fd") for f in found)
        assert any("leak-check-thread" in f for f in found)
        assert any(f"child process {child.pid}" in f for f in found)
    finally:
        bus.shutdown()
        sock.close()
        stop.set()
        thread.join()
        child.kill()
        child.wait()
    assert leaks(before, grace_s=0.2) == []
