import socket

import numpy as np
import pytest

from xmalign.machine import default_machine_path, load_machine


@pytest.fixture
def machine():
    return load_machine(default_machine_path())


@pytest.fixture
def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class StandingCnc:
    """A CNC that stands where the test puts it."""

    def __init__(self, position_mm):
        self.position = np.asarray(position_mm, dtype=float)

    def position_mm(self):
        return self.position.copy()

    def is_standstill(self):
        return True
