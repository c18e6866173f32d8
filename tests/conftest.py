"""Fixtures every test gets: a leak check (after python-can's ``check_unclosed_virtual_channel``).

A test that leaves a python-can bus, a socket, a thread or a child process open fails: each is a resource the
service would leak once per reconnect, replay or restart. What was open before the test is not counted (module
fixtures may hold their own); threads and child processes get a short grace period to finish."""

from __future__ import annotations

import gc
import logging
import os
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from can.interfaces import virtual

GRACE_S = 5.0
"""How long threads and child processes a test started may take to end after it."""


@dataclass(frozen=True)
class Resources:
    """What the process holds open: virtual CAN channels, socket fds, threads, child processes."""

    can_channels: frozenset[str]
    sockets: frozenset[str]
    threads: frozenset[threading.Thread]
    children: frozenset[int]


def _sockets() -> frozenset[str]:
    """Open socket file descriptors of this process (Linux ``/proc``; empty elsewhere)."""
    out = set()
    fds = Path("/proc/self/fd")
    for fd in fds.iterdir() if fds.is_dir() else ():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:"):
            out.add(f"fd {fd.name} {target}")
    return frozenset(out)


def _children() -> frozenset[int]:
    """Live child processes of this process (Linux ``/proc``; empty elsewhere)."""
    out: set[int] = set()
    for task in Path("/proc/self/task").glob("*/children"):
        try:
            out |= {int(p) for p in task.read_text().split()}
        except OSError:
            continue
    return frozenset(out)


def snapshot() -> Resources:
    with virtual.channels_lock:
        channels = frozenset(virtual.channels)
    return Resources(channels, _sockets(), frozenset(t for t in threading.enumerate() if t.is_alive()), _children())


def leaks(before: Resources, grace_s: float = GRACE_S) -> list[str]:
    """What is open now and was not ``before``, after up to ``grace_s`` for threads and children to end."""
    deadline = time.monotonic() + grace_s
    while True:
        gc.collect()
        now = snapshot()
        threads = now.threads - before.threads
        children = now.children - before.children
        if not (threads or children) or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    out = [f"python-can virtual channel {c!r}" for c in sorted(now.can_channels - before.can_channels)]
    out += [f"socket {s}" for s in sorted(now.sockets - before.sockets)]
    out += [f"thread {t.name!r}" for t in threads]
    out += [f"child process {pid}" for pid in sorted(children)]
    return out


@pytest.fixture(autouse=True)
def nothing_left_open() -> Iterator[None]:
    """Fail a test that leaves a bus, socket, thread or child process open."""
    before = snapshot()
    yield
    left = leaks(before)
    assert not left, "left open by the test: " + ", ".join(left)


@pytest.fixture(autouse=True)
def root_logging_put_back() -> Iterator[None]:
    """``sumhe.cli.main`` configures the root logger (``logging.basicConfig(force=True)``: its handler writes to the
    test's captured stderr, pytest's own handlers removed): the root logger is put back as it was after each test,
    so that later tests do not log into a closed capture stream ("I/O operation on closed file") and caplog sees
    their records."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    for handler in root.handlers:
        if handler not in handlers:
            handler.close()
    root.handlers[:] = handlers
    root.setLevel(level)
