"""Machine time of a measurement program from its own moves, feeds and dwells.

Each move starts and ends at rest (exact stop, as the simulated CNC and a
control without look-ahead across a dwell run it): a trapezoidal speed profile
at the programmed feed and the path acceleration; without an acceleration the
feed is reached at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from xmalign.geometry import Vec


def move_time_s(length_mm: float, feed_mm_min: float, accel_mm_s2: float | None) -> float:
    """Duration of one move from rest to rest, s.

    Parameters
    ----------
    length_mm : float
        Path length, mm.
    feed_mm_min : float
        Programmed feed, mm/min (> 0).
    accel_mm_s2 : float or None
        Path acceleration and deceleration, mm/s²; None for an instant feed.
    """
    speed = feed_mm_min / 60.0
    if length_mm <= 0.0:
        return 0.0
    if accel_mm_s2 is None:
        return length_mm / speed
    peak = min(speed, math.sqrt(length_mm * accel_mm_s2))
    ramp_s = peak / accel_mm_s2
    return 2.0 * ramp_s + (length_mm - peak * ramp_s) / peak


@dataclass(frozen=True)
class MachineTime:
    """Machine time of a program, s: moving, dwelling and the total."""

    moving_s: float
    dwell_s: float
    dwells: int
    with_acceleration: bool

    @property
    def total_s(self) -> float:
        return self.moving_s + self.dwell_s


class MachineTimer:
    """Adds up the moves and dwells of a program as it is written.

    Parameters
    ----------
    start_mm : array_like, shape (3,)
        Where the tool point stands when the program starts, mm.
    accel_mm_s2 : float or None
        Path acceleration, mm/s²; None: feeds reached at once.
    """

    def __init__(self, start_mm: Vec, accel_mm_s2: float | None) -> None:
        self.position_mm = np.asarray(start_mm, dtype=float)
        self._accel = accel_mm_s2
        self._moving_s = 0.0
        self._dwell_s = 0.0
        self._dwells = 0

    def move(self, target_mm: Vec, feed_mm_min: float) -> None:
        target = np.asarray(target_mm, dtype=float)
        length = float(np.linalg.norm(target - self.position_mm))
        self._moving_s += move_time_s(length, feed_mm_min, self._accel)
        self.position_mm = target

    def dwell(self, seconds: float) -> None:
        self._dwell_s += seconds
        self._dwells += 1

    def result(self) -> MachineTime:
        return MachineTime(self._moving_s, self._dwell_s, self._dwells, self._accel is not None)
