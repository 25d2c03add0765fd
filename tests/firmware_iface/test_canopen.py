"""The CiA 402 driver against simulated nodes on a python-can virtual bus (real canopen stack)."""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Iterator

import canopen
import numpy as np
import pytest

from firmware_iface.canopen_axis import CanopenUnit
from sim.clock import SimClock
from sim.servers.canopen_node import CanopenUnitServer
from sim.units import SimUnit
from xmalign.errors import DriveFaultError, HeartbeatError, OutOfRangeError
from xmalign.safety import units_locked_on_exit


@pytest.fixture
def served() -> Iterator[tuple[CanopenUnitServer, canopen.Network]]:
    """A real-time simulated receiver unit as nodes 3, 4, 5, and a connected host network."""
    channel = f"xmalign-{uuid.uuid4().hex}"
    sim = SimUnit("receiver", SimClock(real_time=True), seed=5)
    server = CanopenUnitServer([sim], channel, "virtual")
    server.start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    yield server, network
    network.disconnect()
    server.stop()


@pytest.fixture
def bus(served) -> tuple[SimUnit, canopen.Network]:  # noqa: ANN001
    server, network = served
    return server.units[0], network


def test_opening_starts_the_nodes(served) -> None:  # noqa: ANN001
    server, network = served
    assert {node.nmt.state for node in server.nodes.values()} == {"PRE-OPERATIONAL"}
    unit = CanopenUnit(network, "receiver", device_name="receiver unit")
    try:
        assert {node.nmt.state for node in server.nodes.values()} == {"OPERATIONAL"}
    finally:
        unit.close()


def test_profile_position_moves_and_locks(bus) -> None:  # noqa: ANN001
    sim, network = bus
    unit = CanopenUnit(network, "receiver", device_name="receiver unit on test bus")
    try:
        assert [axis.name for axis in unit.axes] == ["a3", "a4", "a5"]
        with units_locked_on_exit(unit):
            unit.move_to([0.02, -0.01, 0.005], timeout_s=5.0)
            np.testing.assert_allclose(unit.angles_rad(), [0.02, -0.01, 0.005], atol=2e-6)
            unit.axes[0].move_to(0.02)  # a move of zero length also completes
            unit.axes[0].wait_in_position(1.0)
        assert all(axis.is_locked() for axis in unit.axes)
        assert all(axis.is_locked() for axis in sim.axes)
    finally:
        unit.close()


def test_out_of_range_target_is_refused(bus) -> None:  # noqa: ANN001
    _, network = bus
    unit = CanopenUnit(network, "receiver", device_name="receiver unit")
    try:
        with pytest.raises(OutOfRangeError, match=r"axis a4 \(CANopen node 4\).*120.0000 deg"):
            unit.axes[1].move_to(math.radians(120.0))
    finally:
        unit.close()


def test_drive_fault_is_reported(bus) -> None:  # noqa: ANN001
    sim, network = bus
    unit = CanopenUnit(network, "receiver", device_name="receiver unit")
    try:
        unit.axes[0].move_to(1.0)
        sim.axes[0].fault(2)
        with pytest.raises(DriveFaultError, match="axis a3 .* reports fault 2: drive fault"):
            unit.axes[0].wait_in_position(5.0)
        unit.axes[0].reset_fault()
        unit.axes[0].move_to(0.0)
        unit.axes[0].wait_in_position(5.0)
    finally:
        unit.close()


def test_velocity_mode_runs_until_stopped(bus) -> None:  # noqa: ANN001
    sim, network = bus
    unit = CanopenUnit(network, "receiver", device_name="receiver unit")
    try:
        axis = unit.axes[2]
        axis.run_at(0.05)
        time.sleep(0.2)
        assert sim.axes[2].is_moving()
        axis.lock()
        time.sleep(0.1)
        assert axis.is_locked() and not sim.axes[2].is_moving()
        assert axis.position_rad() > 0.003
    finally:
        unit.close()


def test_stalled_host_heartbeat_locks_and_is_reported(bus) -> None:  # noqa: ANN001
    sim, network = bus
    unit = CanopenUnit(network, "receiver", device_name="receiver unit")
    unit.axes[0].move_to(1.5)
    unit.close()  # the host heartbeat stops mid-move
    time.sleep(1.0)
    with pytest.raises(HeartbeatError, match="axis a3 .* stopped: heartbeat watchdog expired"):
        unit.axes[0].wait_in_position(5.0)
    assert all(axis.is_locked() for axis in sim.axes)
