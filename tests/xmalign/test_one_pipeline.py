"""Every command and the dry run call the step layer (issue 23, item 1).

Each test puts a spy in place of the step function a command must call (the
spy calls the real step): the test fails if the command wires the step itself.
"""

from __future__ import annotations

import io
import json
from collections.abc import Callable
from pathlib import Path

import pytest
from cli_helpers import run_in_process

from tests.xmalign.test_live_controlled_e2e import served  # noqa: F401 - fixture
from tests.xmalign.test_live_e2e import short_plan  # noqa: F401 - the fixture served uses
from xmalign import steps
from xmalign.errors import InputError
from xmalign.formats.measurements import load_measurements
from xmalign.formats.plan import read_plan, write_plan
from xmalign.formats.pose import read_pose
from xmalign.formats.studies import read_design


@pytest.fixture(scope="module")
def dry(dry_run_of_seed):
    """A dry run's folder (seed 3): session, pose, plan, measurements."""
    return dry_run_of_seed(3, "pipeline")[1]


def _spy(monkeypatch: pytest.MonkeyPatch, module: object, name: str) -> list[tuple]:
    """Replace ``module.name`` by a spy that records its arguments and calls the step."""
    calls: list[tuple] = []
    real: Callable = getattr(steps, name)

    def spy(*args, **kwargs):
        calls.append((args, kwargs))
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, spy)
    return calls


def test_program_calls_the_program_step(dry, tmp_path, monkeypatch):
    import xmalign.cli.program as command

    calls = _spy(monkeypatch, command, "program_step")
    plan, program = tmp_path / "plan.json", tmp_path / "CAL1.h"
    result = run_in_process(
        "program", "--pose", str(dry / "pose.json"), "--plan-out", str(plan),
        "--out", str(program), "--dialect", "heidenhain", "--lines", "X,Y",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert len(calls) == 1
    assert [line.id for line in read_plan(plan).lines] == ["X", "Y"]
    assert "BEGIN PGM CAL1 MM" in program.read_text()  # Heidenhain: named after its file
    shown = io.StringIO()
    result = run_in_process("program", "--pose", str(dry / "pose.json"), stdout=shown)
    assert result.returncode == 0, result.stderr
    assert len(calls) == 2 and "G1" in shown.getvalue()
    assert not list(Path.cwd().glob("run.*"))  # stdout: no program file beside anything


def test_plan_identify_calls_the_design_step(tmp_path, monkeypatch):
    import xmalign.cli.program as command

    calls = _spy(monkeypatch, command, "design_step")
    out = tmp_path / "design.json"
    result = run_in_process("plan-identify", "--count", "4", "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert len(calls) == 1
    assert read_design(out).machine_mm.shape == (4, 3)


def test_identify_solves_and_writes_the_pose_through_the_steps(dry, tmp_path, monkeypatch):
    import xmalign.cli.identify as command

    calls = _spy(monkeypatch, command, "write_pose_step")
    solved = _spy(monkeypatch, command, "solve_step")
    out = tmp_path / "pose.json"
    result = run_in_process("identify", "--input", str(dry / "session.json"), "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert [args[0] for args, _ in solved] == [dry / "session.json"]
    assert [args[0] for args, _ in calls] == [out]
    assert read_pose(out).n_alignments > 0
    roles = [source["role"] for source in json.loads(out.read_text())["inputs"]]
    assert roles == ["session"]


def test_post_calls_the_post_step_which_checks_the_plan(
    dry, tmp_path, monkeypatch, reference_machine
):
    import xmalign.cli.post as command

    calls = _spy(monkeypatch, command, "post_step")
    data = dry / "measurements.csv"
    result = run_in_process(
        "post", "--plan", str(dry / "plan.json"), "--data", str(data),
        "--out", str(tmp_path / "errors.csv"),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert len(calls) == 1 and [path for _, path in calls[0][0][1]] == [data]
    other = read_plan(dry / "plan.json")
    other.lines = other.lines[:2]
    write_plan(tmp_path / "other.json", other)
    with pytest.raises(InputError, match="recorded for another plan"):
        steps.post_step(
            reference_machine, [(read_plan(tmp_path / "other.json"), data)], tmp_path / "e.csv"
        )
    assert not (tmp_path / "e.csv").exists()


def test_run_sim_runs_the_program_steps_gcode_into_the_steps_file(dry, tmp_path, monkeypatch):
    import xmalign.cli.run as command

    opened = _spy(monkeypatch, command, "open_measurements_step")
    gcode = _spy(monkeypatch, steps, "program_gcode")
    plan = read_plan(dry / "plan.json")
    plan.lines = plan.lines[:1]
    write_plan(tmp_path / "plan.json", plan)
    out = tmp_path / "m.csv"
    result = run_in_process(
        "run", "--plan", str(tmp_path / "plan.json"), "--sim", "--seed", "3",
        "--out", str(out), "--in-process",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert len(opened) == 1 and opened[0][0][0] == out
    assert len(gcode) == 1
    assert load_measurements(out).sim_seed == 3


def test_the_dry_run_calls_every_step(reference_machine, tmp_path, monkeypatch):
    import sim.dry_run as dry_run

    names = ("design_step", "station_step", "open_measurements_step", "post_step", "comp_step")
    calls = {name: _spy(monkeypatch, dry_run, name) for name in names}
    # the station step (identify -> program -> run, issue 32) calls these in the step layer
    station = ("identify_step", "program_step", "open_measurements_step")
    calls |= {f"station: {name}": _spy(monkeypatch, steps, name) for name in station}
    poses = _spy(monkeypatch, steps, "write_pose_step")  # identify_step writes the pose
    dry_run.simulate_calibration(
        reference_machine, tmp_path / "dry", dry_run.DryRunOptions(seed=5, verify=True)
    )
    assert {name: len(made) for name, made in calls.items()} == {
        "design_step": 1,
        "station_step": 1,
        "open_measurements_step": 1,  # the verification
        "post_step": 1,
        "comp_step": 1,
        "station: identify_step": 1,
        "station: program_step": 1,
        "station: open_measurements_step": 1,  # the calibration
    }
    assert [args[0] for args, _ in poses] == [tmp_path / "dry" / "pose.json"]


def test_the_instrument_dry_run_posts_through_the_post_step(
    reference_machine, tmp_path, monkeypatch
):
    import sim.instrument_dry_run as instrument_dry_run

    calls = _spy(monkeypatch, instrument_dry_run, "post_step")
    instrument_dry_run.simulate_instruments(reference_machine, tmp_path / "tracer", "tracer", 3)
    assert len(calls) == 1
    errors = (tmp_path / "tracer" / "errors-instruments.csv").read_text()
    assert "tracer.csv" in errors  # the tables name the readings they came from


def test_a_controlled_live_run_calls_the_controlled_run_step(
    served,  # noqa: F811 - fixture
    tmp_path,
    monkeypatch,
):
    """``xmalign run --config`` with ``source: linuxcncrsh`` (here against ``sim serve``)
    wires the controlled run in the step the dry run calls too (tests/sim/test_served_world.py)."""
    calls = _spy(monkeypatch, steps, "controlled_run_step")  # run imports it when it runs
    result = run_in_process(
        "run", "--config", str(tmp_path / "units.yaml"), "--machine",
        str(tmp_path / "machine.yaml"), "--plan", str(tmp_path / "plan.json"), "--out",
        str(tmp_path / "m.csv"),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert len(calls) == 1 and len(load_measurements(tmp_path / "m.csv").rows) == 7
