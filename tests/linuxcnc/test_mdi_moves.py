"""MDI moves of ``identify --live`` (``allow_mdi_moves: true``) on a real headless LinuxCNC.

LinuxCNC 2.9 (Debian ``linuxcnc-uspace``) runs with ``linuxcncrsh`` as its display
(tests/linuxcnc/harness.py); the test brings the machine up over a session of its
own (E-stop reset, machine on, home), then :class:`~firmware_iface.linuxcncrsh.MdiMover`
moves it with ``set mode mdi`` and ``set mdi G21 G90 G94 G53 G1 ...`` (``man linuxcncrsh``).
LinuxCNC's travel (X 0..400, Y 0..300, Z -200..0) is smaller than the machine
file's, so a target inside the file's travel can lie beyond LinuxCNC's soft limits:
LinuxCNC refuses it, and the move stops with LinuxCNC's own message (seen: ``LinuxCNC
at 127.0.0.1:P did not move to [600.0, 100.0, -50.0] mm (Linear move on line 0 would
exceed X's positive limit); the machine is at [10.0, 250.0, -5.0] mm``).

The same runs on a machine whose [TRAJ] LINEAR_UNITS are inches (the harness
writes every length of the INI in inches): linuxcncrsh reports ``abs_act_pos``
in inches (``set linear_unit_conversion mm`` does not change that, seen with
2.9), the driver converts, and the MDI line's own ``G21`` keeps a target in mm
(without it, X 10 would be 10 inch). A Ctrl-C while the machine moves aborts the move.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import free_port
from harness import SimMachine, bring_up, linuxcnc_serving, write_sim_config

from firmware_iface.linuxcnc_control import MdiMover
from firmware_iface.linuxcncrsh import LinuxCnc, open_linuxcnc
from xmalign.errors import DeviceError
from xmalign.machine import Machine
from xmalign.roles import WallClock

pytestmark = pytest.mark.linuxcnc


@pytest.fixture(params=["mm", "inch"])
def linuxcnc(linuxcnc_dir: Path, request: pytest.FixtureRequest) -> Iterator[LinuxCnc]:
    port = free_port()
    cnc = SimMachine(
        max_velocity_mm_s=200.0, max_acceleration_mm_s2=2000.0, linear_units=request.param
    )
    ini = write_sim_config(linuxcnc_dir / "cnc", cnc, f"linuxcncrsh --port {port}")
    with linuxcnc_serving(ini, port):
        client = open_linuxcnc("127.0.0.1", port, 5.0)
        try:
            bring_up(client)
            yield client
        finally:
            client.close()


def test_mdi_moves_reach_each_point_and_linuxcnc_limits_stay(
    linuxcnc: LinuxCnc, reference_machine: Machine
) -> None:
    mover = MdiMover(linuxcnc, reference_machine, 0.005, 60.0)
    for target in ([150.0, 100.0, -50.0], [320.0, 40.0, -150.0], [10.0, 250.0, -5.0]):
        mover.move_to(np.array(target), 6000.0)
        assert np.linalg.norm(linuxcnc.position_mm() - target) <= 0.005
        assert linuxcnc.program_state() == "idle" and linuxcnc.is_standstill()
    # inside the machine file's travel, beyond LinuxCNC's soft limit on X (400 mm)
    with pytest.raises(DeviceError, match=r"did not move to \[600.0, 100.0, -50.0\] mm \(.+\)"):
        mover.move_to(np.array([600.0, 100.0, -50.0]), 6000.0)
    assert np.linalg.norm(linuxcnc.position_mm() - [10.0, 250.0, -5.0]) <= 0.005


def test_positions_are_in_mm_on_an_inch_machine_too(linuxcnc: LinuxCnc) -> None:
    units = linuxcnc._get("user_linear_units")[0]
    assert linuxcnc.mm_per_unit == {"MM": 1.0, "INCH": 25.4}[units]
    raw = [float(word) for word in linuxcnc._get("abs_act_pos")[:3]]
    linuxcnc._set("linear_unit_conversion mm")  # converts offsets only, not abs_act_pos
    assert [float(word) for word in linuxcnc._get("abs_act_pos")[:3]] == raw
    assert np.allclose(linuxcnc.position_mm(), np.array(raw) * linuxcnc.mm_per_unit)


class _CtrlC(WallClock):
    """Ctrl-C during the first wait for the machine (the MDI wait's 0.05 s)."""

    def sleep(self, seconds: float) -> None:
        if seconds >= 0.05:
            raise KeyboardInterrupt
        super().sleep(seconds)


def test_ctrl_c_during_an_mdi_move_aborts_it(
    linuxcnc: LinuxCnc, reference_machine: Machine
) -> None:
    mover = MdiMover(linuxcnc, reference_machine, 0.005, 60.0)
    linuxcnc.clock = _CtrlC()
    with pytest.raises(KeyboardInterrupt):
        mover.move_to(np.array([390.0, 290.0, -190.0]), 600.0)  # 10 mm/s: ~55 s to go
    linuxcnc.clock = WallClock()
    deadline = time.monotonic() + 5.0
    while not (linuxcnc.program_state() == "idle" and linuxcnc.is_standstill()):
        assert time.monotonic() < deadline, "the machine still moves after the abort"
        time.sleep(0.05)
    stopped_at = linuxcnc.position_mm()
    time.sleep(0.5)
    assert np.allclose(linuxcnc.position_mm(), stopped_at, atol=1e-6)
    assert np.linalg.norm(stopped_at - [390.0, 290.0, -190.0]) > 300.0
