"""Simulated time: virtual (``sleep`` advances ``now``) or following the wall clock."""

from __future__ import annotations

import threading
import time


class SimClock:
    """The :class:`xmalign.roles.Clock` of the simulator.

    In virtual mode (the default) ``sleep(dt)`` returns at once and advances
    ``now()`` by ``dt``, so hours of simulated calibration take seconds of CPU;
    devices evaluate their state analytically at ``now()``. With
    ``real_time=True`` (served devices) ``now()`` follows the wall clock from
    ``start_s`` on and ``sleep`` really sleeps. Thread-safe.
    """

    def __init__(self, start_s: float = 0.0, real_time: bool = False) -> None:
        self.real_time = real_time
        self._lock = threading.Lock()
        self._now_s = start_s
        self._wall_origin_s = time.monotonic() - start_s

    def now(self) -> float:
        if self.real_time:
            return time.monotonic() - self._wall_origin_s
        with self._lock:
            return self._now_s

    def follow_wall_clock(self) -> None:
        """Go on in real time from the current ``now()`` (a setup prepared in virtual time,
        then served)."""
        with self._lock:
            self._wall_origin_s = time.monotonic() - self._now_s
            self.real_time = True

    def sleep(self, seconds: float) -> None:
        if self.real_time:
            time.sleep(max(0.0, seconds))
            return
        with self._lock:
            self._now_s += max(0.0, seconds)
