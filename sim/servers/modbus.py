"""A :class:`~sim.units.SimUnit` served over Modbus TCP with pymodbus.

The pymodbus register block is only a mirror: every request goes to the unit's
register-level API first (``SimDevice.action``), so reads see the unit's state
at that instant and a refused write answers a Modbus exception: exception 3
(illegal data value) for an out-of-range value, 2 (illegal data address) for a
read-only or unknown register.
"""

from __future__ import annotations

import asyncio
import threading

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from sim.units import SimUnit
from xmalign.errors import InputError, OutOfRangeError, TransportError


def unit_device(unit: SimUnit, device_id: int = 1) -> SimDevice:
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
        try:
            if set_values:
                unit.write_registers(address, [int(v) for v in set_values])
            current_registers[:] = unit.read_registers(start_address, register_count)
        except OutOfRangeError:
            return ExcCodes.ILLEGAL_VALUE
        except InputError:
            return ExcCodes.ILLEGAL_ADDRESS
        return None

    registers = SimData(0, count=register_count, values=0, datatype=DataType.REGISTERS)
    return SimDevice(id=device_id, simdata=[registers], action=action)


class ModbusUnitServer:
    """Serve a unit on ``host:port`` from a background thread (``start``/``stop``).

    Parameters
    ----------
    unit : SimUnit
        Should run on a real-time clock.
    host, port : str, int
    device_id : int
        The Modbus unit id the unit answers to (0 answers every id).
    """

    def __init__(self, unit: SimUnit, host: str, port: int, device_id: int = 1) -> None:
        self.unit = unit
        self.host = host
        self.port = port
        self.device_id = device_id
        self._server: ModbusTcpServer | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name=f"modbus-{unit.kind}", daemon=True)
        self._started = threading.Event()
        self._error: BaseException | None = None

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._serve())
        except BaseException as error:  # reported to the thread that called start()
            self._error = error
            self._started.set()

    async def _serve(self) -> None:
        # built inside the loop: pymodbus binds its futures to the running loop
        self._server = ModbusTcpServer(
            unit_device(self.unit, self.device_id), address=(self.host, self.port)
        )
        if not await self._server.listen():
            raise OSError(f"cannot listen on {self.host}:{self.port}")
        self._started.set()
        await self._server.serving

    def start(self, timeout_s: float = 5.0) -> None:
        """Start listening; TransportError if the port cannot be bound."""
        self._thread.start()
        if not self._started.wait(timeout_s) or self._error is not None:
            raise TransportError(
                f"cannot serve Modbus on {self.host}:{self.port}: {self._error}"
            ) from self._error

    def stop(self) -> None:
        """Stop serving and close every connection."""
        if self._thread.is_alive() and self._server is not None:
            asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(5.0)
            self._thread.join(5.0)
