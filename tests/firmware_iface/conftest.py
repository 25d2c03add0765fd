"""Simulated units served on loopback for the driver tests (each test starts and stops its own)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from cli_helpers import free_port as free_tcp_port

from sim.clock import SimClock
from sim.servers.modbus import ModbusUnitServer
from sim.units import SimUnit


@pytest.fixture
def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on."""
    return free_tcp_port()


@pytest.fixture
def served_launch() -> Iterator[tuple[SimUnit, ModbusUnitServer]]:
    """A real-time simulated launch unit behind a Modbus TCP server on 127.0.0.1."""
    unit = SimUnit("launch", SimClock(real_time=True), seed=1)
    server = ModbusUnitServer(unit, "127.0.0.1", free_tcp_port())
    server.start()
    yield unit, server
    server.stop()
