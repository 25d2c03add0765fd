"""Modbus driver of the positioning-unit firmware interface (docs/registers.md).

The driver (:class:`ModbusUnit`, :class:`ModbusAxis`) talks to a
:class:`RegisterTransport`: anything that reads and writes holding registers.
:class:`ModbusTransport` is the real one (pymodbus, TCP or RTU) with timeouts,
retries and reconnect; a simulated unit's register API serves in-process
tests unchanged. Every error names the device.

The heartbeat is written from :meth:`ModbusUnit.beat`, which every driver call
and every wait loop invokes, so it keeps pace with simulated time too; for
hardware, :meth:`ModbusUnit.start_heartbeat` adds a background thread that
beats while the host is busy elsewhere (e.g. waiting for the operator).
Opening a unit clears a heartbeat fault left from power-on or an earlier host.

Every register read and write is logged on the ``firmware_iface.modbus``
logger at DEBUG (register name, address and words); reconnects at WARNING.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Literal, Protocol

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException

from firmware_iface.register_map import Control, Register, RegisterMap, Status, load_register_map
from firmware_iface.unit import AxisGroup, axis_fault
from xmalign.errors import (
    DeviceError,
    DeviceTimeoutError,
    HeartbeatError,
    OutOfRangeError,
    TransportError,
    XmalignError,
)
from xmalign.roles import Clock, ClosesOnExit, WallClock

#: Modbus exception code "illegal data value": the firmware refuses an out-of-range write.
ILLEGAL_DATA_VALUE = 3
#: Modbus exception code "server device busy": another host controls the unit.
SERVER_DEVICE_BUSY = 6
#: After its own reconnect the host may still be the unit's owner on the connection it
#: dropped, until the unit sees that one closed (or 500 ms without a heartbeat change,
#: counted from the dropped request, which can reach a slow unit late): a "busy" answer
#: in this time is asked again, not taken as another host's (docs/registers.md).
BUSY_AFTER_RECONNECT_S = 2.0
BUSY_RETRY_S = 0.05
#: Modbus exception code "illegal data address": no such (writable, whole) register.
ILLEGAL_DATA_ADDRESS = 2
#: Modbus exception code "gateway target device failed to respond": no unit with that id.
GATEWAY_TARGET_FAILED = 11
#: docs/conventions.md numbers the axes across both units: launch a1, a2; receiver a3, a4, a5.
FIRST_AXIS = {"launch": 1, "receiver": 3}
_UINT16 = 1 << 16
_UINT32 = 1 << 32

log = logging.getLogger(__name__)


class RegisterTransport(Protocol):
    """Holding-register access to one device (Modbus, or a simulated unit in-process)."""

    def read_registers(self, address: int, count: int) -> list[int]: ...

    def write_registers(self, address: int, values: Sequence[int]) -> None: ...


def encode(register: Register, value: int) -> list[int]:
    """Register words of ``value`` (32-bit values high word first)."""
    if register.width == 1:
        return [value % _UINT16]
    raw = value % _UINT32
    return [raw >> 16, raw & 0xFFFF]


def decode(register: Register, words: Sequence[int]) -> int:
    """Integer value of a register from its words (int32 sign-extended)."""
    if register.width == 1:
        return int(words[0])
    raw = (int(words[0]) << 16) | int(words[1])
    if register.type == "int32" and raw >= 1 << 31:
        raw -= _UINT32
    return raw


class ModbusTransport(ClosesOnExit):
    """A pymodbus client with reconnect and retries; errors name ``device_name``.

    Parameters
    ----------
    client : ModbusTcpClient or ModbusSerialClient
        Not yet connected; the transport connects on first use and after a drop.
    device_name : str
        How errors name the device, e.g. ``"launch unit at 10.0.0.5:502"``.
    device_id : int
        Modbus unit / slave id.
    retries : int
        Extra attempts (each after a reconnect) before a TransportError.
    """

    def __init__(
        self,
        client: ModbusTcpClient | ModbusSerialClient,
        device_name: str,
        device_id: int = 1,
        retries: int = 2,
    ) -> None:
        self.client = client
        self.device_name = device_name
        self.device_id = device_id
        self.retries = retries
        self._lock = threading.Lock()
        self._dropped_s: float | None = None  # when this transport last dropped its connection

    def read_registers(self, address: int, count: int) -> list[int]:
        response = self._call(
            "read",
            address,
            lambda c: c.read_holding_registers(address, count=count, device_id=self.device_id),
        )
        return list(response.registers)

    def write_registers(self, address: int, values: Sequence[int]) -> None:
        self._call(
            "write",
            address,
            lambda c: c.write_registers(address, list(values), device_id=self.device_id),
        )

    def close(self) -> None:
        with self._lock:
            self.client.close()

    def _call(self, verb: str, address: int, request: Callable[[Any], Any]) -> Any:
        with self._lock:
            while True:
                response = self._attempts(verb, address, request)
                if not response.isError():
                    return response
                if not self._busy_with_itself(response):
                    raise self._refusal(verb, address, response)
                time.sleep(BUSY_RETRY_S)

    def _attempts(self, verb: str, address: int, request: Callable[[Any], Any]) -> Any:
        """The response to ``request``, reconnecting after a drop (``retries`` times)."""
        last: Exception | None = None
        for _ in range(self.retries + 1):
            try:
                if not self.client.connected and not self.client.connect():
                    raise TransportError(f"cannot connect to the {self.device_name}")
                return request(self.client)
            except (ModbusException, OSError, TransportError) as error:
                last = error
                log.warning(
                    "%s: %s at register %d failed: %s", self.device_name, verb, address, error
                )
                self.client.close()
                self._dropped_s = time.monotonic()
        raise TransportError(
            f"lost the connection to the {self.device_name} ({verb} at register {address}: {last})"
        ) from last

    def _busy_with_itself(self, response: object) -> bool:
        """A "busy" answer shortly after this transport dropped its own connection."""
        return (
            getattr(response, "exception_code", None) == SERVER_DEVICE_BUSY
            and self._dropped_s is not None
            and time.monotonic() - self._dropped_s < BUSY_AFTER_RECONNECT_S
        )

    def _refusal(self, verb: str, address: int, response: object) -> XmalignError:
        code = getattr(response, "exception_code", None)
        log.debug("%s: %s at %d answered exception %s", self.device_name, verb, address, code)
        if code == SERVER_DEVICE_BUSY:
            return DeviceError(
                f"the {self.device_name} refused the {verb} at register {address}: another host"
                " controls it (Modbus exception 6, server device busy; it is free once that"
                " host closes its connection or stops changing the heartbeat for 500 ms)"
            )
        if code == ILLEGAL_DATA_ADDRESS:
            return DeviceError(
                f"the {self.device_name} refused the {verb} at register {address}: no such"
                " register, a read-only one, or one word of a 32-bit value (Modbus exception 2)"
            )
        if code == GATEWAY_TARGET_FAILED:
            return DeviceError(
                f"the {self.device_name} has no unit with device id {self.device_id}"
                f" (Modbus exception 11 to the {verb} at register {address}); check device_id"
            )
        if code == ILLEGAL_DATA_VALUE:
            return OutOfRangeError(
                f"the {self.device_name} refused the {verb} at register {address}:"
                " value out of range"
            )
        return DeviceError(
            f"the {self.device_name} answered the {verb} at register {address}"
            f" with Modbus exception {code}"
        )


def tcp_transport(
    host: str,
    port: int,
    device_name: str,
    device_id: int = 1,
    timeout_s: float = 1.0,
    retries: int = 2,
) -> ModbusTransport:
    """Transport over Modbus TCP."""
    client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0, reconnect_delay=0)
    return ModbusTransport(client, f"{device_name} at {host}:{port}", device_id, retries)


def rtu_transport(
    serial_port: str,
    device_name: str,
    baudrate: int = 115200,
    device_id: int = 1,
    timeout_s: float = 1.0,
    retries: int = 2,
) -> ModbusTransport:
    """Transport over Modbus RTU on a serial line."""
    client = ModbusSerialClient(
        serial_port, baudrate=baudrate, timeout=timeout_s, retries=0, reconnect_delay=0
    )
    return ModbusTransport(client, f"{device_name} on {serial_port}", device_id, retries)


class ModbusAxis:
    """One axis (1-based ``number``) of a :class:`ModbusUnit`; implements ``RotaryAxis``."""

    def __init__(self, unit: ModbusUnit, number: int, name: str) -> None:
        self.unit = unit
        self.number = number
        self.name = name

    @property
    def label(self) -> str:
        return f"axis {self.name} of the {self.unit.device_name}"

    def position_rad(self) -> float:
        return self.unit.counts_to_rad(self.unit.read(self.number, "actual"))

    def status(self) -> Status:
        return Status(self.unit.read(self.number, "status"))

    def fault_code(self) -> int:
        return self.unit.read(self.number, "fault_code")

    def move_to(self, angle_rad: float) -> None:
        counts = self.unit.rad_to_counts(angle_rad)
        try:
            self.unit.write(self.number, "target", counts)
        except OutOfRangeError as error:
            raise OutOfRangeError(
                f"{self.label}: target {math.degrees(angle_rad):.4f} deg is out of its range"
            ) from error
        self._control(Control.ENABLE | Control.UNLOCK)
        self._control(Control.ENABLE | Control.UNLOCK | Control.START)

    def wait_in_position(self, timeout_s: float) -> None:
        clock = self.unit.clock
        deadline = clock.now() + timeout_s
        while True:
            status = self.check()
            if Status.IN_POSITION in status and Status.MOVING not in status:
                return
            if clock.now() >= deadline:
                raise DeviceTimeoutError(
                    f"{self.label} did not reach its target in {timeout_s:g} s"
                )
            clock.sleep(self.unit.poll_s)

    def check(self) -> Status:
        """Status of the axis; raises the axis's fault as a DriveFaultError or HeartbeatError."""
        status = self.status()
        if Status.FAULT in status:
            raise axis_fault(self.label, self.unit.read(self.number, "fault_code"))
        return status

    def stop(self) -> None:
        self._control(Control.ENABLE | Control.UNLOCK | Control.STOP)

    def lock(self) -> None:
        self._control(Control.ENABLE | Control.STOP)

    def is_locked(self) -> bool:
        return Status.LOCKED in self.status()

    def enable(self) -> None:
        self._control(Control.ENABLE)

    def reset_fault(self) -> None:
        """Reset the axis's fault; a heartbeat goes first (the unit refuses it without one)."""
        self.unit.beat_now()
        self._control(Control.ENABLE | Control.FAULT_RESET)
        self._control(Control.ENABLE)

    def home(self) -> None:
        """Start homing; wait with :meth:`wait_homed`."""
        self._control(Control.ENABLE | Control.UNLOCK)
        self._control(Control.ENABLE | Control.UNLOCK | Control.HOME)

    def wait_homed(self, timeout_s: float) -> None:
        clock = self.unit.clock
        deadline = clock.now() + timeout_s
        while Status.HOMED not in self.check():
            if clock.now() >= deadline:
                raise DeviceTimeoutError(f"{self.label} did not finish homing in {timeout_s:g} s")
            clock.sleep(self.unit.poll_s)

    def set_velocity_limit(self, rad_s: float) -> None:
        self.unit.write(self.number, "velocity_limit", self.unit.rad_to_counts(rad_s))

    def _control(self, bits: Control) -> None:
        self.unit.write(self.number, "control", int(bits))


class ModbusUnit(AxisGroup, ClosesOnExit):
    """A positioning unit behind a register transport; implements ``PositioningUnit``.

    Parameters
    ----------
    transport : RegisterTransport
        Modbus (:func:`tcp_transport`, :func:`rtu_transport`) or a simulated unit.
    device_name : str
        Name used in messages; defaults to the transport's ``device_name``.
    expected_kind : {"launch", "receiver"}, optional
        Refuse a device of the other kind (a swapped cable or address).
    clock : Clock
        Time source of the waits (simulated time for an in-process simulated unit).
    poll_s : float
        Period of the status polls while waiting.
    """

    def __init__(
        self,
        transport: RegisterTransport,
        device_name: str | None = None,
        expected_kind: Literal["launch", "receiver"] | None = None,
        clock: Clock | None = None,
        poll_s: float = 0.01,
        register_map: RegisterMap | None = None,
    ) -> None:
        self.transport = transport
        self.device_name: str = device_name or str(
            getattr(transport, "device_name", "positioning unit")
        )
        self.clock = clock or WallClock()
        self.poll_s = poll_s
        self.register_map = register_map or load_register_map()
        self._heartbeat_value = 0
        self._last_beat_s = -math.inf
        self._heartbeat_lock = threading.Lock()
        self._heartbeat_thread: threading.Thread | None = None
        self._heartbeat_stop = threading.Event()
        self._heartbeat_failure: Exception | None = None
        self._cancel_heartbeat: Callable[[], None] | None = None
        kinds: dict[int, Literal["launch", "receiver"]] = {
            code: kind  # type: ignore[misc]  # registers.yaml names exactly these two
            for kind, code in self.register_map.device_types.items()
        }
        device_type = self._read_device("device_type")
        if device_type not in kinds:
            raise DeviceError(
                f"the {self.device_name} reports an unknown device type {device_type}"
            )
        self.kind: Literal["launch", "receiver"] = kinds[device_type]
        if expected_kind is not None and self.kind != expected_kind:
            raise DeviceError(
                f"the {self.device_name} is a {self.kind} unit, expected a {expected_kind} unit"
            )
        self.counts_per_rev = self._read_device("counts_per_rev")
        self.firmware_version = self._read_device("firmware_version")
        n_axes = self._read_device("axis_count")
        first = FIRST_AXIS[self.kind]
        self._axes = tuple(ModbusAxis(self, n, f"a{first + n - 1}") for n in range(1, n_axes + 1))
        self.clear_heartbeat_faults()

    # --- conversions and register access -------------------------------------------------
    def counts_to_rad(self, counts: int) -> float:
        return 2.0 * math.pi * counts / self.counts_per_rev

    def rad_to_counts(self, angle_rad: float) -> int:
        return round(angle_rad * self.counts_per_rev / (2.0 * math.pi))

    def read(self, axis: int, name: str) -> int:
        self.beat()
        return self._read_register(self.register_map.axis(axis, name))

    def write(self, axis: int, name: str, value: int) -> None:
        self.beat()
        self._write_register(self.register_map.axis(axis, name), value)

    def _read_device(self, name: str) -> int:
        return self._read_register(self.register_map.device[name])

    def _read_register(self, register: Register) -> int:
        words = self.transport.read_registers(register.address, register.width)
        value = decode(register, words)
        log.debug(
            "%s: read %s @%d -> %s = %d",
            self.device_name,
            register.name,
            register.address,
            list(words),
            value,
        )
        return value

    def _write_register(self, register: Register, value: int) -> None:
        words = encode(register, value)
        log.debug(
            "%s: write %s @%d <- %s = %d",
            self.device_name,
            register.name,
            register.address,
            words,
            value,
        )
        self.transport.write_registers(register.address, words)

    # --- heartbeat ------------------------------------------------------------------------
    def beat(self) -> None:
        """Change the heartbeat register if half a heartbeat period has passed."""
        self._beat_if_older(self.register_map.heartbeat_period_s / 2.0)

    def beat_now(self) -> None:
        """Change the heartbeat register now (before a fault reset, which needs a fresh one).

        The register holds the driver's previous beat (just after opening, whatever an
        earlier host left, but the open's first beat went before), so this one is a
        change either way and the unit takes the fault reset that follows.
        """
        self._beat_if_older(0.0)

    def _beat_if_older(self, age_s: float) -> None:
        if self._heartbeat_failure is not None:
            raise HeartbeatError(
                f"the heartbeat to the {self.device_name} stalled: {self._heartbeat_failure}"
            ) from self._heartbeat_failure
        with self._heartbeat_lock:  # the background thread and the calls: one count
            now = self.clock.now()
            if now - self._last_beat_s < age_s:
                return
            self._last_beat_s = now
            # 1..65535: the power-on value 0 never comes back, so every beat is a change
            self._heartbeat_value = self._heartbeat_value % (_UINT16 - 1) + 1
            self._write_register(self.register_map.device["heartbeat"], self._heartbeat_value)

    def start_heartbeat(self) -> None:
        """Beat from a background thread (wall time) until :meth:`stop_heartbeat`.

        A clock that offers ``call_every(period_s, callback) -> cancel`` (the
        simulator's :class:`sim.clock.LockstepClock`, whose time a wall-clock
        thread would not keep pace with) calls the beat in its own time instead.
        """
        if self._heartbeat_thread is not None or self._cancel_heartbeat is not None:
            return
        call_every = getattr(self.clock, "call_every", None)
        if call_every is not None:
            period_s = self.register_map.heartbeat_period_s / 2.0
            self._cancel_heartbeat = call_every(period_s, self._background_beat)
            return
        self._heartbeat_stop.clear()
        self._heartbeat_thread = threading.Thread(
            target=self._heartbeat_loop, name=f"heartbeat {self.device_name}", daemon=True
        )
        self._heartbeat_thread.start()

    def stop_heartbeat(self) -> None:
        if self._cancel_heartbeat is not None:
            self._cancel_heartbeat()
            self._cancel_heartbeat = None
        if self._heartbeat_thread is None:
            return
        self._heartbeat_stop.set()
        self._heartbeat_thread.join()
        self._heartbeat_thread = None

    def _heartbeat_loop(self) -> None:
        # A beat on every wake (a quarter period, 50 ms), not only when the driver's half
        # period has passed: a host process stalled by its computer for up to 300 ms
        # (the 350 ms expiry less one wake) does not trip the watchdog (docs/hardware.md).
        period_s = self.register_map.heartbeat_period_s / 4.0
        while not self._heartbeat_stop.wait(period_s) and self._background_beat():
            pass

    def _background_beat(self) -> bool:
        """A beat of the background heartbeat; False (the failure kept) when it failed."""
        if self._heartbeat_failure is not None:
            return False
        try:
            self._beat_if_older(self.register_map.heartbeat_period_s / 8.0)
        except XmalignError as error:
            self._heartbeat_failure = error
            return False
        return True

    # --- unit operations ------------------------------------------------------------------
    def home(self, timeout_s: float) -> None:
        """Home every axis and wait until all report homed."""
        for axis in self._axes:
            axis.home()
        for axis in self._axes:
            axis.wait_homed(timeout_s)

    def close(self) -> None:
        """Stop the heartbeat thread and close the transport (axes are left as they are)."""
        self.stop_heartbeat()
        close = getattr(self.transport, "close", None)
        if close is not None:
            close()
