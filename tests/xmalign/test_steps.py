"""The step layer: the same step functions whatever drives the machine."""

import re

import numpy as np
import pytest

from sim.dry_run import virtual_run_devices, virtual_setup
from trajectories.gcode import DIALECTS
from trajectories.gcode.program import write_program
from xmalign.calibration import open_run_output
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan
from xmalign.program_check import same_program
from xmalign.steps import (
    comp_step,
    post_step,
    program_drive,
    program_file,
    program_gcode,
    program_name_on_controller,
    refine_guess,
    run_step,
    stepping_drive,
)


@pytest.fixture(scope="module")
def dry_run_folder(dry_run_of_seed):
    return dry_run_of_seed(3, "steps")[1]


def _two_lines(workdir):
    plan = read_plan(workdir / "plan.json")
    plan.lines = plan.lines[:2]
    return plan


def test_program_and_stepping_drives_capture_the_same_points(
    dry_run_folder, reference_machine, tmp_path
):
    """A controller running the program and the machine stepped target by target:
    the same points, in the same order, with channels that agree to the noise."""
    plan = _two_lines(dry_run_folder)
    program = write_program(plan, reference_machine, DIALECTS["linuxcnc"]())
    rows = {}
    for name in ("program", "stepping"):
        setup = virtual_setup(reference_machine, 3)
        drive = (
            program_drive(setup.cnc.run_program(program, "linuxcnc"))
            if name == "program"
            else stepping_drive(setup.cnc, reference_machine)
        )
        path = tmp_path / f"{name}.csv"
        with open_run_output(path, plan, resume=False) as output:
            run = run_step(plan, virtual_run_devices(setup), output, drive)
        assert run.statistics.points > 0
        rows[name] = read_measurements(path)
    assert [r.key() for r in rows["program"]] == [r.key() for r in rows["stepping"]]
    program_ch = np.array([r.channels for r in rows["program"]])
    stepping_ch = np.array([r.channels for r in rows["stepping"]])
    assert np.abs(program_ch[:, 0] - stepping_ch[:, 0]).max() < 5e-3  # mm, machine + noise


def test_units_are_locked_after_a_run_step_however_it_ends(
    dry_run_folder, reference_machine, tmp_path
):
    plan = _two_lines(dry_run_folder)
    setup = virtual_setup(reference_machine, 3)

    def failing(run):
        setup.launch.move_to(setup.launch.angles_rad() + 1e-3, 30.0)
        assert not all(axis.is_locked() for axis in setup.launch.axes)
        raise KeyboardInterrupt

    output = open_run_output(tmp_path / "m.csv", plan, resume=False)
    with output, pytest.raises(KeyboardInterrupt):
        run_step(plan, virtual_run_devices(setup), output, failing)
    assert all(axis.is_locked() for axis in (*setup.launch.axes, *setup.receiver.axes))


def test_post_and_comp_steps_write_their_files(dry_run_folder, reference_machine, tmp_path):
    plan = read_plan(dry_run_folder / "plan.json")
    posted = post_step(
        reference_machine, [(plan, dry_run_folder / "measurements.csv")], tmp_path / "errors.csv"
    )
    assert (tmp_path / "errors.csv").exists()
    compensation = comp_step(reference_machine, posted.tables, tmp_path / "comp")
    assert compensation.files
    assert all((tmp_path / "comp" / name).exists() for name in compensation.files)


def test_refine_guess_waits_for_three_alignments(dry_run_folder):
    from xmalign.formats.session import read_session

    session = read_session(dry_run_folder / "session.json")
    assert len(session.alignments) >= 3
    guess = refine_guess(session)
    assert guess is not None and np.all(np.isfinite(guess.launch2mcs_mm))
    session.alignments = session.alignments[:2]
    assert refine_guess(session) is None


@pytest.mark.parametrize("controller", ["sinumerik", "fanuc", "heidenhain", "linuxcnc"])
def test_the_expected_program_name_is_the_one_the_program_step_gives(
    controller, dry_run_folder, reference_machine
):
    """What a followed run expects a controller to report (without ``program_name``) is
    what that controller calls the program ``xmalign program --out run<suffix>`` writes:
    a Fanuc its O number (the file's name means nothing there), the others the file."""
    machine = reference_machine.model_copy(update={"controller": controller})
    plan = _two_lines(dry_run_folder)
    text = program_gcode(plan, machine, name="RUN")[1]
    file_name = program_file(dry_run_folder / "plan.json", machine).name
    numbers = re.findall(r"^(O\d+)\b", text, flags=re.MULTILINE)
    reported = numbers[0] if controller == "fanuc" else file_name
    assert same_program(reported, program_name_on_controller(machine))
    if controller == "fanuc":
        assert not same_program(file_name, program_name_on_controller(machine))
