"""What a driven positioning unit does with all its axes at once (shared by the drivers)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from firmware_iface.register_map import load_register_map
from xmalign.errors import DriveFaultError, HeartbeatError
from xmalign.geometry import Vec
from xmalign.roles import Clock, move_axes

#: Fault code of the heartbeat watchdog (registers.yaml, docs/registers.md).
HEARTBEAT_FAULT = 4


def axis_fault(label: str, code: int) -> DriveFaultError:
    """The error every unit implementation raises for fault ``code`` of the axis ``label``.

    Fault 4 is a :class:`HeartbeatError` (a DriveFaultError: the unit stopped and
    locked its axes because the host heartbeat went stale), any other a DriveFaultError.
    """
    text = load_register_map().fault_text(code)
    if code == HEARTBEAT_FAULT:
        return HeartbeatError(f"{label} stopped: {text} (the host heartbeat went stale)")
    return DriveFaultError(f"{label} reports fault {code}: {text}")


class AxisGroup:
    """Unit operations over ``_axes``; a driver sets ``device_name`` and ``_axes``.

    Each axis offers ``position_rad``, ``enable``, ``reset_fault``, ``fault_code``,
    ``move_to``, ``wait_in_position`` and ``lock``.
    """

    device_name: str
    clock: Clock
    _axes: tuple[Any, ...]

    @property
    def axes(self) -> tuple[Any, ...]:
        return self._axes

    def angles_rad(self) -> Vec:
        return np.array([axis.position_rad() for axis in self._axes])

    def enable(self) -> None:
        for axis in self._axes:
            axis.enable()

    def reset_faults(self) -> None:
        for axis in self._axes:
            axis.reset_fault()

    def clear_heartbeat_faults(self) -> None:
        """Reset the heartbeat fault (4) left from power-on or an earlier host; axes stay locked."""
        for axis in self._axes:
            if axis.fault_code() == HEARTBEAT_FAULT:
                axis.reset_fault()

    def move_to(self, angles_rad: ArrayLike, timeout_s: float) -> None:
        """Move every axis and wait; ``timeout_s`` is one deadline for the whole move."""
        angles = np.asarray(angles_rad, dtype=float)
        move_axes(self._axes, angles, timeout_s, self.device_name, self.clock)

    def lock(self) -> None:
        for axis in self._axes:
            axis.lock()
