import cli_helpers
import numpy as np
import pytest

from xmalign.machine import default_machine_path, load_machine


@pytest.fixture
def machine():
    return load_machine(default_machine_path())


@pytest.fixture
def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on."""
    return cli_helpers.free_port()


class StandingCnc:
    """A CNC that stands where the test puts it."""

    def __init__(self, position_mm):
        self.position = np.asarray(position_mm, dtype=float)

    def position_mm(self):
        return self.position.copy()

    def is_standstill(self):
        return True
