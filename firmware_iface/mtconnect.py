"""A machine's position and program state read from an MTConnect agent (read-only, HTTP).

MTConnect (ANSI/MTC1.4) agents serve XML over HTTP: ``/probe`` describes the
device (``MTConnectDevices``: components such as ``Linear`` X/Y/Z with their
``DataItem`` elements), ``/current`` gives the latest value of every data item
(``MTConnectStreams``: observations named by element, keyed by
``dataItemId``). :class:`MTConnectAgent` is a ``MachinePositionSource``:

* the position: per ``Linear`` axis X, Y, Z the data item of ``type="POSITION"``,
  ``subType="ACTUAL"`` in machine coordinates (``coordinateSystem="MACHINE"``, or
  none given: machine coordinates are an axis position's default), in
  ``MILLIMETER``; ``UNAVAILABLE`` is refused;
* the program state from ``EXECUTION`` (``ACTIVE`` running; ``INTERRUPTED``,
  ``FEED_HOLD``, ``OPTIONAL_STOP``, ``PROGRAM_STOPPED`` paused; else idle) and the
  ``CONTROLLER_MODE``;
* standstill: the position unchanged over ``STANDSTILL_PROBE_S`` (MTConnect has
  no in-position item; an agent samples at its own rate).

Nothing is ever written: with MTConnect the operator runs the program and xmalign
follows the machine, as with a position file (docs/hardware.md).
"""

from __future__ import annotations

import logging
import urllib.error
import urllib.request
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np

from xmalign.errors import DeviceError, DeviceTimeoutError, TransportError
from xmalign.geometry import Vec
from xmalign.roles import Clock, ProgramState, WallClock

log = logging.getLogger(__name__)

AXES = ("X", "Y", "Z")
#: Time between the two reads of the position that tell a standstill, s.
STANDSTILL_PROBE_S = 0.2
_PAUSED = ("INTERRUPTED", "FEED_HOLD", "OPTIONAL_STOP", "PROGRAM_STOPPED")


def _local(tag: str) -> str:
    """An element's name without its namespace (agents use MTConnectStreams:1.x URNs)."""
    return tag.rsplit("}", 1)[-1]


@dataclass(frozen=True)
class DataItems:
    """The ``dataItemId`` of each item xmalign reads."""

    position: dict[str, str]
    execution: str | None
    controller_mode: str | None


class MTConnectAgent:
    """The device ``device`` (default: the first) of the agent at ``url``."""

    def __init__(
        self,
        url: str,
        timeout_s: float,
        device: str | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.url = url.rstrip("/")
        self.timeout_s = timeout_s
        self.device = device
        self.name = f"MTConnect agent at {self.url}"
        self.clock = clock or WallClock()
        self.items = self._probe()

    def _get(self, request: str) -> ET.Element:
        path = f"/{self.device}/{request}" if self.device else f"/{request}"
        url = self.url + path
        log.debug("%s > GET %s", self.name, path)
        try:
            with urllib.request.urlopen(url, timeout=self.timeout_s) as response:
                body = response.read()
        except TimeoutError as error:
            raise DeviceTimeoutError(
                f"{self.name} did not answer GET {path} within {self.timeout_s:g} s"
            ) from error
        except urllib.error.HTTPError as error:
            raise DeviceError(f"{self.name}: GET {path} answered HTTP {error.code}") from error
        except (urllib.error.URLError, OSError) as error:
            reason = getattr(error, "reason", error)
            raise TransportError(f"cannot reach the {self.name} ({reason})") from error
        log.debug("%s < %d bytes", self.name, len(body))
        try:
            return ET.fromstring(body)
        except ET.ParseError as error:
            raise DeviceError(f"{self.name}: GET {path} is not XML ({error})") from error

    def _device(self, root: ET.Element) -> ET.Element:
        for element in root.iter():
            if _local(element.tag) in ("Device", "DeviceStream") and (
                self.device is None or element.get("name") == self.device
            ):
                return element
        raise DeviceError(f"{self.name}: no device {self.device or ''} in the answer".strip())

    def _probe(self) -> DataItems:
        device = self._device(self._get("probe"))
        position: dict[str, str] = {}
        for component in device.iter():
            name = component.get("name", "").upper()
            if _local(component.tag) != "Linear" or name not in AXES:
                continue
            position[name] = self._position_item(component, name)
        missing = [axis for axis in AXES if axis not in position]
        if missing:
            raise DeviceError(f"{self.name}: no Linear axis {', '.join(missing)} in /probe")
        by_type = {
            item.get("type"): item.get("id", "")
            for item in device.iter()
            if _local(item.tag) == "DataItem"
        }
        return DataItems(position, by_type.get("EXECUTION"), by_type.get("CONTROLLER_MODE"))

    def _position_item(self, axis: ET.Element, name: str) -> str:
        """The id of the axis' actual position in machine coordinates, in mm."""
        for item in axis.iter():
            if (
                _local(item.tag) == "DataItem"
                and item.get("type") == "POSITION"
                and item.get("subType") == "ACTUAL"
                and item.get("coordinateSystem", "MACHINE") == "MACHINE"
            ):
                if item.get("units", "MILLIMETER") != "MILLIMETER":
                    raise DeviceError(f"{self.name}: axis {name} reports {item.get('units')}")
                return item.get("id", "")
        raise DeviceError(
            f"{self.name}: axis {name} has no actual position in machine coordinates"
            " (DataItem type POSITION, subType ACTUAL, coordinateSystem MACHINE)"
        )

    def current(self) -> dict[str, str]:
        """The latest value of every data item of the device, by ``dataItemId``."""
        device = self._device(self._get("current"))
        return {
            element.get("dataItemId", ""): (element.text or "").strip()
            for element in device.iter()
            if element.get("dataItemId")
        }

    def position_mm(self) -> Vec:
        """Actual X Y Z in machine coordinates, mm, shape (3,)."""
        return self._position(self.current())

    def _position(self, values: dict[str, str]) -> Vec:
        texts = [values.get(self.items.position[axis], "UNAVAILABLE") for axis in AXES]
        try:
            return np.array([float(text) for text in texts])
        except ValueError as error:
            raise DeviceError(f"{self.name}: position X Y Z is {' '.join(texts)}") from error

    def is_standstill(self) -> bool:
        before = self.position_mm()
        self.clock.sleep(STANDSTILL_PROBE_S)
        return bool(np.array_equal(before, self.position_mm()))

    def execution(self) -> str:
        """The ``EXECUTION`` value (``UNAVAILABLE`` when the device has none)."""
        if self.items.execution is None:
            return "UNAVAILABLE"
        return self.current().get(self.items.execution, "UNAVAILABLE")

    def program_state(self) -> ProgramState:
        execution = self.execution()
        if execution == "ACTIVE":
            return "running"
        return "paused" if execution in _PAUSED else "idle"

    def controller_mode(self) -> str:
        """The ``CONTROLLER_MODE`` value (``AUTOMATIC``, ``MANUAL``, ...)."""
        if self.items.controller_mode is None:
            return "UNAVAILABLE"
        return self.current().get(self.items.controller_mode, "UNAVAILABLE")
