"""Simulated unit axes as CiA 402 nodes (``canopen`` LocalNode over python-can).

One node per axis with the object dictionary of ``firmware_iface/cia402_axis.eds``;
the behaviour is docs/canopen-axis.md. :class:`Cia402Axis` is the CiA 402
state machine of a drive: it takes only the transitions of the CiA 402 state
diagram and ignores every other command, as a drive does; a fault of the axis
shows as *Fault reaction active* while the axis stops and as *Fault* once it is
at rest. Its states drive the unit's firmware control bits (``SimUnit.control``),
so Modbus and CANopen share one behaviour: *Operation enabled* = enable |
unlock, *Switched on* = enable (locked), everything else disabled and locked.

:class:`CanopenUnitServer` puts the nodes on a bus (by default ``udp_local``,
firmware_iface/can_bus.py): each sends its boot-up message and waits in NMT
*pre-operational* until a host starts it; PDOs (RPDO 1 controlword, RPDO 2
target position, TPDO 1 statusword + position actual value on a change and
every 50 ms) only in *operational*; an EMCY whenever the error code 0x603F
changes. Every SDO, PDO, NMT command and EMCY is logged on
``sim.servers.canopen_node`` at DEBUG.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections.abc import Callable
from functools import partial

import canopen
from canopen import SdoAbortedError

from firmware_iface.can_bus import LOOPBACK, open_can_bus
from firmware_iface.register_map import REGISTER_MAP_PATH, Control, Status
from firmware_iface.unit import HEARTBEAT_FAULT
from sim.units import COUNTS_PER_REV, SimAxis, SimUnit, counts_to_rad, rad_to_counts
from xmalign.errors import OutOfRangeError

log = logging.getLogger(__name__)

EDS_PATH = REGISTER_MAP_PATH.with_name("cia402_axis.eds")
HOST_NODE_ID = 0x7F
ABORT_VALUE_RANGE = 0x06090030
MODE_PROFILE_POSITION, MODE_HOMING, MODE_CYCLIC_VELOCITY = 1, 6, 9
MODES = (MODE_PROFILE_POSITION, MODE_HOMING, MODE_CYCLIC_VELOCITY)
FAULT_CODE_BASE = 0xFF00
#: Error register 0x1001: bit 0 generic error, bit 4 communication error (the host heartbeat).
ERROR_GENERIC, ERROR_COMMUNICATION = 0x01, 0x10
#: TPDO 1 is sent at least this often (0x1800 sub5), and on every statusword change.
TPDO_EVENT_TIMER_S = 0.05
_POLL_S = 0.01
#: How long the bus reader waits for a frame before it looks whether to stop (canopen: 1 s).
_NOTIFIER_CYCLE_S = 0.1
_CONTROLWORD = struct.Struct("<H")  # RPDO 1
_TARGET_POSITION = struct.Struct("<i")  # RPDO 2
_TPDO1 = struct.Struct("<Hi")  # statusword, position actual value
#: NMT commands (CiA 301): start, stop, enter pre-operational, reset node, reset communication.
NMT_RESET_NODE, NMT_RESET_COMMUNICATION = 0x81, 0x82

# Controlword bits
_NEW_SETPOINT, _FAULT_RESET, _HALT = 0x10, 0x80, 0x100

# CiA 402 states and their statusword bits (voltage enabled where the drive has power on)
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
FAULT = "FAULT"
STATE_BITS = {
    SWITCH_ON_DISABLED: 0x0040,
    READY_TO_SWITCH_ON: 0x0031,
    SWITCHED_ON: 0x0033,
    OPERATION_ENABLED: 0x0037,
    QUICK_STOP_ACTIVE: 0x0017,
    FAULT_REACTION_ACTIVE: 0x001F,
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
    (  # enable operation: transition 4; from ready to switch on "switch on" with bit 3: 3 + 4
        0x8F,
        0x0F,
        {SWITCHED_ON: OPERATION_ENABLED, READY_TO_SWITCH_ON: OPERATION_ENABLED},
    ),
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
    """The CiA 402 state after controlword ``word`` (``previous_word`` for the fault-reset edge).

    *Fault reaction active* ignores every command: it ends by itself (transition 14).
    """
    if state == FAULT_REACTION_ACTIVE:
        return state
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
        """A fault of the unit's axis (drive, watchdog) starts the fault reaction (13); Fault
        once the axis is at rest (14)."""
        self.unit.check_watchdog()
        if self.axis.fault_code and self.state not in (FAULT_REACTION_ACTIVE, FAULT):
            log.debug("node axis %d: %s -> %s", self.n, self.state, FAULT_REACTION_ACTIVE)
            self.state = FAULT_REACTION_ACTIVE
        at_rest = not self.axis.is_moving()
        if self.state == FAULT_REACTION_ACTIVE and at_rest:
            log.debug("node axis %d: %s -> %s", self.n, self.state, FAULT)
            self.state = FAULT
        if self.state == QUICK_STOP_ACTIVE and at_rest:
            self.state = SWITCH_ON_DISABLED  # quick stop option code 2: then switch on disabled

    def write_controlword(self, word: int) -> None:
        self._follow_faults()
        previous_state, previous_word = self.state, self.controlword
        self.controlword = word
        if previous_state == FAULT_REACTION_ACTIVE:
            return  # the axis is stopping at the quick-stop deceleration: nothing interrupts it
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
            if self.axis.fault_code:  # refused (the cause persists): stay in Fault
                log.debug("node axis %d: fault reset refused, fault %d", self.n, self.fault())
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

    def max_profile_velocity_counts_s(self) -> int:
        """The highest profile velocity (0x6081) the axis takes: its maximum in whole counts/s."""
        return rad_to_counts(self.axis.limits.max_velocity_rad_s)

    def set_profile_velocity(self, counts_s: int) -> None:
        """0x6081; OutOfRangeError outside 1 .. :meth:`max_profile_velocity_counts_s`."""
        highest = self.max_profile_velocity_counts_s()
        if not 1 <= counts_s <= highest:
            raise OutOfRangeError(
                f"axis {self.axis.name}: profile velocity {counts_s} counts/s outside 1..{highest}"
            )
        self.axis.set_velocity_limit(
            min(counts_to_rad(counts_s), self.axis.limits.max_velocity_rad_s)
        )

    def fault(self) -> int:
        """The axis's fault code (docs/registers.md numbering), 0 for none."""
        self._follow_faults()
        return self.axis.fault_code

    def error_code(self) -> int:
        """0x603F: ``0xFF00 + fault code``, 0 without a fault."""
        code = self.fault()
        return FAULT_CODE_BASE + code if code else 0

    def error_register(self) -> int:
        """0x1001: generic error while faulted, plus communication error for the heartbeat."""
        code = self.fault()
        if not code:
            return 0
        return ERROR_GENERIC | (ERROR_COMMUNICATION if code == HEARTBEAT_FAULT else 0)

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

    def reset(self) -> None:
        """NMT reset node: the drive returns to *Switch on disabled* (stopped, braked); a
        fault stays until a fault reset."""
        with self.unit.lock:
            self._follow_faults()
            self.controlword = 0
            self.mode = MODE_PROFILE_POSITION
            self.target_velocity_counts_s = 0
            self.target_refused = False
            if self.state not in (FAULT_REACTION_ACTIVE, FAULT):
                self.state = SWITCH_ON_DISABLED
                self.unit.control(self.n, Control(0))

    # SDO access -----------------------------------------------------------------
    def read(self, index: int, subindex: int) -> int | None:
        """Value of an object, or None to fall back to the EDS default."""
        with self.unit.lock:
            axis = self.axis
            values = {
                (0x1001, 0): self.error_register,
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
                (0x603F, 0): self.error_code,
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
                    self.set_profile_velocity(value)
                elif index == 0x6060:
                    if value not in MODES:
                        raise OutOfRangeError(f"mode of operation {value} not supported")
                    self.mode = value
                elif index == 0x60FF:
                    self.target_velocity_counts_s = value
                    self._run_velocity_mode()
            except OutOfRangeError as error:
                raise SdoAbortedError(ABORT_VALUE_RANGE) from error

    def on_controlword_pdo(self, data: bytes) -> None:
        """RPDO 1: the controlword."""
        (controlword,) = _CONTROLWORD.unpack(data)
        with self.unit.lock:
            self.write_controlword(controlword)

    def on_target_pdo(self, data: bytes) -> None:
        """RPDO 2: the target position (a refused one is dropped, and the next new set-point
        is not acknowledged)."""
        (target,) = _TARGET_POSITION.unpack(data)
        with self.unit.lock:
            try:
                self.set_target(target)
            except OutOfRangeError as error:
                log.warning("node axis %d: RPDO target refused: %s", self.n, error)

    def tpdo(self) -> bytes:
        with self.unit.lock:
            return _TPDO1.pack(self.statusword(), rad_to_counts(self.axis.reported_rad()))


#: The RPDOs: COB-ID base -> (content, what the node does with it).
RPDOS: dict[int, tuple[struct.Struct, Callable[[Cia402Axis, bytes], None]]] = {
    0x200: (_CONTROLWORD, Cia402Axis.on_controlword_pdo),
    0x300: (_TARGET_POSITION, Cia402Axis.on_target_pdo),
}


class CanopenUnitServer:
    """Every axis of the given units as CiA 402 nodes on one CAN bus.

    Node ids are the docs/conventions.md axis numbers (launch a1, a2 = 1, 2;
    receiver a3, a4, a5 = 3, 4, 5) plus ``node_base``. The host's heartbeat
    (node 127, CAN id 0x77F) feeds every unit's watchdog.

    Parameters
    ----------
    units : list of SimUnit
    channel : str
        python-can channel (a multicast group for ``udp_local``, a name for ``virtual``).
    interface : str
        ``udp_local`` (across processes, firmware_iface/can_bus.py), ``virtual`` (in one
        process) or another python-can interface.
    host : str
        ``udp_local``: address of the network interface (default the loopback).
    hop_limit : int
        ``udp_local`` TTL; 0 (default) keeps the frames on this computer.
    """

    def __init__(
        self,
        units: list[SimUnit],
        channel: str,
        interface: str = "virtual",
        node_base: int = 0,
        hop_limit: int = 0,
        host: str = LOOPBACK,
    ) -> None:
        self.units = units
        self.channel = channel
        self.interface = interface
        self.host = host
        self.hop_limit = hop_limit
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = _NOTIFIER_CYCLE_S
        self.axes: dict[int, Cia402Axis] = {}
        self.nodes: dict[int, canopen.LocalNode] = {}
        for unit in units:
            first = 1 if unit.kind == "launch" else 3
            for n in range(1, len(unit.axes) + 1):
                self.axes[node_base + first + n - 1] = Cia402Axis(unit, n)
        self.bus_info = ""  # the bus, once started
        self._heartbeats = 0
        self._stop = threading.Event()
        self._poll_thread = threading.Thread(target=self._poll, name="canopen-nodes", daemon=True)

    @property
    def node_ids(self) -> list[int]:
        return sorted(self.axes)

    def start(self) -> None:
        """Open the bus (TransportError if it cannot be), boot every node into pre-operational."""
        bus = open_can_bus(self.interface, self.channel, host=self.host, hop_limit=self.hop_limit)
        self.bus_info = bus.channel_info
        self.network.bus = bus
        self.network.connect()
        for node_id, axis in self.axes.items():
            node = canopen.LocalNode(node_id, str(EDS_PATH))
            node.sdo.on_request = _silent_when_stopped(node)  # type: ignore[method-assign]
            node.add_read_callback(_reader(node_id, axis))
            node.add_write_callback(_writer(node_id, axis))
            self.network.add_node(node)
            self.nodes[node_id] = node
            for base, (content, apply) in RPDOS.items():
                handler = self._rpdo_handler(node_id, content, partial(apply, axis))
                self.network.subscribe(base + node_id, handler)
        self.network.subscribe(0, self._on_nmt_command)  # after each node's own NMT handler
        self.network.subscribe(0x700 + HOST_NODE_ID, self._on_host_heartbeat)
        for node_id in self.axes:
            self._boot(node_id)
        self._poll_thread.start()

    def _boot(self, node_id: int) -> None:
        """Boot-up message (0x700 + id, one byte 0), then NMT pre-operational."""
        log.debug("node %d NMT boot-up -> pre-operational", node_id)
        self.network.send_message(0x700 + node_id, b"\x00")
        self.nodes[node_id].nmt.state = "PRE-OPERATIONAL"

    def _on_nmt_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2:
            return
        command, target = data[0], data[1]
        log.debug("NMT command 0x%02X for node %d", command, target)
        if command not in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            return
        for node_id, axis in self.axes.items():
            if target in (0, node_id):
                if command == NMT_RESET_NODE:
                    axis.reset()
                self._boot(node_id)

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._heartbeats = self._heartbeats % 0xFFFF + 1
        for unit in self.units:
            unit.heartbeat(self._heartbeats)

    def _poll(self) -> None:
        """Follow every axis: an EMCY when its error code changes; TPDO 1 in operational."""
        last_tpdo: dict[int, tuple[int, float]] = {}
        error_codes = dict.fromkeys(self.axes, 0)
        while not self._stop.wait(_POLL_S):
            for node_id, axis in self.axes.items():
                state = self.nodes[node_id].nmt.state
                if state == "STOPPED":
                    continue  # NMT stopped: neither PDOs nor EMCY
                with axis.unit.lock:
                    error_code, error_register = axis.error_code(), axis.error_register()
                if error_code != error_codes[node_id]:
                    error_codes[node_id] = error_code
                    log.debug(
                        "node %d EMCY 0x%04X register 0x%02X", node_id, error_code, error_register
                    )
                    self.nodes[node_id].emcy.send(error_code, error_register)
                if state == "OPERATIONAL":  # PDOs only in NMT operational
                    self._send_tpdo(node_id, axis, last_tpdo)

    def _send_tpdo(
        self, node_id: int, axis: Cia402Axis, last: dict[int, tuple[int, float]]
    ) -> None:
        data = axis.tpdo()
        statusword = _TPDO1.unpack(data)[0]
        now = axis.unit.clock.now()
        previous = last.get(node_id)
        if previous is None or previous[0] != statusword or now - previous[1] >= TPDO_EVENT_TIMER_S:
            last[node_id] = (statusword, now)
            self.network.send_message(0x180 + node_id, data)

    def _rpdo_handler(
        self, node_id: int, content: struct.Struct, apply: Callable[[bytes], None]
    ) -> Callable[[int, bytearray, float], None]:
        def on_rpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            if self.nodes[node_id].nmt.state != "OPERATIONAL":
                return  # PDOs only in NMT operational
            log.debug("node %d RPDO 0x%03X <- %s", node_id, can_id, bytes(data).hex())
            if len(data) < content.size:
                log.warning("node %d: RPDO 0x%03X of %d bytes dropped", node_id, can_id, len(data))
                return
            apply(bytes(data[: content.size]))

        return on_rpdo

    def stop(self) -> None:
        self._stop.set()
        if self._poll_thread.is_alive():
            self._poll_thread.join(2.0)
        for node in self.nodes.values():
            node.nmt.stop_heartbeat()
        self.network.disconnect()


def _silent_when_stopped(node: canopen.LocalNode) -> Callable[[int, bytearray, float], None]:
    """The node's SDO server, silent in NMT stopped (CiA 301: only NMT and heartbeat there)."""
    answer = node.sdo.on_request

    def on_request(can_id: int, data: bytearray, timestamp: float) -> None:
        if node.nmt.state != "STOPPED":
            answer(can_id, data, timestamp)

    return on_request


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
