"""A :class:`~sim.units.SimUnit` served over Modbus TCP or Modbus RTU (on a pty) with pymodbus.

The pymodbus register block is only a mirror: every request goes to the unit's
register-level API first (``unit_device``'s action), so reads see the unit's
state at that instant and a refused write answers a Modbus exception:
exception 3 (illegal data value) for an out-of-range value, 2 (illegal data
address) for a read-only or unknown register, 6 (server device busy) for a
write from a connection that does not control the unit (docs/registers.md,
"One controlling host"). Every request is logged on ``sim.servers.modbus`` at
DEBUG.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import threading
import time
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from sim.servers.pty_pair import PtyPair
from sim.units import SimUnit
from xmalign.errors import InputError, OutOfRangeError, TransportError

log = logging.getLogger(__name__)

#: The connection (request handler) whose request is being served.
_connection: contextvars.ContextVar[object] = contextvars.ContextVar("modbus_connection")


#: A serial line never closes: its master is taken as gone after this long without a request.
SERIAL_MASTER_GONE_S = 1.0


class ControllingHost:
    """Which connection controls the unit: the first that writes, until it closes.

    One per unit, shared by every server of it (TCP and RTU). A serial line's
    master also gives the unit up after :data:`SERIAL_MASTER_GONE_S` of silence.
    """

    def __init__(self) -> None:
        self.owner: object | None = None
        self._owner_seen_s = 0.0
        self._lock = threading.Lock()

    def may_write(self, connection: object) -> bool:
        """Claim the unit for ``connection`` if free; whether it controls the unit."""
        with self._lock:
            silent_s = time.monotonic() - self._owner_seen_s
            if getattr(self.owner, "serial", False) and silent_s > SERIAL_MASTER_GONE_S:
                log.info("the serial master has been silent for %.1f s; the unit is free", silent_s)
                self.owner = None
            if self.owner is None:
                self.owner = connection
                log.info("connection %s now controls the unit", id(connection))
            return self.owner is connection

    def seen(self, connection: object) -> None:
        """Any request of ``connection`` (reads too)."""
        with self._lock:
            if self.owner is connection:
                self._owner_seen_s = time.monotonic()

    def release(self, connection: object) -> None:
        with self._lock:
            if self.owner is connection:
                self.owner = None
                log.info("connection %s closed; the unit is free", id(connection))


def unit_device(unit: SimUnit, host: ControllingHost, device_id: int = 1) -> SimDevice:
    """A pymodbus device whose holding registers are the unit's."""
    register_count = unit.register_map.axis_stride * (len(unit.axes) + 1)

    async def action(
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        current_registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        connection = _connection.get(None)
        host.seen(connection)
        if set_values and not host.may_write(connection):
            log.debug(
                "%s unit: fc %d @%d <- %s from %s: busy",
                unit.kind,
                function_code,
                address,
                set_values,
                id(connection),
            )
            return ExcCodes.DEVICE_BUSY
        try:
            if set_values:
                unit.write_registers(address, [int(v) for v in set_values])
            current_registers[:] = unit.read_registers(start_address, register_count)
        except OutOfRangeError as error:
            log.debug(
                "%s unit: fc %d @%d: exception 3 (%s)", unit.kind, function_code, address, error
            )
            return ExcCodes.ILLEGAL_VALUE
        except InputError as error:
            log.debug(
                "%s unit: fc %d @%d: exception 2 (%s)", unit.kind, function_code, address, error
            )
            return ExcCodes.ILLEGAL_ADDRESS
        if set_values:
            log.debug(
                "%s unit: fc %d @%d <- %s", unit.kind, function_code, address, list(set_values)
            )
        else:
            served = current_registers[address - start_address : address - start_address + count]
            log.debug(
                "%s unit: fc %d @%d x%d -> %s", unit.kind, function_code, address, count, served
            )
        return None

    registers = SimData(0, count=register_count, values=0, datatype=DataType.REGISTERS)
    return SimDevice(id=device_id, simdata=[registers], action=action)


class _Handler(ServerRequestHandler):
    """A connection: serves its requests as itself and frees the unit when it closes."""

    def __init__(self, owner: Any, host: ControllingHost, serial: bool = False) -> None:
        super().__init__(owner, owner.trace_packet, owner.trace_pdu, owner.trace_connect)
        self.host = host
        self.serial = serial

    async def handle_request(self) -> None:
        _connection.set(self)
        await super().handle_request()

    def callback_disconnected(self, exc: Exception | None) -> None:
        self.host.release(self)
        super().callback_disconnected(exc)


class _TcpServer(ModbusTcpServer):
    def __init__(self, host: ControllingHost, *args: Any, **kwargs: Any) -> None:
        self.host = host
        super().__init__(*args, **kwargs)

    def callback_new_connection(self) -> _Handler:
        return _Handler(self, self.host)


class _SerialServer(ModbusSerialServer):
    def __init__(self, host: ControllingHost, *args: Any, **kwargs: Any) -> None:
        self.host = host
        super().__init__(*args, **kwargs)

    def callback_new_connection(self) -> _Handler:
        return _Handler(self, self.host, serial=True)


class ModbusUnitServer:
    """Serve a unit over Modbus TCP on ``host:port`` from a background thread.

    Parameters
    ----------
    unit : SimUnit
        Should run on a real-time clock.
    host, port : str, int
        Where to listen (``127.0.0.1`` unless the user asks otherwise); port 0
        takes a free port (:attr:`port` then says which).
    device_id : int
        The Modbus unit id the unit answers to.
    controlling_host : ControllingHost, optional
        Shared with the unit's other servers (a new one by default).
    """

    def __init__(
        self,
        unit: SimUnit,
        host: str,
        port: int,
        device_id: int = 1,
        controlling_host: ControllingHost | None = None,
    ) -> None:
        self.unit = unit
        self.host = host
        self.port = port
        self.device_id = device_id
        self.controlling_host = controlling_host or ControllingHost()
        self.where = f"{host}:{port}"
        self._server: ModbusTcpServer | ModbusSerialServer | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name=f"modbus-{unit.kind}", daemon=True)
        self._started = threading.Event()
        self._error: BaseException | None = None

    def _build(self) -> ModbusTcpServer | ModbusSerialServer:
        device = unit_device(self.unit, self.controlling_host, self.device_id)
        return _TcpServer(self.controlling_host, device, address=(self.host, self.port))

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._serve())
        except BaseException as error:  # reported to the thread that called start()
            self._error = error
            self._started.set()

    async def _serve(self) -> None:
        # built inside the loop: pymodbus binds its futures to the running loop
        self._server = self._build()
        if not await self._server.listen():
            raise OSError(f"cannot listen on {self.where}")
        sockets = getattr(self._server.transport, "sockets", None)
        if self.port == 0 and sockets:  # an ephemeral port: say which one it is
            self.port = int(sockets[0].getsockname()[1])
            self.where = f"{self.host}:{self.port}"
        self._started.set()
        await self._server.serving

    def start(self, timeout_s: float = 5.0) -> None:
        """Start listening; TransportError if it cannot."""
        self._thread.start()
        if not self._started.wait(timeout_s) or self._error is not None:
            raise TransportError(
                f"cannot serve Modbus on {self.where}: {self._error}"
            ) from self._error

    def stop(self) -> None:
        """Stop serving and close every connection."""
        if self._thread.is_alive() and self._server is not None:
            asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(5.0)
            self._thread.join(5.0)


class ModbusRtuUnitServer(ModbusUnitServer):
    """Serve a unit over Modbus RTU on a new pty; a client opens :attr:`port` (e.g. /dev/pts/7).

    The line's master is one host; it controls the unit once it writes, until it
    has been silent for :data:`SERIAL_MASTER_GONE_S`.
    """

    def __init__(
        self,
        unit: SimUnit,
        device_id: int = 1,
        baudrate: int = 115200,
        controlling_host: ControllingHost | None = None,
    ) -> None:
        self.pair = PtyPair("modbus-rtu")
        super().__init__(unit, "", 0, device_id, controlling_host)
        self.baudrate = baudrate
        #: the pty a client opens (``port`` is the TCP port of the base class, unused here)
        self.serial_port = self.pair.client_port
        self.where = self.serial_port

    def _build(self) -> ModbusTcpServer | ModbusSerialServer:
        device = unit_device(self.unit, self.controlling_host, self.device_id)
        return _SerialServer(
            self.controlling_host, device, port=self.pair.server_port, baudrate=self.baudrate
        )

    def start(self, timeout_s: float = 5.0) -> None:
        self.pair.start()
        super().start(timeout_s)

    def stop(self) -> None:
        super().stop()
        self.pair.stop()
