"""The driver of LinuxCNC's Python module ``linuxcnc``, and the simulated module it runs on here.

The simulated module (sim/linuxcnc_module.py) serves the same simulated LinuxCNC
as the simulated linuxcncrsh; the real module (Debian ``linuxcnc-uspace``, in
/usr/lib/python3/dist-packages) is checked once for every name the driver uses
and for the constants' values, so the simulated one cannot drift from it. The
real module against a running headless LinuxCNC: tests/linuxcnc/test_real_linuxcnc_module.py.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from required_tools import skip_unless_required

from firmware_iface.config import _mover, load_units_config
from firmware_iface.linuxcnc_control import MdiMover
from firmware_iface.linuxcnc_module import (
    MODULE_API,
    SYSTEM_MODULE_DIR,
    LocalLinuxCnc,
    find_linuxcnc_module,
)
from firmware_iface.linuxcncrsh import open_linuxcnc
from firmware_iface.machine_position import OperatorPrompt
from sim.cnc import SimulatedCnc
from sim.linuxcnc_module import CONSTANTS, simulated_module
from sim.linuxcnc_task import SimulatedLinuxcnc
from sim.servers.linuxcncrsh import LinuxcncrshServer
from tests.sim.test_linuxcncrsh_server import _wait, run_through_a_stop_and_a_feed_hold
from xmalign.errors import DeviceError, DeviceTimeoutError, DriveFaultError, InputError
from xmalign.machine import Machine
from xmalign.roles import WallClock

ROOT = Path(__file__).resolve().parents[2]


def _real_module() -> Any:
    try:
        return find_linuxcnc_module(SYSTEM_MODULE_DIR)
    except InputError:
        skip_unless_required("LinuxCNC's Python module is not installed (Debian linuxcnc-uspace)")


def test_the_real_module_has_what_the_driver_uses_and_the_simulated_one_its_values() -> None:
    real = _real_module()
    missing = [
        f"{part}.{name}"
        for part, names in MODULE_API.items()
        for name in names
        if not hasattr(real if part == "module" else getattr(real, part), name)
    ]
    assert missing == []
    assert {name: getattr(real, name) for name in CONSTANTS} == CONSTANTS
    assert issubclass(real.error, RuntimeError)


def test_the_simulated_module_offers_the_same(reference_machine: Machine) -> None:
    module = simulated_module(
        SimulatedLinuxcnc(SimulatedCnc(reference_machine, WallClock()), reference_machine)
    )
    stat = module.stat()
    stat.poll()
    parts = {
        "module": module,
        "stat": stat,
        "command": module.command(),
        "error_channel": module.error_channel(),
    }
    missing = [
        f"{part}.{name}"
        for part, names in MODULE_API.items()
        for name in names
        if not hasattr(parts[part], name)
    ]
    assert missing == []
    assert len(stat.actual_position) == 9 and len(stat.homed) == 16  # as the real one's


def test_the_module_is_found_in_debians_folder_without_the_rest_of_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _real_module()
    (tmp_path / "linuxcnc").mkdir()  # a folder of that name (tests/linuxcnc): not the module
    monkeypatch.syspath_prepend(str(tmp_path))
    module = find_linuxcnc_module()
    assert module.__file__.startswith(str(SYSTEM_MODULE_DIR))
    assert str(SYSTEM_MODULE_DIR) not in sys.path
    assert find_linuxcnc_module() is module


def test_an_absent_module_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(
        InputError, match=f"'linuxcnc' is not in {tmp_path}: install LinuxCNC"
    ) as error:
        find_linuxcnc_module(tmp_path)
    assert "\n" not in str(error.value)
    (tmp_path / "linuxcnc.cpython-27-x86_64-linux-gnu.so").write_bytes(b"")
    with pytest.raises(
        InputError, match="found linuxcnc.cpython-27-x86_64-linux-gnu.so, built for another Python"
    ):
        find_linuxcnc_module(tmp_path)


@pytest.fixture
def linuxcnc(reference_machine: Machine) -> Iterator[SimulatedLinuxcnc]:
    simulated = SimulatedLinuxcnc(SimulatedCnc(reference_machine, WallClock()), reference_machine)
    yield simulated
    simulated.shut_down()


@pytest.fixture
def cnc(linuxcnc: SimulatedLinuxcnc) -> LocalLinuxCnc:
    return LocalLinuxCnc(simulated_module(linuxcnc), timeout_s=1.0)


def test_program_control_through_the_module_with_each_command_logged(
    cnc: LocalLinuxCnc, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="firmware_iface")
    program = run_through_a_stop_and_a_feed_hold(cnc, tmp_path)
    log = caplog.text
    for line in (
        "> mode(MODE_AUTO)",
        f"> program_open('{program}')",
        "< auto(AUTO_RUN, 0): ",
        "> auto(AUTO_PAUSE)",
        "> abort()",
    ):
        assert line in log, log


def test_a_refusal_carries_linuxcncs_message(cnc: LocalLinuxCnc) -> None:
    with pytest.raises(
        DeviceError,
        match=r"refused 'program_open\('/nowhere.ngc'\)' \(Unable to open file </nowhere.ngc>\)",
    ):
        cnc.start_program("/nowhere.ngc")


def test_a_command_a_dead_task_never_receives_is_named(linuxcnc: SimulatedLinuxcnc) -> None:
    """After milltask dies the status stays as it was and no command is received (2.9)."""
    linuxcnc.kill_task()
    with pytest.raises(DeviceError) as caught:
        LocalLinuxCnc(simulated_module(linuxcnc), timeout_s=0.2).stop_program()
    assert str(caught.value) == (
        "LinuxCNC on this computer (simulated LinuxCNC) did not receive 'abort()' within 0.2 s"
        " although its status answers: LinuxCNC's task (milltask) has stopped; restart LinuxCNC"
    )


def test_a_command_received_but_not_completed_in_time_is_a_timeout(
    linuxcnc: SimulatedLinuxcnc,
) -> None:
    module = simulated_module(linuxcnc)
    stat = module.stat

    def poll(self: object) -> None:  # received (echoed), never done: the task hangs on it
        stat.poll(self)
        self.state = module.RCS_EXEC  # type: ignore[attr-defined]

    module.stat = type("Busy", (stat,), {"poll": poll})
    with pytest.raises(
        DeviceTimeoutError, match=r"did not complete 'abort\(\)' within 0.2 s \(received\)"
    ):
        LocalLinuxCnc(module, timeout_s=0.2).stop_program()


def test_mdi_moves_and_a_target_linuxcnc_refuses(
    cnc: LocalLinuxCnc, reference_machine: Machine
) -> None:
    mover = MdiMover(cnc, reference_machine, 0.005, 10.0)
    target = np.array([120.0, 80.0, -20.0])
    mover.move_to(target, 30000.0)
    assert np.allclose(cnc.position_mm(), target, atol=1e-6) and cnc.program_state() == "idle"
    with pytest.raises(DeviceError, match=r"did not move to \[1000000.0, 0.0, 0.0\] mm .Unable"):
        cnc.move_mdi(np.array([1e6, 0.0, 0.0]), 30000.0, 0.005, 10.0)


class _Stat:
    """The simulated stat with some fields replaced."""

    def __init__(self, stat: Any, **fields: Any) -> None:
        self.__dict__.update(stat.__dict__)
        self.__dict__.update(fields)

    def poll(self) -> None: ...


@pytest.mark.parametrize(
    ("fields", "fragment"),
    [
        ({"task_state": 1}, "E-stop is pressed"),
        ({"task_state": 3}, "the machine is off"),
        ({"homed": (1, 0, 1) + (0,) * 13}, r"not every joint is homed \(YES NO YES\)"),
        ({"joint": ({"fault": 0}, {"fault": 1}, {"fault": 0})}, r"joint fault \(OK FAULT OK\)"),
    ],
)
def test_a_machine_not_ready_is_refused(
    linuxcnc: SimulatedLinuxcnc, fields: dict, fragment: str
) -> None:
    module = simulated_module(linuxcnc)
    stat = module.stat()
    stat.poll()
    module.stat = lambda: _Stat(stat, **fields)
    with pytest.raises(DriveFaultError, match=fragment):
        LocalLinuxCnc(module).check_ready()


def test_both_channels_see_the_same_simulated_linuxcnc(
    reference_machine: Machine, tmp_path: Path
) -> None:
    server = LinuxcncrshServer(SimulatedCnc(reference_machine, WallClock()), reference_machine)
    server.start()
    rsh = open_linuxcnc("127.0.0.1", server.port, 2.0)
    local = LocalLinuxCnc(simulated_module(server.linuxcnc))
    try:
        program = tmp_path / "p.ngc"
        program.write_text("G21 G90\nG53 G1 X10 Y20 Z-30 F6000\nM0\nM2\n")
        local.start_program(str(program))
        _wait(lambda: rsh.program_state() == "paused")
        assert np.array_equal(rsh.position_mm(), local.position_mm())
        assert rsh.loaded_program() == local.loaded_program() == str(program)
        rsh.resume()
        _wait(lambda: local.program_state() == "idle")
    finally:
        rsh.close()
        server.stop()


def test_the_documented_example_loads_and_is_in_the_docs() -> None:
    example = ROOT / "examples" / "units-linuxcnc.yaml"
    config = load_units_config(example).machine_position
    assert config.source == "linuxcnc" and config.controlled is config.linuxcnc
    assert not config.follows_the_machine
    docs = (ROOT / "docs" / "hardware.md").read_text(encoding="utf-8")
    assert example.read_text(encoding="utf-8") in docs, "docs/hardware.md lost the example"


@pytest.mark.parametrize(("allowed", "mover_type"), [(False, OperatorPrompt), (True, MdiMover)])
def test_units_yaml_source_linuxcnc(
    cnc: LocalLinuxCnc, reference_machine: Machine, tmp_path: Path, allowed: bool, mover_type: type
) -> None:
    path = tmp_path / "units.yaml"
    path.write_text(
        "format: xmalign.units/1\nlaunch: {transport: modbus-tcp, host: a}\n"
        "receiver: {transport: modbus-tcp, host: b}\ninterferometer: {port: /dev/null}\n"
        "machine_position:\n  source: linuxcnc\n"
        "  linuxcnc: {program: cnc/run.ngc, nml_file: cnc/x.nml,"
        f" allow_mdi_moves: {str(allowed).lower()}}}\n"
    )
    config = load_units_config(path)
    local = config.machine_position.linuxcnc
    assert local is not None and config.machine_position.controlled is local
    assert local.cnc_program_path == str((tmp_path / "cnc" / "run.ngc").resolve())
    assert local.nml_file == tmp_path / "cnc" / "x.nml" and local.module_dir is None
    assert (local.joints, local.in_position_mm, local.tolerance_mm) == (3, 0.002, 0.005)
    assert type(_mover(config, reference_machine, cnc, input, print, cnc)) is mover_type


@pytest.fixture
def inch_linuxcnc(reference_machine: Machine) -> Iterator[SimulatedLinuxcnc]:
    """A simulated LinuxCNC with [TRAJ] LINEAR_UNITS = inch, in G20 until told otherwise."""
    simulated = SimulatedLinuxcnc(
        SimulatedCnc(reference_machine, WallClock()), reference_machine, linear_units="inch"
    )
    yield simulated
    simulated.shut_down()


def test_an_inch_machine_is_read_and_moved_in_mm(
    inch_linuxcnc: SimulatedLinuxcnc, reference_machine: Machine
) -> None:
    """``stat.actual_position`` is in machine units, ``stat.linear_units`` machine units
    per mm (LinuxCNC's Python interface documentation); the MDI line says G21 itself."""
    cnc = LocalLinuxCnc(simulated_module(inch_linuxcnc), timeout_s=1.0)
    target = np.array([120.0, 80.0, -20.0])
    MdiMover(cnc, reference_machine, 0.005, 10.0).move_to(target, 30000.0)
    assert np.allclose(inch_linuxcnc.position_mm(), target, atol=1e-6)
    assert np.allclose(cnc.position_mm(), target, atol=1e-6)
    assert np.allclose(cnc.commanded_mm(), target, atol=1e-6)
    assert inch_linuxcnc.program_units == "mm"  # modal: the G21 stays in force


def test_a_refused_resume_is_refused_at_once(cnc: LocalLinuxCnc) -> None:
    """``RCS_ERROR`` for a command that does not complete (a resume, nothing paused) is a
    refusal with LinuxCNC's message, not 'received': the run does not wait for the machine."""
    cnc.clock = _NoTimePasses()
    with pytest.raises(DeviceError, match=r"refused 'auto\(AUTO_RESUME\)' \(no program to resume"):
        cnc.resume()


class _NoTimePasses(WallClock):
    """A clock on which any wait fails the test: the answer must come without one."""

    def sleep(self, seconds: float) -> None:
        raise AssertionError(f"waited {seconds} s")


class _InterruptedClock(WallClock):
    """Ctrl-C during the first wait longer than a command's poll."""

    def sleep(self, seconds: float) -> None:
        if seconds >= 0.05:
            raise KeyboardInterrupt
        super().sleep(seconds)


def test_ctrl_c_during_an_mdi_move_aborts_it(
    linuxcnc: SimulatedLinuxcnc, reference_machine: Machine
) -> None:
    cnc = LocalLinuxCnc(simulated_module(linuxcnc), clock=_InterruptedClock(), timeout_s=1.0)
    mover = MdiMover(cnc, reference_machine, 0.005, 60.0)
    with pytest.raises(KeyboardInterrupt):
        mover.move_to(np.array([900.0, 0.0, 0.0]), 600.0)  # 10 mm/s: 90 s to go
    assert linuxcnc.program_status == "idle" and linuxcnc.cnc.is_standstill()
    stopped_at = linuxcnc.position_mm()
    WallClock().sleep(0.2)
    assert np.array_equal(linuxcnc.position_mm(), stopped_at) and stopped_at[0] < 10.0
