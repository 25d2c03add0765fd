"""A machine followed through its MTConnect agent (HTTP, read-only; docs/hardware.md).

Two layers, as for every device:

* :class:`AgentLink` sends one HTTP GET to the agent (standard library
  ``urllib``) with a timeout and logs each request and the size of its answer.
* :class:`MTConnectMachine` reads the agent's documents: ``/probe`` once, to
  find the data items, then ``/current`` on every call. It is a
  ``MachinePositionSource`` (:mod:`xmalign.roles`) and reports the program
  state; it never writes anything (MTConnect is read-only).

Which data items (MTConnect Part 2, Devices; Part 3, Streams):

* position: per linear axis (a ``Linear`` component named ``X``, ``Y``, ``Z``
  or as configured), the ``DataItem`` of ``type="POSITION"``, ``subType="ACTUAL"``
  in machine coordinates: ``coordinateSystem="MACHINE"`` (version 1.1 on), or
  ``coordinateSystemIdRef`` naming a ``CoordinateSystem`` of ``type="MACHINE"``
  (2.0 on), or no coordinate system at all (version 1.0 documents have none;
  taken as machine coordinates). ``WORK`` positions are never used.
  Values are converted to mm from the item's ``units`` (what the agent
  reports), or ``nativeUnits`` when the agent declares no ``units`` (it then
  passes the controller's values on unconverted): ``MILLIMETER``, ``INCH``, ``FOOT``.
* program state: the ``EXECUTION`` event (READY, ACTIVE, INTERRUPTED,
  FEED_HOLD, STOPPED, OPTIONAL_STOP, PROGRAM_STOPPED, PROGRAM_COMPLETED, WAIT);
  operating mode: ``CONTROLLER_MODE``. The first of each in the device is used.
* the program: the ``PROGRAM`` event ("the identity of the logic or motion
  program being executed"), the one of ``subType="MAIN"`` first, then one
  without a subType, then ``ACTIVE`` (never ``SCHEDULE``). A device without
  one, or one reporting it ``UNAVAILABLE``, does not report its program.

Standstill: the positions read on successive calls stayed within
``standstill_tolerance_mm`` for ``settle_s`` of xmalign's clock
(:class:`StandstillWindow`; adapters that repeat unchanged or jittering values
pass too). The observations' timestamps are not used for it: they are the
adapter's clock (cppagent keeps the timestamp an adapter sends) and the
document's ``creationTime`` the agent's, so an adapter whose clock runs behind
would make a moving machine look settled.
"""

from __future__ import annotations

import http.client
import logging
import math
import socket
import urllib.error
import urllib.parse
import urllib.request
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from firmware_iface.controller_status import ControllerStatus
from firmware_iface.standstill import StandstillWindow
from xmalign.errors import DeviceError, DeviceTimeoutError, TransportError
from xmalign.geometry import Vec
from xmalign.roles import Clock, ClosesOnExit, ProgramReport, ProgramState, WallClock

log = logging.getLogger(__name__)

#: mm per unit of the MTConnect vocabulary (units and nativeUnits of a POSITION).
MM_PER_UNIT = {"MILLIMETER": 1.0, "INCH": 25.4, "FOOT": 304.8}

#: MTConnect Execution values (Part 3) as program states.
EXECUTION_STATES: dict[str, ProgramState] = {
    "READY": "idle",
    "STOPPED": "idle",
    "PROGRAM_COMPLETED": "idle",
    "ACTIVE": "running",
    "WAIT": "running",
    "INTERRUPTED": "paused",
    "FEED_HOLD": "paused",
    "OPTIONAL_STOP": "paused",
    "PROGRAM_STOPPED": "paused",
}
UNAVAILABLE = "UNAVAILABLE"
#: Which PROGRAM data item names the program the machine runs, best first.
PROGRAM_SUBTYPES = ("MAIN", None, "ACTIVE")


class AgentTransport(Protocol):
    """What the driver needs of the HTTP side (:class:`AgentLink`, or a test double)."""

    name: str

    def get(self, path: str) -> tuple[int, bytes]:
        """GET ``path`` (relative to the agent's address): the HTTP status and the body."""
        ...

    def close(self) -> None:
        """Release the connection, if the transport keeps one."""
        ...


class AgentLink:
    """HTTP GETs to one MTConnect agent.

    Parameters
    ----------
    url : str
        The agent's base address, e.g. ``http://192.168.10.30:5000``.
    timeout_s : float
        Largest wait for the connection and for each read of the answer.
    """

    def __init__(self, url: str, timeout_s: float) -> None:
        self.url = url.rstrip("/")
        self.timeout_s = timeout_s
        self.name = f"the MTConnect agent at {self.url}"

    def get(self, path: str) -> tuple[int, bytes]:
        """GET ``path`` (relative to the base address); the HTTP status and the body."""
        url = f"{self.url}/{path}"
        log.debug("%s > GET %s", self.name, url)
        try:
            with urllib.request.urlopen(url, timeout=self.timeout_s) as reply:
                status, body = int(reply.status), reply.read()
        except urllib.error.HTTPError as error:  # an MTConnectError document comes with it
            status, body = error.code, error.read()
        except TimeoutError as error:
            raise DeviceTimeoutError(
                f"{self.name} did not answer {path} within {self.timeout_s:g} s"
            ) from error
        except urllib.error.URLError as error:
            if isinstance(error.reason, TimeoutError | socket.timeout):
                raise DeviceTimeoutError(
                    f"{self.name} did not answer {path} within {self.timeout_s:g} s"
                ) from error
            raise TransportError(f"cannot reach {self.name} ({error.reason})") from error
        except (http.client.HTTPException, OSError) as error:
            raise TransportError(f"lost the connection to {self.name} ({error!r})") from error
        log.debug("%s < HTTP %d, %d bytes", self.name, status, len(body))
        return status, body

    def close(self) -> None:
        """Nothing to release: every request opens and closes its own connection."""


@dataclass(frozen=True)
class _Item:
    """A data item found in /probe."""

    id: str
    mm_per_unit: float = 1.0


def _local(tag: str) -> str:
    """An element's name without its namespace (MTConnect versions differ in namespace)."""
    return tag.rsplit("}", 1)[-1]


class MTConnectMachine(ClosesOnExit):
    """The machine as its MTConnect agent reports it (``MachinePositionSource``, read-only).

    Parameters
    ----------
    link : AgentTransport
        Usually an :class:`AgentLink`.
    device : str, optional
        The ``Device`` name or uuid; needed when the agent serves several.
    axes : sequence of 3 str
        Names of the ``Linear`` components giving x, y, z of the plan.
    clock : Clock, optional
        For the standstill window (default the wall clock).
    settle_s, standstill_tolerance_mm : float
        Standstill: position unchanged within the tolerance for the settle time.
    """

    def __init__(
        self,
        link: AgentTransport,
        device: str | None = None,
        axes: Sequence[str] = ("X", "Y", "Z"),
        clock: Clock | None = None,
        settle_s: float = 0.2,
        standstill_tolerance_mm: float = 0.002,
    ) -> None:
        if len(axes) != 3:
            raise ValueError("axes: expected three names (x, y, z)")
        self.link = link
        self.device = device
        self.axes = tuple(axes)
        self.settle_s = settle_s
        self._window = StandstillWindow(clock or WallClock(), settle_s, standstill_tolerance_mm)
        self._positions: tuple[_Item, ...] = ()
        self._execution: _Item | None = None
        self._mode: _Item | None = None
        self._program: _Item | None = None
        where = f" (device {device})" if device else ""
        self.name = f"{link.name}{where}"

    # -- opening ---------------------------------------------------------------
    def open(self) -> MTConnectMachine:
        """Read ``/probe`` and find the data items; DeviceError when an axis is missing."""
        device = self._device(self._document("probe", "MTConnectDevices"))
        self._positions = tuple(self._position_item(device, axis) for axis in self.axes)
        self._execution = self._first_item(device, "EXECUTION")
        self._mode = self._first_item(device, "CONTROLLER_MODE")
        self._program = _program_item(device)
        self._window.reset()
        return self

    def close(self) -> None:
        """Close the transport."""
        self.link.close()

    def __enter__(self) -> MTConnectMachine:
        return self if self._positions else self.open()

    # -- the role ----------------------------------------------------------------
    def position_mm(self) -> Vec:
        """Actual position in machine coordinates, shape (3,), mm."""
        return self._position(self._current())

    def is_standstill(self) -> bool:
        """The position stayed within the tolerance for the settle time (module docstring)."""
        return self._window.add(self.position_mm())

    def program_state(self) -> ProgramState:
        """``idle``, ``running`` or ``paused`` from the device's ``Execution``."""
        return self.status().program_state

    def status(self) -> ControllerStatus:
        """Position, program state and mode from one ``/current`` document."""
        return self._status(self._current())

    def program_report(self) -> ProgramReport | None:
        """The ``Program`` and its state from one ``/current``; None when the device has no
        PROGRAM data item or reports it UNAVAILABLE. Without an Execution to tell, the
        program counts as running (it is then always compared)."""
        if self._program is None:
            return None
        current = self._current()
        name = current.get(self._program.id, UNAVAILABLE)
        if name == UNAVAILABLE:
            return None
        execution = None if self._execution is None else current.get(self._execution.id)
        state = EXECUTION_STATES.get(execution, "running") if execution else "running"
        return ProgramReport(name or None, state)

    def _status(self, current: dict[str, str]) -> ControllerStatus:
        position = self._position(current)
        if self._execution is None:
            raise DeviceError(f"{self.name} reports no Execution (no EXECUTION data item)")
        execution = self._value(current, self._execution, "Execution")
        if execution not in EXECUTION_STATES:
            raise DeviceError(f"{self.name} reports an unknown Execution '{execution}'")
        mode = None if self._mode is None else current.get(self._mode.id)
        return ControllerStatus(position, EXECUTION_STATES[execution], execution, mode)

    # -- documents ---------------------------------------------------------------
    def _path(self, request: str) -> str:
        if self.device is None:
            return request
        return f"{urllib.parse.quote(self.device, safe='')}/{request}"

    def _document(self, request: str, root_name: str) -> ET.Element:
        status, body = self.link.get(self._path(request))
        try:
            root = ET.fromstring(body)
        except ET.ParseError as error:
            line, column = error.position
            raise TransportError(
                f"{self.name} sent a damaged /{request} document"
                f" (not XML at line {line}, column {column})"
            ) from error
        except (LookupError, ValueError) as error:  # e.g. a damaged encoding declaration
            raise TransportError(
                f"{self.name} sent a damaged /{request} document ({error})"
            ) from error
        if _local(root.tag) == "MTConnectError":
            errors = [
                f"{e.get('errorCode', '?')}: {(e.text or '').strip()}"
                for e in root.iter()
                if _local(e.tag) == "Error"
            ]
            raise DeviceError(f"{self.name} refused /{request}: {'; '.join(errors) or 'error'}")
        if status != 200:
            raise TransportError(f"{self.name} answered /{request} with HTTP {status}")
        if _local(root.tag) != root_name:
            raise TransportError(
                f"{self.name} answered /{request} with <{_local(root.tag)}>, not <{root_name}>"
            )
        return root

    def _device(self, probe: ET.Element) -> ET.Element:
        devices = [e for e in probe.iter() if _local(e.tag) == "Device"]
        if self.device is not None:
            devices = [d for d in devices if self.device in (d.get("name"), d.get("uuid"))]
        if len(devices) != 1:
            names = ", ".join(str(d.get("name")) for d in probe.iter() if _local(d.tag) == "Device")
            wanted = f"device '{self.device}'" if self.device else "one device"
            raise DeviceError(f"{self.name}: expected {wanted}, the agent has: {names or 'none'}")
        return devices[0]

    def _position_item(self, device: ET.Element, axis: str) -> _Item:
        machine_frames = {
            e.get("id")
            for e in device.iter()
            if _local(e.tag) == "CoordinateSystem" and e.get("type") == "MACHINE"
        }
        candidates: list[tuple[int, ET.Element]] = []
        for component in device.iter():
            if _local(component.tag) != "Linear" or (component.get("name") or "").upper() != (
                axis.upper()
            ):
                continue
            for item in component.iter():
                if (
                    _local(item.tag) == "DataItem"
                    and item.get("type") == "POSITION"
                    and item.get("category", "SAMPLE") == "SAMPLE"
                    and item.get("subType", "ACTUAL") == "ACTUAL"
                ):
                    rank = _machine_rank(item, machine_frames)
                    if rank is not None:
                        candidates.append((rank, item))
        if not candidates:
            raise DeviceError(
                f"{self.name} has no actual machine POSITION of a linear axis {axis}"
                f" (linear axes: {', '.join(_linear_names(device)) or 'none'})"
            )
        item = min(candidates, key=lambda c: c[0])[1]
        unit = item.get("units") or item.get("nativeUnits")
        if unit not in MM_PER_UNIT:
            raise DeviceError(
                f"{self.name}: the {axis} position {item.get('id')} is in"
                f" {unit or 'no declared unit'} (expected one of {', '.join(MM_PER_UNIT)})"
            )
        return _Item(str(item.get("id")), MM_PER_UNIT[unit])

    @staticmethod
    def _first_item(device: ET.Element, kind: str) -> _Item | None:
        for item in device.iter():
            if _local(item.tag) == "DataItem" and item.get("type") == kind:
                return _Item(str(item.get("id")))
        return None

    def _current(self) -> dict[str, str]:
        """``dataItemId -> value`` of the ``/current`` document."""
        root = self._document("current", "MTConnectStreams")
        return {
            str(element.get("dataItemId")): (element.text or "").strip()
            for element in root.iter()
            if element.get("dataItemId") is not None
        }

    def _value(self, current: dict[str, str], item: _Item, what: str) -> str:
        if item.id not in current:
            raise DeviceError(f"{self.name}: /current has no {what} (data item {item.id})")
        value = current[item.id]
        if value == UNAVAILABLE:
            raise DeviceError(f"{self.name} reports the {what} UNAVAILABLE (controller offline?)")
        return value

    def _position(self, current: dict[str, str]) -> Vec:
        values = []
        for axis, item in zip(self.axes, self._positions, strict=True):
            text = self._value(current, item, f"{axis} position")
            try:
                value = float(text)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                raise DeviceError(f"{self.name}: the {axis} position '{text}' is not a number")
            values.append(value * item.mm_per_unit)
        position = np.array(values)
        log.debug("%s: machine position %s mm", self.name, np.array2string(position))
        return position


def _machine_rank(item: ET.Element, machine_frames: set[str | None]) -> int | None:
    """0 for an explicit machine position, 1 for one without a frame, None for another frame."""
    reference = item.get("coordinateSystemIdRef")
    if reference is not None:
        return 0 if reference in machine_frames else None
    frame = item.get("coordinateSystem")
    if frame is None:
        return 1
    return 0 if frame == "MACHINE" else None


def _program_item(device: ET.Element) -> _Item | None:
    """The PROGRAM data item naming the program the machine runs (:data:`PROGRAM_SUBTYPES`)."""
    items = [
        item
        for item in device.iter()
        if _local(item.tag) == "DataItem"
        and item.get("type") == "PROGRAM"
        and item.get("subType") in PROGRAM_SUBTYPES
    ]
    if not items:
        return None
    best = min(items, key=lambda item: PROGRAM_SUBTYPES.index(item.get("subType")))
    return _Item(str(best.get("id")))


def _linear_names(device: ET.Element) -> list[str]:
    return [str(e.get("name")) for e in device.iter() if _local(e.tag) == "Linear"]


def open_mtconnect(
    url: str,
    timeout_s: float,
    device: str | None = None,
    axes: Sequence[str] = ("X", "Y", "Z"),
    settle_s: float = 0.2,
    standstill_tolerance_mm: float = 0.002,
    clock: Clock | None = None,
) -> MTConnectMachine:
    """Connect to an agent and read its ``/probe`` (one line naming the agent on failure)."""
    machine = MTConnectMachine(
        AgentLink(url, timeout_s), device, axes, clock, settle_s, standstill_tolerance_mm
    )
    return machine.open()
