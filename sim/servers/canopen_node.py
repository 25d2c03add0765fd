"""Simulated unit axes as CiA 402 nodes (``canopen`` LocalNode over python-can).

One node per axis with the object dictionary of ``firmware_iface/cia402_axis.eds``;
the behaviour is docs/canopen-axis.md. :class:`Cia402Axis` is the CiA 402
state machine of a drive: it takes only the transitions of the CiA 402 state
diagram and ignores every other command, as a drive does. Its states drive the
unit's firmware control bits (``SimUnit.control``), so Modbus and CANopen
share one behaviour: *Operation enabled* = enable | unlock, *Switched on* =
enable (locked), everything else disabled and locked. RPDO 1 (controlword +
target position) is applied as it arrives; TPDO 1 (statusword + position
actual value) is sent on a change of the statusword and every 50 ms. Every
SDO and PDO is logged on ``sim.servers.canopen_node`` at DEBUG.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections.abc import Callable
from typing import Any

import canopen
from canopen import SdoAbortedError

from firmware_iface.register_map import REGISTER_MAP_PATH, Control, Status
from sim.units import COUNTS_PER_REV, SimAxis, SimUnit, counts_to_rad, rad_to_counts
from xmalign.errors import OutOfRangeError

log = logging.getLogger(__name__)

EDS_PATH = REGISTER_MAP_PATH.with_name("cia402_axis.eds")
HOST_NODE_ID = 0x7F
ABORT_VALUE_RANGE = 0x06090030
MODE_PROFILE_POSITION, MODE_HOMING, MODE_CYCLIC_VELOCITY = 1, 6, 9
MODES = (MODE_PROFILE_POSITION, MODE_HOMING, MODE_CYCLIC_VELOCITY)
FAULT_CODE_BASE = 0xFF00
#: TPDO 1 is sent at least this often (0x1800 sub5), and on every statusword change.
TPDO_EVENT_TIMER_S = 0.05
_TPDO_POLL_S = 0.01
#: How long the bus reader waits for a frame before it looks whether to stop (canopen: 1 s).
_NOTIFIER_CYCLE_S = 0.1
_RPDO1 = struct.Struct("<Hi")  # controlword, target position
_TPDO1 = struct.Struct("<Hi")  # statusword, position actual value

# Controlword bits
_NEW_SETPOINT, _FAULT_RESET, _HALT = 0x10, 0x80, 0x100

# CiA 402 states and their statusword bits (voltage enabled where the drive has power on)
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT = "FAULT"
STATE_BITS = {
    SWITCH_ON_DISABLED: 0x0040,
    READY_TO_SWITCH_ON: 0x0031,
    SWITCHED_ON: 0x0033,
    OPERATION_ENABLED: 0x0037,
    QUICK_STOP_ACTIVE: 0x0017,
    FAULT: 0x0018,
}
_REMOTE, _TARGET_REACHED, _INTERNAL_LIMIT, _MODE_BIT12 = 0x200, 0x400, 0x800, 0x1000

# The device-control commands of CiA 402 (mask, value) and the transitions each one
# takes: {from state: to state}. A command not valid in the present state is ignored.
_COMMANDS: tuple[tuple[int, int, dict[str, str]], ...] = (
    (  # shutdown: transitions 2, 6, 8
        0x87,
        0x06,
        {
            SWITCH_ON_DISABLED: READY_TO_SWITCH_ON,
            SWITCHED_ON: READY_TO_SWITCH_ON,
            OPERATION_ENABLED: READY_TO_SWITCH_ON,
        },
    ),
    (0x8F, 0x07, {READY_TO_SWITCH_ON: SWITCHED_ON, OPERATION_ENABLED: SWITCHED_ON}),  # on: 3, 5
    (0x8F, 0x0F, {SWITCHED_ON: OPERATION_ENABLED}),  # enable operation: transition 4
    (  # disable voltage: transitions 7, 9, 10, 12
        0x82,
        0x00,
        {
            READY_TO_SWITCH_ON: SWITCH_ON_DISABLED,
            OPERATION_ENABLED: SWITCH_ON_DISABLED,
            SWITCHED_ON: SWITCH_ON_DISABLED,
            QUICK_STOP_ACTIVE: SWITCH_ON_DISABLED,
        },
    ),
    (  # quick stop: transitions 7, 10, 11
        0x86,
        0x02,
        {
            READY_TO_SWITCH_ON: SWITCH_ON_DISABLED,
            SWITCHED_ON: SWITCH_ON_DISABLED,
            OPERATION_ENABLED: QUICK_STOP_ACTIVE,
        },
    ),
)


def next_state(state: str, previous_word: int, word: int) -> str:
    """The CiA 402 state after controlword ``word`` (``previous_word`` for the fault-reset edge)."""
    if state == FAULT:  # transition 15 on the rising edge of bit 7, nothing else
        rising = word & _FAULT_RESET and not previous_word & _FAULT_RESET
        return SWITCH_ON_DISABLED if rising else FAULT
    for mask, value, transitions in _COMMANDS:
        if word & mask == value:
            return transitions.get(state, state)
    return state


class Cia402Axis:
    """The CiA 402 view of axis ``n`` (1-based) of a :class:`SimUnit`."""

    def __init__(self, unit: SimUnit, n: int) -> None:
        self.unit = unit
        self.n = n
        self.state = SWITCH_ON_DISABLED
        self.mode = MODE_PROFILE_POSITION
        self.controlword = 0
        self.target_velocity_counts_s = 0
        self.target_refused = False

    @property
    def axis(self) -> SimAxis:
        return self.unit.axes[self.n - 1]

    def _follow_faults(self) -> None:
        """A fault of the unit's axis (drive, watchdog) puts the node in Fault."""
        self.unit.check_watchdog()
        if self.axis.fault_code and self.state != FAULT:
            self.state = FAULT
        if self.state == QUICK_STOP_ACTIVE and not self.axis.is_moving():
            self.state = SWITCH_ON_DISABLED  # quick stop option code 2: then switch on disabled

    def write_controlword(self, word: int) -> None:
        self._follow_faults()
        previous_state, previous_word = self.state, self.controlword
        self.controlword = word
        state = next_state(self.state, previous_word, word)
        if state in (SWITCHED_ON, OPERATION_ENABLED) and not self.unit.heartbeat_seen:
            state = self.state  # no host heartbeat yet: the drive stays disabled
        self.state = state
        if previous_state != state:
            log.debug("node axis %d: %s -> %s", self.n, previous_state, state)
        if state == FAULT:
            self.unit.control(self.n, Control(0))
            return
        if previous_state == FAULT:
            self.unit.control(self.n, Control.FAULT_RESET)
            if self.axis.fault_code:  # the cause persists: stay in Fault
                self.state = FAULT
                return
        if state == QUICK_STOP_ACTIVE:
            if previous_state != QUICK_STOP_ACTIVE:
                self.unit.quick_stop(self.n)
            return
        self.unit.control(self.n, self._unit_control(state, previous_word, word))
        self._run_velocity_mode()

    def _unit_control(self, state: str, previous_word: int, word: int) -> Control:
        bits = {SWITCHED_ON: Control.ENABLE, OPERATION_ENABLED: Control.ENABLE | Control.UNLOCK}
        control = bits.get(state, Control(0))
        if word & _HALT:
            control |= Control.STOP
        # new set-point: the unit acts on the rising edge of START/HOME, so pass the bit through
        if word & _NEW_SETPOINT and self.mode == MODE_PROFILE_POSITION and not self.target_refused:
            control |= Control.START
        if word & _NEW_SETPOINT and self.mode == MODE_HOMING:
            control |= Control.HOME
        return control

    def _run_velocity_mode(self) -> None:
        if self.mode == MODE_CYCLIC_VELOCITY and self.state == OPERATION_ENABLED:
            self.axis.run_at(counts_to_rad(self.target_velocity_counts_s))

    def set_target(self, counts: int) -> None:
        """Target position; OutOfRangeError (nothing changes) outside the axis range."""
        try:
            self.axis.set_target(counts_to_rad(counts))
        except OutOfRangeError:
            self.target_refused = True
            raise
        self.target_refused = False

    def statusword(self) -> int:
        self._follow_faults()
        axis = self.axis
        status = axis.status()
        word = STATE_BITS[self.state] | _REMOTE
        moving = axis.is_moving()
        if not moving and (Status.IN_POSITION in status or self.controlword & _HALT):
            word |= _TARGET_REACHED
        if Status.AT_LIMIT in status:
            word |= _INTERNAL_LIMIT
        acknowledged = self.controlword & _NEW_SETPOINT and not self.target_refused
        if (self.mode == MODE_HOMING and Status.HOMED in status and not moving) or (
            self.mode == MODE_PROFILE_POSITION and acknowledged and self.state == OPERATION_ENABLED
        ):
            word |= _MODE_BIT12
        return word

    # SDO access -----------------------------------------------------------------
    def read(self, index: int, subindex: int) -> int | None:
        """Value of an object, or None to fall back to the EDS default."""
        with self.unit.lock:
            axis = self.axis
            values = {
                (0x6040, 0): lambda: self.controlword,
                (0x6041, 0): self.statusword,
                (0x6060, 0): lambda: self.mode,
                (0x6061, 0): lambda: self.mode,
                (0x6064, 0): lambda: rad_to_counts(axis.reported_rad()),
                (0x606C, 0): lambda: rad_to_counts(axis.profile.state(self.unit.clock.now())[1]),
                (0x607A, 0): lambda: rad_to_counts(axis.target_rad),
                (0x6081, 0): lambda: rad_to_counts(axis.velocity_limit_rad_s),
                (0x6083, 0): lambda: rad_to_counts(axis.limits.acceleration_rad_s2),
                (0x6085, 0): lambda: rad_to_counts(self.unit.register_map.quick_stop_rad_s2),
                (0x603F, 0): lambda: FAULT_CODE_BASE + axis.fault_code if axis.fault_code else 0,
                (0x607D, 1): lambda: rad_to_counts(axis.limits.min_rad),
                (0x607D, 2): lambda: rad_to_counts(axis.limits.max_rad),
                (0x608F, 1): lambda: COUNTS_PER_REV,
                (0x60FF, 0): lambda: self.target_velocity_counts_s,
            }
            self._follow_faults()
            value = values.get((index, subindex))
            return None if value is None else int(value())

    def write(self, index: int, subindex: int, value: int) -> None:
        """Apply an object write; SdoAbortedError (value range) for a refused value."""
        with self.unit.lock:
            try:
                if index == 0x6040:
                    self.write_controlword(value)
                elif index == 0x607A:
                    self.set_target(value)
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

    def on_rpdo(self, data: bytes) -> None:
        """RPDO 1: target position first, then the controlword (so a new set-point uses it)."""
        controlword, target = _RPDO1.unpack(bytes(data[: _RPDO1.size]))
        with self.unit.lock:
            try:
                self.set_target(target)
            except OutOfRangeError as error:
                log.warning("node axis %d: RPDO target refused: %s", self.n, error)
            self.write_controlword(controlword)

    def tpdo(self) -> bytes:
        with self.unit.lock:
            return _TPDO1.pack(self.statusword(), rad_to_counts(self.axis.reported_rad()))


class CanopenUnitServer:
    """Every axis of the given units as CiA 402 nodes on one CAN bus.

    Node ids are the docs/conventions.md axis numbers (launch a1, a2 = 1, 2;
    receiver a3, a4, a5 = 3, 4, 5) plus ``node_base``. The host's heartbeat
    (node 127, CAN id 0x77F) feeds every unit's watchdog.

    Parameters
    ----------
    units : list of SimUnit
    channel : str
        python-can channel (a name for ``virtual``, a multicast group for ``udp_multicast``).
    interface : str
        ``virtual`` (in one process) or ``udp_multicast`` (across processes).
    hop_limit : int
        TTL of ``udp_multicast`` frames; 0 (default) keeps them on this computer.
    """

    def __init__(
        self,
        units: list[SimUnit],
        channel: str,
        interface: str = "virtual",
        node_base: int = 0,
        hop_limit: int = 0,
    ) -> None:
        self.units = units
        self.channel = channel
        self.interface = interface
        self.hop_limit = hop_limit
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = _NOTIFIER_CYCLE_S
        self.axes: dict[int, Cia402Axis] = {}
        self.nodes: dict[int, canopen.LocalNode] = {}
        for unit in units:
            first = 1 if unit.kind == "launch" else 3
            for n in range(1, len(unit.axes) + 1):
                self.axes[node_base + first + n - 1] = Cia402Axis(unit, n)
        self._heartbeats = 0
        self._stop = threading.Event()
        self._tpdo_thread = threading.Thread(target=self._send_tpdos, name="tpdo", daemon=True)

    @property
    def node_ids(self) -> list[int]:
        return sorted(self.axes)

    def start(self) -> None:
        options: dict[str, Any] = {}
        if self.interface == "udp_multicast":
            options["hop_limit"] = self.hop_limit
        self.network.connect(interface=self.interface, channel=self.channel, **options)
        for node_id, axis in self.axes.items():
            node = canopen.LocalNode(node_id, str(EDS_PATH))
            node.add_read_callback(_reader(node_id, axis))
            node.add_write_callback(_writer(node_id, axis))
            self.network.add_node(node)
            node.nmt.state = "OPERATIONAL"
            self.nodes[node_id] = node
            self.network.subscribe(0x200 + node_id, self._rpdo_handler(node_id, axis))
        self.network.subscribe(0x700 + HOST_NODE_ID, self._on_host_heartbeat)
        self._tpdo_thread.start()

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._heartbeats = self._heartbeats % 0xFFFF + 1
        for unit in self.units:
            unit.heartbeat(self._heartbeats)

    def _send_tpdos(self) -> None:
        last: dict[int, tuple[int, float]] = {}
        while not self._stop.wait(_TPDO_POLL_S):
            for node_id, axis in self.axes.items():
                if self.nodes[node_id].nmt.state != "OPERATIONAL":
                    continue  # PDOs only in NMT operational
                data = axis.tpdo()
                statusword = _TPDO1.unpack(data)[0]
                now = axis.unit.clock.now()
                previous = last.get(node_id)
                if (
                    previous is None
                    or previous[0] != statusword
                    or now - previous[1] >= TPDO_EVENT_TIMER_S
                ):
                    last[node_id] = (statusword, now)
                    self.network.send_message(0x180 + node_id, data)

    def _rpdo_handler(
        self, node_id: int, axis: Cia402Axis
    ) -> Callable[[int, bytearray, float], None]:
        def on_rpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if self.nodes[node_id].nmt.state != "OPERATIONAL":
                return  # PDOs only in NMT operational
            log.debug("node %d RPDO1 <- %s", node_id, bytes(data).hex())
            axis.on_rpdo(bytes(data))

        return on_rpdo

    def stop(self) -> None:
        self._stop.set()
        if self._tpdo_thread.is_alive():
            self._tpdo_thread.join(2.0)
        self.network.disconnect()


def _reader(node_id: int, axis: Cia402Axis) -> Callable[..., int | None]:
    def read(index: int, subindex: int, od: canopen.objectdictionary.ODVariable) -> int | None:
        value = axis.read(index, subindex)
        log.debug("node %d SDO read 0x%04X:%d -> %s", node_id, index, subindex, value)
        return value

    return read


def _writer(node_id: int, axis: Cia402Axis) -> Callable[..., None]:
    def write(
        index: int, subindex: int, od: canopen.objectdictionary.ODVariable, data: bytes
    ) -> None:
        value = int(od.decode_raw(data))
        log.debug("node %d SDO write 0x%04X:%d <- %d", node_id, index, subindex, value)
        axis.write(index, subindex, value)

    return write
