"""Fixtures shared by test modules (used by name: none is autouse)."""

import can.interfaces.virtual
import pytest


@pytest.fixture
def no_bus_left_open():
    """Fail a test that leaves a virtual bus open (its source was not closed)."""
    yield
    left = list(can.interfaces.virtual.channels)
    can.interfaces.virtual.channels.clear()
    assert not left, f"virtual buses left open on channels {left}"
