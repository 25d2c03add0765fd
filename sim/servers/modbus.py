"""A :class:`~sim.units.SimUnit` served over Modbus TCP or Modbus RTU (on a pty) with pymodbus.

The pymodbus register block is only a mirror: every request goes to the unit's
register-level API first (``unit_device``'s action), so reads see the unit's
state at that instant and a refused write answers a Modbus exception:
exception 3 (illegal data value) for an out-of-range value or an undefined
control bit, 2 (illegal data address) for a read-only or unknown register or
one word of a 32-bit value, 6 (server device busy) for a write from a
connection that does not control the unit (docs/registers.md, "One
controlling host"), 1 (illegal function) for any function but 3, 6 and 16.
A serial unit answers its own device id only (never another id, never a
broadcast); the reply to function 6 echoes the request, as the Modbus
specification gives it. Every request is logged on ``sim.servers.modbus`` at
DEBUG.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import threading
import traceback
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import WriteSingleRegisterResponse
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from sim.servers.pty_pair import PtyPair
from sim.units import SimUnit
from xmalign.errors import InputError, OutOfRangeError, TransportError

log = logging.getLogger(__name__)

#: The connection (request handler) whose request is being served.
_connection: contextvars.ContextVar[object] = contextvars.ContextVar("modbus_connection")

#: Read holding registers, write single register, write multiple registers.
SERVED_FUNCTIONS = frozenset({3, 6, 16})
#: The unit ids a unit answers on Modbus TCP besides its own: 0 (the original Modbus
#: TCP value for a device addressed by its IP address) and 255 (the Modbus TCP
#: implementation guide's "not significant"). On a serial line: its own id only.
TCP_DIRECT_IDS = frozenset({0, 255})


class ControllingHost:
    """Which connection controls the unit: the first that writes, until it closes or lapses.

    One per unit, shared by every server of it (TCP and RTU). The owner's
    control lapses once it has neither claimed the unit nor changed the
    heartbeat for the watchdog timeout (500 ms): then the next connection that
    writes takes it over (a host that hung with its socket open, or a serial
    master that went quiet, does not hold the unit for ever).
    """

    def __init__(self) -> None:
        self.owner: object | None = None
        self._claimed_s = 0.0
        self._lock = threading.Lock()

    def may_write(self, connection: object, unit: SimUnit) -> bool:
        """Claim ``unit`` for ``connection`` if free or lapsed; whether it controls the unit."""
        with self._lock:
            if self.owner is not None and self.owner is not connection:
                quiet_s = min(unit.heartbeat_age_s(), unit.clock.now() - self._claimed_s)
                if quiet_s > unit.register_map.watchdog_timeout_s:
                    log.info(
                        "connection %s has not changed the heartbeat for %.0f ms: it no"
                        " longer controls the unit",
                        id(self.owner),
                        1000.0 * quiet_s,
                    )
                    self.owner = None
            if self.owner is None:
                self.owner = connection
                self._claimed_s = unit.clock.now()
                log.info("connection %s now controls the unit", id(connection))
            return self.owner is connection

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
        if set_values and not host.may_write(connection, unit):
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


class _Refused(ModbusPDU):
    """A request the unit cannot serve: answered with ``exception`` for its function code."""

    def __init__(self, function_code: int, exception: ExcCodes) -> None:
        super().__init__()
        self.function_code = function_code
        self.exception = exception


class _Decoder:
    """pymodbus's request decoder, but a function other than 3, 6, 16 is refused
    with exception 1 and a malformed request (e.g. a count outside 1..125) with 3,
    each under its own function code (pymodbus answers function 0 with exception 1)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def __getattr__(self, name: str) -> Any:  # the framers also look up frame sizes
        return getattr(self.inner, name)

    def decode(self, frame: bytes) -> ModbusPDU:
        function_code = int(frame[0]) & 0x7F
        if int(frame[0]) not in SERVED_FUNCTIONS:
            return _Refused(function_code, ExcCodes.ILLEGAL_FUNCTION)
        pdu = self.inner.decode(frame)
        return pdu if pdu is not None else _Refused(function_code, ExcCodes.ILLEGAL_VALUE)


class _Handler(ServerRequestHandler):
    """A connection: serves its requests as itself and frees the unit when it closes.

    Requests for another device id are not served: on a serial line (``serial``)
    they, and broadcasts (id 0), get no reply at all; on TCP, ids 0 and 255 mean
    this unit (:data:`TCP_DIRECT_IDS`) and any other id is answered exception 11
    (gateway target device failed to respond).
    """

    def __init__(self, owner: Any, host: ControllingHost, device_id: int, serial: bool) -> None:
        super().__init__(owner, owner.trace_packet, owner.trace_pdu, owner.trace_connect)
        self.framer.decoder = _Decoder(self.framer.decoder)  # type: ignore[assignment]
        self.host = host
        self.device_id = device_id
        self.serial = serial

    async def handle_request(self) -> None:
        request = self.last_pdu
        if request is None:
            return
        _connection.set(self)
        response = await self._answer(request)
        if response is None:
            return
        response.transaction_id = request.transaction_id
        response.dev_id = request.dev_id
        self.server_send(response, self.last_addr)

    def _for_this_unit(self, request: ModbusPDU) -> bool:
        if request.dev_id == self.device_id:
            return True
        return not self.serial and request.dev_id in TCP_DIRECT_IDS

    async def _answer(self, request: ModbusPDU) -> ModbusPDU | None:
        if not self._for_this_unit(request):
            log.debug(
                "fc %d for device id %d, not %d: %s",
                request.function_code,
                request.dev_id,
                self.device_id,
                "no reply" if self.serial else "exception 11",
            )
            if self.serial:
                return None
            return ExceptionResponse(request.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
        if isinstance(request, _Refused):
            log.debug("fc %d: exception %d", request.function_code, request.exception)
            return ExceptionResponse(request.function_code, request.exception)
        try:
            response = await request.datastore_update(self.server.context, self.device_id)
        except Exception:  # a fault of the server itself: answered, and logged with its trace
            log.error("fc %d failed: %s", request.function_code, traceback.format_exc())
            return ExceptionResponse(request.function_code, ExcCodes.DEVICE_FAILURE)
        if request.function_code == 6 and not response.isError():
            # the specified reply echoes the request, whatever the register now holds
            return WriteSingleRegisterResponse(address=request.address, registers=request.registers)
        return response

    def callback_disconnected(self, exc: Exception | None) -> None:
        self.host.release(self)
        super().callback_disconnected(exc)


class _TcpServer(ModbusTcpServer):
    def __init__(self, host: ControllingHost, device_id: int, *args: Any, **kwargs: Any) -> None:
        self.host = host
        self.device_id = device_id
        super().__init__(*args, **kwargs)

    def callback_new_connection(self) -> _Handler:
        return _Handler(self, self.host, self.device_id, serial=False)


class _SerialServer(ModbusSerialServer):
    def __init__(self, host: ControllingHost, device_id: int, *args: Any, **kwargs: Any) -> None:
        self.host = host
        self.device_id = device_id
        super().__init__(*args, **kwargs)

    def callback_new_connection(self) -> _Handler:
        return _Handler(self, self.host, self.device_id, serial=True)


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
        return _TcpServer(
            self.controlling_host, self.device_id, device, address=(self.host, self.port)
        )

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

    The line's master is one host; it controls the unit once it writes, until its
    heartbeat has been stale for the watchdog timeout (:class:`ControllingHost`).
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
            self.controlling_host,
            self.device_id,
            device,
            port=self.pair.server_port,
            baudrate=self.baudrate,
        )

    def start(self, timeout_s: float = 5.0) -> None:
        self.pair.start()
        super().start(timeout_s)

    def stop(self) -> None:
        super().stop()
        self.pair.stop()
