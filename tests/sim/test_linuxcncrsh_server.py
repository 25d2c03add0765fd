"""The simulated CNC behind linuxcncrsh's protocol, driven by xmalign's own LinuxCNC driver.

The replies the server gives are those LinuxCNC 2.9 gave in
tests/linuxcnc/test_unattended_run.py (the driver passes against both).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from firmware_iface.config import _mover, load_units_config
from firmware_iface.linuxcnc_control import LinuxCncControl, MdiMover
from firmware_iface.linuxcncrsh import LinuxCnc, open_linuxcnc
from firmware_iface.machine_position import OperatorPrompt
from sim.clock import LockstepClock
from sim.cnc import SimulatedCnc
from sim.servers.linuxcncrsh import LinuxcncrshServer
from xmalign.errors import DeviceError, OutOfRangeError
from xmalign.machine import Machine
from xmalign.roles import ProgramControl, WallClock


@pytest.fixture
def cnc(reference_machine: Machine) -> Iterator[tuple[LinuxCnc, LinuxcncrshServer]]:
    server = LinuxcncrshServer(SimulatedCnc(reference_machine, WallClock()), reference_machine)
    server.start()
    client = open_linuxcnc("127.0.0.1", server.port, 2.0)
    yield client, server
    client.close()
    server.stop()


def _wait(condition, timeout_s: float = 10.0) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def run_through_a_stop_and_a_feed_hold(client: LinuxCncControl, folder: Path) -> Path:
    """Start a program, see it paused at its M0 at rest, resume, hold the feed mid-move (at
    rest where it is), resume, abort: what xmalign's program control does, on any channel
    to a simulated LinuxCNC. Returns the program's path."""
    assert isinstance(client, ProgramControl)
    client.check_ready()
    program = folder / "p.ngc"
    program.write_text("G21 G90\nG53 G1 X100 Y50 Z-10 F6000\nM0\nG53 G1 X300 F600\nM2\n")
    client.start_program(str(program))
    assert client.loaded_program() == str(program)
    _wait(lambda: client.program_state() == "paused")  # the M0
    assert np.allclose(client.position_mm(), [100, 50, -10]) and client.is_standstill()
    client.resume()
    _wait(lambda: client.position_mm()[0] > 110)
    assert not client.is_standstill()
    client.hold()  # feed hold mid-move: the machine stops where it is (as LinuxCNC's status,
    # the program state follows the acknowledged command a moment later)
    _wait(lambda: client.program_state() == "paused" and client.is_standstill())
    held = client.position_mm()
    time.sleep(0.1)
    assert np.array_equal(client.position_mm(), held)
    client.resume()
    _wait(lambda: client.position_mm()[0] > held[0])
    client.stop_program()
    assert client.program_state() == "idle"
    return program


def test_program_with_a_stop_a_feed_hold_and_the_end(cnc, tmp_path: Path) -> None:  # noqa: ANN001
    client, _ = cnc
    run_through_a_stop_and_a_feed_hold(client, tmp_path)


def test_a_program_that_cannot_be_opened_and_a_refused_enable(cnc) -> None:  # noqa: ANN001
    client, server = cnc
    with pytest.raises(DeviceError, match="did not open /nowhere.ngc .Unable to open file"):
        client.start_timeout_s = 0.2
        client.start_program("/nowhere.ngc")
    with pytest.raises(DeviceError, match="refused the enable password"):
        open_linuxcnc("127.0.0.1", server.port, 2.0, enable_password="WRONG")


def test_an_mdi_move_to_a_point_and_what_is_refused(cnc, reference_machine, tmp_path) -> None:  # noqa: ANN001
    """``set mode mdi`` + ``set mdi G21 G90 G94 G53 G1 ...`` as :class:`MdiMover` sends them (the
    commands of ``man linuxcncrsh``); back at rest at the point, the program idle."""
    client, server = cnc
    mover = MdiMover(client, reference_machine, 0.005, 10.0)
    target = np.array([120.0, 80.0, -20.0])
    mover.move_to(target, 30000.0)
    assert np.allclose(client.position_mm(), target, atol=1e-6)
    assert client.program_state() == "idle" and server.mode == "mdi"
    with pytest.raises(OutOfRangeError, match="outside the machine's travel"):
        mover.move_to(np.array([1e6, 0.0, 0.0]), 30000.0)
    # past the mover's check (a machine file wider than the CNC's limits): the CNC refuses
    # and says why at once, as LinuxCNC's error channel does
    with pytest.raises(DeviceError, match=r"did not move to \[1000000.0, 0.0, 0.0\] mm .Unable"):
        client.move_mdi(np.array([1e6, 0.0, 0.0]), 30000.0, 0.005, 10.0)
    assert np.allclose(client.position_mm(), target, atol=1e-6)
    program = tmp_path / "p.ngc"
    program.write_text("G21 G90\nG53 G1 X100 F600\nM0\nM2\n")
    client.start_program(str(program))
    with pytest.raises(DeviceError, match="a program is running"):
        mover.move_to(target, 30000.0)
    client.stop_program()


def test_a_controlled_program_on_the_lockstep_clock(reference_machine, tmp_path) -> None:  # noqa: ANN001
    """On a LockstepClock the program moves in virtual time only: a feed hold acts at the
    virtual time it arrives, and nothing moves while the host does not let time pass."""
    clock = LockstepClock()
    server = LinuxcncrshServer(
        SimulatedCnc(reference_machine, clock), reference_machine, lockstep=clock
    )
    server.start()
    client = open_linuxcnc("127.0.0.1", server.port, 2.0, clock=clock)
    try:
        program = tmp_path / "p.ngc"
        program.write_text("G21 G90\nG53 G1 X0 Y0 Z0 F6000\nM0\nG53 G1 X100 F600\nM2\n")
        client.start_program(str(program))
        while client.program_state() != "paused":
            clock.sleep(0.5)
        assert np.allclose(client.position_mm(), 0.0) and client.is_standstill()
        client.resume()
        clock.sleep(2.0)  # 10 mm/s after the acceleration: short of 20 mm
        moved = client.position_mm()[0]
        time.sleep(0.2)
        assert 19.0 < moved < 20.0 and client.position_mm()[0] == moved  # wall time: nothing
        client.hold()
        clock.sleep(5.0)
        assert client.program_state() == "paused" and client.position_mm()[0] == moved
        client.resume()
        clock.sleep(7.0)  # 80 mm at 10 mm/s and the acceleration: not quite there yet
        assert client.program_state() == "running"
        clock.sleep(2.0)
        assert client.program_state() == "idle"
        assert client.position_mm()[0] == pytest.approx(100.0, abs=1e-6)
    finally:
        client.close()
        server.stop()


@pytest.mark.parametrize(("allowed", "mover_type"), [(False, OperatorPrompt), (True, MdiMover)])
def test_xmalign_moves_the_machine_only_where_units_yaml_allows_it(
    cnc, reference_machine, tmp_path, allowed: bool, mover_type: type
) -> None:  # noqa: ANN001
    client, server = cnc
    path = tmp_path / "units.yaml"
    path.write_text(
        "format: xmalign.units/1\nlaunch: {transport: modbus-tcp, host: a}\n"
        "receiver: {transport: modbus-tcp, host: b}\ninterferometer: {port: /dev/null}\n"
        "machine_position:\n  source: linuxcncrsh\n"
        f"  linuxcncrsh: {{host: 127.0.0.1, port: {server.port}, program: p.ngc,"
        f" allow_mdi_moves: {str(allowed).lower()}}}\n"
    )
    config = load_units_config(path)
    mover = _mover(config, reference_machine, client, input, print, client)
    assert type(mover) is mover_type


def test_an_inch_linuxcnc_reports_inches_and_reads_mdi_lines_in_the_units_in_force(
    reference_machine: Machine,
) -> None:
    """As a LinuxCNC with [TRAJ] LINEAR_UNITS = inch: ``get user_linear_units`` INCH,
    ``abs_act_pos`` in inches, MDI lines in G20 until a G21 (then G21, modal)."""
    server = LinuxcncrshServer(
        SimulatedCnc(reference_machine, WallClock()), reference_machine, linear_units="inch"
    )
    server.start()
    client = open_linuxcnc("127.0.0.1", server.port, 2.0)
    try:
        assert client.mm_per_unit == 25.4
        client._set("mode mdi")
        client._set("mdi G53 G1 X1 Y2 Z-0.5 F100")  # the machine's units: inch
        _wait(lambda: client.program_state() == "idle" and client.is_standstill())
        assert np.allclose(server.linuxcnc.position_mm(), [25.4, 50.8, -12.7], atol=1e-6)
        assert client._get("abs_act_pos")[:3] == ["1.000000", "2.000000", "-0.500000"]
        MdiMover(client, reference_machine, 0.005, 10.0).move_to(np.array([100, 60, -20]), 6e3)
        assert np.allclose(server.linuxcnc.position_mm(), [100.0, 60.0, -20.0], atol=1e-6)
        assert server.linuxcnc.program_units == "mm"
    finally:
        client.close()
        server.stop()
