"""sim.position_publisher: the position file the simulated instruments follow, and its end.

The real LinuxCNC case (the publisher ends by itself when LinuxCNC stops) runs in
tests/linuxcnc/test_no_one_at_the_machine.py.
"""

from __future__ import annotations

import threading

import numpy as np

from firmware_iface.machine_position import FilePositions
from sim.position_publisher import publish_positions
from xmalign.errors import TransportError


class _Controller:
    """Moves 1 mm in X a read, then stops answering (the controller shut down)."""

    def __init__(self, reads: int) -> None:
        self.left = reads
        self.x = 0.0

    def position_mm(self) -> np.ndarray:
        if self.left == 0:
            raise TransportError("LinuxCNC on this computer could not be read; is it running?")
        self.left -= 1
        self.x += 1.0
        return np.array([self.x, 2.0, -3.0])

    def is_standstill(self) -> bool:
        return False


def test_the_file_follows_the_controller_and_publishing_ends_with_it(tmp_path) -> None:
    path = tmp_path / "position.txt"
    reason = publish_positions(_Controller(5), path, threading.Event(), 0.001)
    assert "could not be read" in reason
    assert path.read_text() == "5.000000 2.000000 -3.000000\n"
    np.testing.assert_allclose(FilePositions(path).position_mm(), [5.0, 2.0, -3.0])
    assert not (tmp_path / "position.txt.part").exists()


def test_publishing_stops_when_told(tmp_path) -> None:
    stop = threading.Event()
    stop.set()
    assert publish_positions(_Controller(5), tmp_path / "p.txt", stop) == "stopped"
