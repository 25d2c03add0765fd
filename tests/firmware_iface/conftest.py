"""Simulated units served on loopback for the driver tests (each test starts and stops its own)."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from sim.clock import SimClock
from sim.servers.modbus import ModbusUnitServer
from sim.units import SimUnit


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on."""
    return _free_port()


@pytest.fixture
def served_launch() -> Iterator[tuple[SimUnit, ModbusUnitServer]]:
    """A real-time simulated launch unit behind a Modbus TCP server on 127.0.0.1."""
    unit = SimUnit("launch", SimClock(real_time=True), seed=1)
    server = ModbusUnitServer(unit, "127.0.0.1", _free_port())
    server.start()
    yield unit, server
    server.stop()
