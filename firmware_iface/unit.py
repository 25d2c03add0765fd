"""What a driven positioning unit does with all its axes at once (shared by the drivers)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from xmalign.geometry import Vec
from xmalign.roles import move_axes


class AxisGroup:
    """Unit operations over ``_axes``; a driver sets ``device_name`` and ``_axes``.

    Each axis offers ``position_rad``, ``enable``, ``reset_fault``, ``move_to``,
    ``wait_in_position`` and ``lock``.
    """

    device_name: str
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

    def move_to(self, angles_rad: ArrayLike, timeout_s: float) -> None:
        move_axes(self._axes, angles_rad, timeout_s, self.device_name)

    def lock(self) -> None:
        for axis in self._axes:
            axis.lock()
