import numpy as np
import pytest

from sim.dry_run import DryRunOptions, measure_virtually, simulate_calibration, virtual_setup
from trajectories.gcode import DIALECTS
from trajectories.gcode.program import write_program
from xmalign.calibration import capture_sequence, open_run_output
from xmalign.errors import InputError
from xmalign.formats.measurements import plan_sha256, read_measurements, write_measurements
from xmalign.formats.plan import read_plan
from xmalign.post.evaluate import post_process


@pytest.fixture(scope="module")
def dry_run(dry_run_of_seed):
    return dry_run_of_seed(2, "dry")


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


def _two_line_plan(workdir, machine):
    plan = read_plan(workdir / "plan.json")
    plan.lines = plan.lines[:2]
    return plan, write_program(plan, machine, DIALECTS["linuxcnc"]())


def _measure(setup, plan, program, path, resume=False, stop_after=None):
    """measure_virtually into ``path``; Ctrl-C (KeyboardInterrupt) once ``stop_after`` are saved."""

    def on_saved(saved):
        if stop_after is not None and saved >= stop_after:
            raise KeyboardInterrupt

    with open_run_output(path, plan, resume) as output:
        output.on_saved = on_saved
        return measure_virtually(setup, plan, program, "linuxcnc", output)


def test_an_interrupted_run_resumes_without_losing_or_repeating_points(dry_run, reference_machine):
    _, workdir = dry_run
    plan, program = _two_line_plan(workdir, reference_machine)
    full_csv = workdir / "full.csv"
    _measure(virtual_setup(reference_machine, 2), plan, program, full_csv)
    full = read_measurements(full_csv)
    partial_csv = workdir / "partial.csv"
    write_measurements(partial_csv, full[: len(full) // 3], plan_sha256(plan))
    run = _measure(virtual_setup(reference_machine, 2), plan, program, partial_csv, resume=True)
    resumed = read_measurements(partial_csv)
    assert [r.key() for r in resumed] == [r.key() for r in full]
    assert run.statistics.points == len(full) - len(full) // 3
    difference = np.array([a.channels - b.channels for a, b in zip(full, resumed, strict=True)])
    assert np.abs(difference[:, 1:3]).max() < 5.0  # straightness agrees within noise, um


def test_a_stop_mid_line_keeps_the_locked_setup_when_the_units_did_not_move(
    dry_run, reference_machine
):
    _, workdir = dry_run
    plan, program = _two_line_plan(workdir, reference_machine)
    path = workdir / "stopped.csv"
    setup = virtual_setup(reference_machine, 2)
    with pytest.raises(KeyboardInterrupt):
        _measure(setup, plan, program, path, stop_after=40)
    assert all(axis.is_locked() for unit in (setup.launch, setup.receiver) for axis in unit.axes)
    run = _measure(setup, plan, program, path, resume=True)
    assert run.statistics.resumed == ["line X: the units stand where they were locked; setup kept"]
    assert list(run.statistics.alignments) == ["Y"]  # X was not aligned again
    rows = read_measurements(path)
    assert len(rows) == sum(1 for line in plan.lines for _ in capture_sequence(line))
    assert {row.segment for row in rows} == {0}


def test_units_that_moved_are_aligned_again_and_start_a_new_segment(dry_run, reference_machine):
    _, workdir = dry_run
    plan = read_plan(workdir / "plan.json")
    program = write_program(plan, reference_machine, DIALECTS["linuxcnc"]())
    path = workdir / "moved.csv"
    with pytest.raises(KeyboardInterrupt):
        _measure(virtual_setup(reference_machine, 2), plan, program, path, stop_after=40)
    run = _measure(virtual_setup(reference_machine, 2), plan, program, path, resume=True)
    assert run.statistics.resumed[0].startswith("line X: the units had moved")
    rows = read_measurements(path)
    segments = [row.segment for row in rows if row.line == "X"]
    assert segments == [0] * 40 + [1] * (len(segments) - 40)
    assert {row.segment for row in rows if row.line != "X"} == {0}
    fit = post_process(reference_machine, plan, rows, str(path)).fit
    assert [(s.line_id, s.segment) for s in fit.setup][:3] == [("X", 0), ("X", 1), ("Y", 0)]
    uninterrupted = post_process(
        reference_machine, plan, read_measurements(workdir / "measurements.csv"), "m.csv"
    ).fit
    # one setup for both segments would leave the re-alignment in the residuals (sigma0 1.36)
    assert fit.sigma0 < 1.15 * uninterrupted.sigma0
    for name, table in uninterrupted.tables.tables.items():  # two measurements agree (4 sigma)
        other = fit.tables.tables[name]
        bound = 2 * np.hypot(table.u95, other.u95)
        assert np.all(np.abs(table.values - other.values) <= bound), name


def test_a_dry_run_never_replaces_an_earlier_one(dry_run, reference_machine):
    _, workdir = dry_run
    before = (workdir / "measurements.csv").read_bytes()
    with pytest.raises(InputError, match="already holds a dry run .*measurements.csv"):
        simulate_calibration(reference_machine, workdir, DryRunOptions(seed=2))
    assert (workdir / "measurements.csv").read_bytes() == before
