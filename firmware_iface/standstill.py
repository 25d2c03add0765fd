"""Standstill from a stream of positions: unchanged within a tolerance over a settle time.

Controllers that only report positions (an MTConnect agent, a Sinumerik's OPC UA
server) say nothing reliable about "in position": a program dwelling at a point
is still *running*, and a path feedrate of zero is reported late or not at all
by many adapters. :class:`StandstillWindow` decides from the positions
themselves: the machine stands still once every position seen over the last
``settle_s`` (on the given clock) lies within ``tolerance_mm`` of the newest.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import ArrayLike

from xmalign.geometry import Vec
from xmalign.roles import Clock


class StandstillWindow:
    """Positions of the last ``settle_s`` seconds; standstill when they all agree.

    Parameters
    ----------
    clock : Clock
        Time of each sample (the wall clock for hardware).
    settle_s : float
        How long the position must stay put, s (> 0).
    tolerance_mm : float
        Largest distance of any sample in the window from the newest one, mm.
    """

    def __init__(self, clock: Clock, settle_s: float, tolerance_mm: float) -> None:
        if settle_s <= 0 or tolerance_mm <= 0:
            raise ValueError("settle_s and tolerance_mm must be positive")
        self.clock = clock
        self.settle_s = settle_s
        self.tolerance_mm = tolerance_mm
        self._samples: deque[tuple[float, Vec]] = deque()

    def add(self, position_mm: ArrayLike) -> bool:
        """Record a position read now; True when the machine has stood still for ``settle_s``."""
        now = self.clock.now()
        newest = np.asarray(position_mm, dtype=float)
        moved = any(np.linalg.norm(p - newest) > self.tolerance_mm for _, p in self._samples)
        if moved:
            self._samples.clear()
        self._samples.append((now, newest))
        # keep one sample at or before the window's start: it proves the window is covered
        while len(self._samples) > 1 and self._samples[1][0] <= now - self.settle_s:
            self._samples.popleft()
        return self._samples[0][0] <= now - self.settle_s

    def reset(self) -> None:
        """Forget the samples (after a reconnect: a gap says nothing about standing still)."""
        self._samples.clear()
