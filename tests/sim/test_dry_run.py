import numpy as np
import pytest

from sim.dry_run import DryRunOptions, measure_virtually, simulate_calibration, virtual_setup
from trajectories.gcode import DIALECTS
from trajectories.gcode.program import write_program
from xmalign.errors import BeamLostError
from xmalign.formats.measurements import read_measurements, write_measurements
from xmalign.formats.plan import read_plan


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory, reference_machine):
    workdir = tmp_path_factory.mktemp("dry")
    return simulate_calibration(reference_machine, workdir, DryRunOptions(seed=2)), workdir


def test_dry_run_finds_the_pose_and_compensates_the_machine(dry_run):
    report, workdir = dry_run
    assert np.linalg.norm(report.position_error_um) < 60
    assert abs(report.gamma_error_urad) < 60
    assert report.volumetric_before_um > 5
    assert report.volumetric_after_um < 0.2 * report.volumetric_before_um
    assert all(m.measured_straightness_um > 0 and m.measured_angle_urad > 0 for m in report.margins)
    assert [m.line for m in report.margins] == ["X", "Y", "Z", "XY", "YZ", "XZ"]
    assert report.on_machine_s > 0 and report.points == len(
        read_measurements(workdir / "measurements.csv")
    )
    for path in report.files.values():
        assert path.exists(), path


def test_an_interrupted_run_resumes_without_losing_or_repeating_points(dry_run, reference_machine):
    _, workdir = dry_run
    plan = read_plan(workdir / "plan.json")
    plan.lines = plan.lines[:2]
    program = write_program(plan, reference_machine, DIALECTS["linuxcnc"]())
    full_csv = workdir / "full.csv"
    measure_virtually(virtual_setup(reference_machine, 2), plan, program, "linuxcnc", full_csv)
    full = read_measurements(full_csv)
    partial_csv = workdir / "partial.csv"
    write_measurements(partial_csv, full[: len(full) // 3])
    measure_virtually(
        virtual_setup(reference_machine, 2), plan, program, "linuxcnc", partial_csv, resume=True
    )
    resumed = read_measurements(partial_csv)
    assert [r.key() for r in resumed] == [r.key() for r in full]
    difference = np.array([a.channels - b.channels for a, b in zip(full, resumed, strict=True)])
    assert np.abs(difference[:, 1:3]).max() < 5.0  # straightness agrees within noise, um


def test_a_beam_loss_stops_the_line_with_the_units_locked(dry_run, reference_machine):
    _, workdir = dry_run
    plan = read_plan(workdir / "plan.json")
    line = plan.lines[0]
    line.launch_rad = line.launch_rad + np.array([0.0, 2e-4])  # 200 urad off: beam leaves range
    plan.lines = [line]
    setup = virtual_setup(reference_machine, 2)
    program = write_program(plan, reference_machine, DIALECTS["sinumerik"]())
    csv_path = workdir / "lost.csv"
    with pytest.raises(BeamLostError, match="line X .*units are locked"):
        measure_virtually(setup, plan, program, "sinumerik", csv_path)
    assert all(axis.is_locked() for unit in (setup.launch, setup.receiver) for axis in unit.axes)
    assert len(read_measurements(csv_path)) > 0  # what was captured before the loss is kept
