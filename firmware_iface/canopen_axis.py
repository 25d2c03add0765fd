"""CiA 402 driver (canopen on python-can) for positioning-unit axes, one node per axis.

The object dictionary is ``cia402_axis.eds`` beside this file; the node
behaviour is docs/canopen-axis.md. The driver takes a connected
``canopen.Network`` (transport apart from driver: a socketcan, PCAN, virtual
or udp_local bus are interchangeable, firmware_iface/can_bus.py) and uses SDOs only, so it needs no
PDO configuration:

* profile position moves (``0x6060`` = 1) with the new-set-point handshake;
* cyclic synchronous velocity (``0x6060`` = 9) for tracking (:meth:`CanopenAxis.run_at`);
* homing (``0x6060`` = 6), fault reset, and locking = *switched on* (brake applied).

The nodes boot into NMT *pre-operational*; :class:`CanopenUnit` starts each
one (NMT start) once it has answered an SDO. The host heartbeat (CAN id
``0x77F``) that the nodes' watchdog consumes is produced by
:class:`CanopenUnit` while it is open; opening clears a heartbeat fault left
from power-on or an earlier host. Every SDO read and write is logged
on the ``firmware_iface.canopen_axis`` logger at DEBUG.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Literal, TypeVar

import can
import canopen

from firmware_iface.unit import AxisGroup, axis_fault
from xmalign.errors import (
    DeviceError,
    DeviceTimeoutError,
    OutOfRangeError,
    TransportError,
)
from xmalign.roles import Clock, ClosesOnExit, WallClock

EDS_PATH = Path(__file__).with_name("cia402_axis.eds")

CONTROLWORD, STATUSWORD, MODE = 0x6040, 0x6041, 0x6060
TARGET_POSITION, POSITION_ACTUAL, TARGET_VELOCITY = 0x607A, 0x6064, 0x60FF
PROFILE_VELOCITY, ERROR_CODE, ENCODER_RESOLUTION = 0x6081, 0x603F, 0x608F

MODE_PROFILE_POSITION, MODE_HOMING, MODE_CSV = 1, 6, 9
SHUTDOWN, SWITCH_ON, ENABLE_OPERATION = 0x06, 0x07, 0x0F
NEW_SET_POINT, HALT, FAULT_RESET = 0x10, 0x100, 0x80
FAULT, TARGET_REACHED, SET_POINT_ACK = 0x08, 0x400, 0x1000
#: Statusword mask and value of *operation enabled* (the only state with the brake released).
STATE_MASK, SWITCHED_ON_STATE, OPERATION_ENABLED = 0x6F, 0x23, 0x27
#: *Fault reaction active* (mask, value): the node stops the axis and takes no command.
FAULT_REACTION_MASK, FAULT_REACTION_ACTIVE = 0x4F, 0x0F
#: The longest fault reaction of a node: a stop from full speed (0.33 s on the units).
FAULT_REACTION_TIMEOUT_S = 2.0
#: SDO abort code "value range of parameter exceeded": the node refuses a target.
ABORT_VALUE_RANGE = 0x06090030
#: ``0x603F`` holds ``FAULT_CODE_BASE + fault code`` of registers.yaml.
FAULT_CODE_BASE = 0xFF00
#: The host's heartbeat: node 127, state operational, every 100 ms (the nodes allow 500 ms).
HOST_HEARTBEAT_ID, HOST_HEARTBEAT_DATA, HOST_HEARTBEAT_PERIOD_S = 0x77F, b"\x05", 0.1
#: docs/conventions.md numbers the axes across both units: launch a1, a2; receiver a3, a4, a5.
FIRST_AXIS = {"launch": 1, "receiver": 3}
#: Number of axes of each unit.
AXIS_COUNT = {"launch": 2, "receiver": 3}


def unit_node_ids(kind: Literal["launch", "receiver"], node_ids: Sequence[int] | None) -> list[int]:
    """The CANopen node id of each axis of a unit: ``node_ids``, else its axis numbers."""
    first = FIRST_AXIS[kind]
    return list(node_ids) if node_ids is not None else list(range(first, first + AXIS_COUNT[kind]))


T = TypeVar("T")

log = logging.getLogger(__name__)


class CanopenAxis:
    """One CiA 402 node as a ``RotaryAxis`` (reported angles in rad).

    Parameters
    ----------
    node : canopen.RemoteNode
        The node, added to a connected network with the EDS.
    name : str
        Axis name of docs/conventions.md (``a1`` .. ``a5``).
    device_name : str
        Unit name for messages, e.g. ``"launch unit on can0"``.
    clock : Clock
        Time source of the waits.
    """

    def __init__(
        self,
        node: canopen.RemoteNode,
        name: str,
        device_name: str,
        clock: Clock | None = None,
        poll_s: float = 0.01,
    ) -> None:
        self.node = node
        self.name = name
        self.label = f"axis {name} (CANopen node {node.id}) of the {device_name}"
        self.clock = clock or WallClock()
        self.poll_s = poll_s
        self._mode: int | None = None
        #: Bit 8 (halt) of the controlword this driver wrote last: with it CiA 402 sets
        #: statusword bit 10 for "velocity 0", not for "target reached".
        self._halted = False
        self.counts_per_rev = self._read(ENCODER_RESOLUTION, 1)

    def start(self) -> None:
        """NMT start: the node goes to *operational* (it boots into *pre-operational*)."""
        log.debug("%s: NMT start", self.label)
        try:
            self.node.nmt.state = "OPERATIONAL"
        except (can.CanError, OSError) as error:
            raise TransportError(f"lost the CAN bus of {self.label}: {error}") from error

    # --- SDO access with errors that name the axis ----------------------------------------
    def _sdo(self, action: Callable[[], T], verb: str) -> T:
        try:
            return action()
        except canopen.SdoAbortedError as error:
            if error.code == ABORT_VALUE_RANGE:
                raise OutOfRangeError(f"{self.label} refused the value: out of range") from error
            raise DeviceError(f"{self.label} refused the {verb}: {error}") from error
        except canopen.SdoCommunicationError as error:
            raise DeviceTimeoutError(f"{self.label} did not answer ({verb}: {error})") from error
        except (can.CanError, OSError) as error:
            raise TransportError(f"lost the CAN bus of {self.label}: {error}") from error

    def _read(self, index: int, subindex: int = 0) -> int:
        def read() -> int:
            entry = self.node.sdo[index]
            return int((entry[subindex] if subindex else entry).raw)

        value = self._sdo(read, f"read of 0x{index:04X}")
        log.debug("%s: SDO read 0x%04X:%d -> %d (0x%X)", self.label, index, subindex, value, value)
        return value

    def _write(self, index: int, value: int) -> None:
        def write() -> None:
            self.node.sdo[index].raw = value

        log.debug("%s: SDO write 0x%04X:0 <- %d (0x%X)", self.label, index, value, value)
        self._sdo(write, f"write of 0x{index:04X}")
        if index == CONTROLWORD:
            self._halted = bool(value & HALT)

    def _set_mode(self, mode: int) -> None:
        if self._mode != mode:
            self._write(MODE, mode)
            self._mode = mode

    def counts_to_rad(self, counts: int) -> float:
        return 2.0 * math.pi * counts / self.counts_per_rev

    def rad_to_counts(self, angle_rad: float) -> int:
        return round(angle_rad * self.counts_per_rev / (2.0 * math.pi))

    # --- RotaryAxis ------------------------------------------------------------------------
    def position_rad(self) -> float:
        return self.counts_to_rad(self._read(POSITION_ACTUAL))

    def statusword(self) -> int:
        """The statusword; raises the node's fault as DriveFaultError or HeartbeatError."""
        status = self._read(STATUSWORD)
        if status & FAULT:
            raise axis_fault(self.label, self._read(ERROR_CODE) - FAULT_CODE_BASE)
        return status

    def fault_code(self) -> int:
        """The node's fault code (registers.yaml numbering), 0 when it has none."""
        error_code = self._read(ERROR_CODE)
        return error_code - FAULT_CODE_BASE if error_code else 0

    def move_to(self, angle_rad: float) -> None:
        """Profile-position move to a reported angle (returns once the node took the target)."""
        self._set_mode(MODE_PROFILE_POSITION)
        self._ensure_switched_on()
        try:
            self._write(TARGET_POSITION, self.rad_to_counts(angle_rad))
        except OutOfRangeError as error:
            raise OutOfRangeError(
                f"{self.label}: target {math.degrees(angle_rad):.4f} deg is out of its range"
            ) from error
        self._write(CONTROLWORD, ENABLE_OPERATION)
        self._write(CONTROLWORD, ENABLE_OPERATION | NEW_SET_POINT)
        # acknowledged, or already there (a short move can end before the first poll)
        self._wait_for(SET_POINT_ACK | TARGET_REACHED, 1.0, "take the new target")
        self._write(CONTROLWORD, ENABLE_OPERATION)

    def _ensure_switched_on(self) -> None:
        if self.statusword() & STATE_MASK not in (SWITCHED_ON_STATE, OPERATION_ENABLED):
            self.enable()

    def wait_in_position(self, timeout_s: float) -> None:
        """Wait for target reached (bit 10). After :meth:`stop` (halt) the bit only says the
        axis stands: a halted axis never reaches its target, and the wait runs to its end."""
        self._wait_for(TARGET_REACHED, timeout_s, "reach its target", unless_halted=True)

    def _wait_for(self, bit: int, timeout_s: float, what: str, unless_halted: bool = False) -> None:
        deadline = self.clock.now() + timeout_s
        while not self.statusword() & bit or (unless_halted and self._halted):
            if self.clock.now() >= deadline:
                raise DeviceTimeoutError(f"{self.label} did not {what} in {timeout_s:g} s")
            self.clock.sleep(self.poll_s)

    def stop(self) -> None:
        self._write(CONTROLWORD, ENABLE_OPERATION | HALT)

    def lock(self) -> None:
        """Stop and apply the brake (*disable operation* -> switched on)."""
        self._write(CONTROLWORD, SWITCH_ON)

    def is_locked(self) -> bool:
        return (self._read(STATUSWORD) & STATE_MASK) != OPERATION_ENABLED

    # --- beyond the role -------------------------------------------------------------------
    def enable(self) -> None:
        """Shutdown, then switch on: enabled with the brake applied."""
        self._write(CONTROLWORD, SHUTDOWN)
        self._write(CONTROLWORD, SWITCH_ON)

    def reset_fault(self) -> None:
        """Fault reset (once the fault reaction is over: the node ignores it before), enable."""
        deadline = self.clock.now() + FAULT_REACTION_TIMEOUT_S
        while self._read(STATUSWORD) & FAULT_REACTION_MASK == FAULT_REACTION_ACTIVE:
            if self.clock.now() >= deadline:
                raise DeviceTimeoutError(
                    f"{self.label} did not end its fault reaction in {FAULT_REACTION_TIMEOUT_S:g} s"
                )
            self.clock.sleep(self.poll_s)
        self._write(CONTROLWORD, 0)
        self._write(CONTROLWORD, FAULT_RESET)
        self.enable()

    def home(self, timeout_s: float) -> None:
        """Home on the current position (method of the EDS) and wait until attained."""
        self._set_mode(MODE_HOMING)
        self._ensure_switched_on()
        self._write(CONTROLWORD, ENABLE_OPERATION)
        self._write(CONTROLWORD, ENABLE_OPERATION | NEW_SET_POINT)
        self._wait_for(SET_POINT_ACK, timeout_s, "finish homing")
        self._write(CONTROLWORD, ENABLE_OPERATION)

    def run_at(self, velocity_rad_s: float) -> None:
        """Cyclic synchronous velocity: run at ``velocity_rad_s`` until :meth:`stop`/:meth:`lock`.

        For tracking, call it every control cycle with the new velocity command.
        """
        self._set_mode(MODE_CSV)
        self._ensure_switched_on()
        self._write(TARGET_VELOCITY, self.rad_to_counts(velocity_rad_s))
        self._write(CONTROLWORD, ENABLE_OPERATION)


class CanopenUnit(AxisGroup, ClosesOnExit):
    """A positioning unit made of CiA 402 axis nodes; implements ``PositioningUnit``.

    Parameters
    ----------
    network : canopen.Network
        Connected network.
    kind : {"launch", "receiver"}
    node_ids : sequence of int
        Node of each axis in order (default: the axis numbers, docs/canopen-axis.md).
    device_name : str
        Name for messages, e.g. ``"launch unit on can0"``.
    heartbeat : bool
        Produce the host heartbeat on the network while the unit is open.
    """

    def __init__(
        self,
        network: canopen.Network,
        kind: Literal["launch", "receiver"],
        node_ids: Sequence[int] | None = None,
        device_name: str | None = None,
        clock: Clock | None = None,
        heartbeat: bool = True,
    ) -> None:
        self.kind = kind
        self.device_name = device_name or f"{kind} unit"
        self.clock = clock or WallClock()
        first = FIRST_AXIS[kind]
        ids = unit_node_ids(kind, node_ids)
        self.network = network
        self._heartbeat_task = (
            network.send_periodic(HOST_HEARTBEAT_ID, HOST_HEARTBEAT_DATA, HOST_HEARTBEAT_PERIOD_S)
            if heartbeat
            else None
        )
        self._axes = tuple(
            CanopenAxis(
                network.add_node(node_id, str(EDS_PATH)), f"a{first + i}", self.device_name, clock
            )
            for i, node_id in enumerate(ids)
        )
        for axis in self._axes:
            axis.start()
        self.clear_heartbeat_faults()

    def close(self) -> None:
        """Stop producing the heartbeat (the nodes lock themselves 500 ms later)."""
        if self._heartbeat_task is not None:
            self._heartbeat_task.stop()
            self._heartbeat_task = None
