"""Simulated unit axes as CiA 402 nodes (``canopen`` LocalNode over python-can).

One node per axis with the object dictionary of ``firmware_iface/cia402_axis.eds``;
the semantics are docs/canopen-axis.md. The CiA 402 state machine is mapped onto
the unit's firmware control bits (``SimUnit.control``), so Modbus and CANopen
share one behaviour: *Operation enabled* = enable | unlock, *Switched on* =
enable (locked), bit 4 starts a move (mode 1) or homing (mode 6), bit 8 halts.
"""

from __future__ import annotations

from collections.abc import Callable

import canopen
from canopen.sdo import SdoAbortedError

from firmware_iface.register_map import REGISTER_MAP_PATH, Control, Status
from sim.units import COUNTS_PER_REV, SimAxis, SimUnit, counts_to_rad, rad_to_counts
from xmalign.errors import OutOfRangeError

EDS_PATH = REGISTER_MAP_PATH.with_name("cia402_axis.eds")
HOST_NODE_ID = 0x7F
ABORT_VALUE_RANGE = 0x06090030
MODE_PROFILE_POSITION = 1
MODE_HOMING = 6
MODE_CYCLIC_VELOCITY = 9
MODES = (MODE_PROFILE_POSITION, MODE_HOMING, MODE_CYCLIC_VELOCITY)

# Statusword (CiA 402)
_READY, _SWITCHED_ON, _OPERATION_ENABLED, _FAULT = 0x01, 0x02, 0x04, 0x08
_VOLTAGE_ENABLED, _QUICK_STOP, _SWITCH_ON_DISABLED = 0x10, 0x20, 0x40
_REMOTE, _TARGET_REACHED, _INTERNAL_LIMIT, _MODE_BIT12 = 0x200, 0x400, 0x800, 0x1000
# Controlword
_NEW_SETPOINT, _FAULT_RESET, _HALT = 0x10, 0x80, 0x100

DISABLED, READY, SWITCHED_ON, OPERATION_ENABLED = "disabled", "ready", "switched_on", "enabled"


class Cia402Axis:
    """The CiA 402 view of axis ``n`` (1-based) of a :class:`SimUnit`."""

    def __init__(self, unit: SimUnit, n: int) -> None:
        self.unit = unit
        self.n = n
        self.state = DISABLED
        self.mode = MODE_PROFILE_POSITION
        self.controlword = 0
        self.target_velocity_counts_s = 0

    @property
    def axis(self) -> SimAxis:
        return self.unit.axes[self.n - 1]

    def write_controlword(self, word: int) -> None:
        if word & _FAULT_RESET and not self.controlword & _FAULT_RESET:
            self.state = DISABLED
        self.controlword = word
        self.state = _next_state(self.state, word)
        base = {
            DISABLED: Control(0),
            READY: Control(0),
            SWITCHED_ON: Control.ENABLE,
            OPERATION_ENABLED: Control.ENABLE | Control.UNLOCK,
        }[self.state]
        if word & _FAULT_RESET:
            base |= Control.FAULT_RESET
        if word & _HALT:
            base |= Control.STOP
        if word & _NEW_SETPOINT and self.mode == MODE_PROFILE_POSITION:
            base |= Control.START
        if word & _NEW_SETPOINT and self.mode == MODE_HOMING:
            base |= Control.HOME
        self.unit.control(self.n, base)
        self._run_velocity_mode()

    def _run_velocity_mode(self) -> None:
        if self.mode == MODE_CYCLIC_VELOCITY and self.state == OPERATION_ENABLED:
            self.axis.run_at(counts_to_rad(self.target_velocity_counts_s))

    def statusword(self) -> int:
        axis = self.axis
        status = axis.status()
        if Status.FAULT in status:
            word = _FAULT
        else:
            word = {
                DISABLED: _SWITCH_ON_DISABLED,
                READY: _READY | _QUICK_STOP | _VOLTAGE_ENABLED,
                SWITCHED_ON: _READY | _SWITCHED_ON | _QUICK_STOP | _VOLTAGE_ENABLED,
                OPERATION_ENABLED: _READY
                | _SWITCHED_ON
                | _OPERATION_ENABLED
                | _QUICK_STOP
                | _VOLTAGE_ENABLED,
            }[self.state]
        word |= _REMOTE
        if not axis.is_moving() and (Status.IN_POSITION in status or self.controlword & _HALT):
            word |= _TARGET_REACHED
        if Status.AT_LIMIT in status:
            word |= _INTERNAL_LIMIT
        if (self.mode == MODE_HOMING and Status.HOMED in status) or (
            self.mode == MODE_PROFILE_POSITION and axis.is_moving()
        ):
            word |= _MODE_BIT12
        return word

    # SDO access -----------------------------------------------------------------
    def read(self, index: int, subindex: int) -> int | None:
        """Value of an object, or None to fall back to the EDS default."""
        with self.unit.lock:
            self.unit.check_watchdog()
            axis = self.axis
            values = {
                (0x6040, 0): self.controlword,
                (0x6041, 0): self.statusword(),
                (0x6060, 0): self.mode,
                (0x6061, 0): self.mode,
                (0x6064, 0): rad_to_counts(axis.reported_rad()),
                (0x606C, 0): rad_to_counts(axis.profile.state(self.unit.clock.now())[1]),
                (0x607A, 0): rad_to_counts(axis.target_rad),
                (0x6081, 0): rad_to_counts(axis.velocity_limit_rad_s),
                (0x6083, 0): rad_to_counts(axis.limits.acceleration_rad_s2),
                (0x603F, 0): 0xFF00 + axis.fault_code if axis.fault_code else 0,
                (0x607D, 1): rad_to_counts(axis.limits.min_rad),
                (0x607D, 2): rad_to_counts(axis.limits.max_rad),
                (0x608F, 1): COUNTS_PER_REV,
                (0x60FF, 0): self.target_velocity_counts_s,
            }
            return values.get((index, subindex))

    def write(self, index: int, subindex: int, value: int) -> None:
        """Apply an object write; SdoAbortedError (value range) for a refused value."""
        with self.unit.lock:
            self.unit.check_watchdog()
            try:
                if index == 0x6040:
                    self.write_controlword(value)
                elif index == 0x607A:
                    self.axis.set_target(counts_to_rad(value))
                elif index == 0x6081:
                    self.axis.set_velocity_limit(counts_to_rad(value))
                elif index == 0x6060:
                    if value not in MODES:
                        raise OutOfRangeError(f"mode of operation {value} not supported")
                    self.mode = value
                elif index == 0x60FF:
                    self.target_velocity_counts_s = value
                    self._run_velocity_mode()
            except OutOfRangeError as error:
                raise SdoAbortedError(ABORT_VALUE_RANGE) from error


def _next_state(state: str, word: int) -> str:
    """CiA 402 device-control commands (controlword bits 0-3 and 7)."""
    if word & 0x02 == 0:  # disable voltage
        return DISABLED
    if word & 0x04 == 0:  # quick stop
        return DISABLED
    if word & 0x8F == 0x06:  # shutdown
        return READY
    if word & 0x8F == 0x07:  # switch on / disable operation
        return SWITCHED_ON if state in (READY, SWITCHED_ON, OPERATION_ENABLED) else state
    if word & 0x8F == 0x0F:  # enable operation
        return OPERATION_ENABLED if state in (SWITCHED_ON, OPERATION_ENABLED) else state
    return state


class CanopenUnitServer:
    """Every axis of the given units as CiA 402 nodes on one CAN bus.

    Node ids are the CONVENTIONS.md axis numbers (launch a1, a2 = 1, 2;
    receiver a3, a4, a5 = 3, 4, 5) plus ``node_base``. The host's heartbeat
    (node 127, CAN id 0x77F) feeds every unit's watchdog.

    Parameters
    ----------
    units : list of SimUnit
    channel : str
        python-can channel (a name for ``virtual``, a multicast group for ``udp_multicast``).
    interface : str
        ``virtual`` (in one process) or ``udp_multicast`` (across processes).
    """

    def __init__(
        self, units: list[SimUnit], channel: str, interface: str = "virtual", node_base: int = 0
    ) -> None:
        self.units = units
        self.channel = channel
        self.interface = interface
        self.network = canopen.Network()
        self.axes: dict[int, Cia402Axis] = {}
        for unit in units:
            first = 1 if unit.kind == "launch" else 3
            for n in range(1, len(unit.axes) + 1):
                self.axes[node_base + first + n - 1] = Cia402Axis(unit, n)
        self._heartbeats = 0

    @property
    def node_ids(self) -> list[int]:
        return sorted(self.axes)

    def start(self) -> None:
        self.network.connect(interface=self.interface, channel=self.channel)
        for node_id, axis in self.axes.items():
            node = canopen.LocalNode(node_id, str(EDS_PATH))
            node.add_read_callback(_reader(axis))
            node.add_write_callback(_writer(axis))
            self.network.add_node(node)
            node.nmt.state = "OPERATIONAL"
        self.network.subscribe(0x700 + HOST_NODE_ID, self._on_host_heartbeat)

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._heartbeats = (self._heartbeats + 1) & 0xFFFF
        for unit in self.units:
            unit.heartbeat(self._heartbeats)

    def stop(self) -> None:
        self.network.disconnect()


def _reader(axis: Cia402Axis) -> Callable[..., int | None]:
    def read(index: int, subindex: int, od: canopen.objectdictionary.ODVariable) -> int | None:
        return axis.read(index, subindex)

    return read


def _writer(axis: Cia402Axis) -> Callable[..., None]:
    def write(
        index: int, subindex: int, od: canopen.objectdictionary.ODVariable, data: bytes
    ) -> None:
        axis.write(index, subindex, int(od.decode_raw(data)))

    return write
