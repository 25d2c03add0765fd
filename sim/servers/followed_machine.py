"""The virtual world's machine moved by another CNC: the receiver follows its position.

:class:`FollowedMachine` reads another ``MachinePositionSource`` (e.g. the
position file a real LinuxCNC keeps up to date) in a background thread and
gives its latest position to the simulated interferometer, whose receiver the
virtual machine carries. The world's CNC is then that controller itself: the
simulator is one more listener on it, as a machine's scales are.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from xmalign.errors import XmalignError
from xmalign.geometry import Vec
from xmalign.roles import MachinePositionSource

logger = logging.getLogger(__name__)

#: How often the controller's position is read, s.
FOLLOW_PERIOD_S = 0.01
#: The position unchanged for this long is a standstill, s.
STILL_S = 0.05


class FollowedMachine:
    """``MachinePositionSource``: the last position read from ``source`` (read every period).

    A read that fails is logged and tried again at the next period; the
    position stays where it was last read. Standstill: the position read has
    not changed for ``STILL_S`` (only the follower's thread talks to ``source``).
    """

    def __init__(self, source: MachinePositionSource, period_s: float = FOLLOW_PERIOD_S) -> None:
        self.source = source
        self.period_s = period_s
        self._position_mm = np.asarray(source.position_mm(), dtype=float)
        self._changed_s = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._follow, name="follow-cnc", daemon=True)

    def position_mm(self) -> Vec:
        return self._position_mm.copy()

    def is_standstill(self) -> bool:
        return time.monotonic() - self._changed_s >= STILL_S

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def _follow(self) -> None:
        failing = False
        while not self._stop.wait(self.period_s):
            try:
                position = np.asarray(self.source.position_mm(), dtype=float)
            except XmalignError as error:
                if not failing:
                    logger.warning("cannot read the machine position: %s", error)
                failing = True
                continue
            failing = False
            if not np.array_equal(position, self._position_mm):
                self._changed_s = time.monotonic()
            self._position_mm = position
