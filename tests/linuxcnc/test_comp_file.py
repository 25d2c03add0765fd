"""xmalign's LinuxCNC pitch tables (COMP_FILE) applied by a real headless LinuxCNC.

One dry run (the virtual machine measured and posted by xmalign) gives the
error tables, the pose and the linuxcnc-dialect program. ``xmalign comp
--controller linuxcnc --ini`` writes the tables and merges them into the
harness's sim INI; LinuxCNC (trivkins XYZ, and the XYYZ gantry) runs the
program to the end with a feed override, with a G54 work offset, a G92 offset
and a tool length offset left active before the run. At every standstill of
the program the correction each joint applies (``motor-pos-cmd - pos-cmd -
motor-offset``) must equal the table of its axis, interpolated and chosen by
the direction of the joint's last move, and the joints must stand at the
plan's targets in machine coordinates.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_helpers import run_cli
from harness import LinuxCNCRun, SimMachine, run_linuxcnc, standard_start, write_sim_config

from xmalign.comp.linuxcnc import ini_value
from xmalign.formats.plan import read_plan

pytestmark = pytest.mark.linuxcnc

TRAVEL_MM = {"X": (0.0, 600.0), "Y": (0.0, 400.0), "Z": (-300.0, 0.0)}
MACHINE = {
    "name": "LinuxCNC sim mill",
    "chain": "FYXZ",
    "travel_mm": {axis: list(limits) for axis, limits in TRAVEL_MM.items()},
    "feed_mm_min": {"rapid": 8000, "measure": 2000},
    "controller": "linuxcnc",
    "receiver_offset_mm": [0, 0, -180],
    "launch_unit": {"position_mm": [100, 100, -480]},
    # a short plan: one run per line, 100 mm spacing, short dwells
    "measurement": {"target_spacing_mm": 100, "runs": 1, "diagonal_runs": 1, "dwell_s": 0.1},
    "cnc": {"acceleration_mm_s2": 1000},
}
FEED_OVERRIDE = 20.0
#: offsets left active on the controller before the run; the program must not be shifted by them
OFFSETS_BEFORE_RUN = ["G10 L2 P1 X37 Y-21 Z15", "G10 L2 P2 X-11 Y13 Z-7", "G54", "G43.1 Z25"]
#: required agreement of the applied correction with the table over the last servo
#: period's travel (the comp file's resolution), mm
TOLERANCE_MM = 1e-6
#: the program's coordinates have three decimals
POSITION_TOLERANCE_MM = 6e-4


@pytest.fixture(scope="module")
def calibration() -> Iterator[Path]:
    """A dry run of the sim-sized machine: errors.csv, pose.json, plan.json, run.ngc."""
    folder = Path(tempfile.mkdtemp(prefix="xmalign-lcnc-comp-"))
    (folder / "machine.yaml").write_text(yaml.safe_dump(MACHINE))
    result = run_cli(
        "dry-run", "--machine", str(folder / "machine.yaml"), "--out", str(folder / "dry"),
        "--in-process",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


@dataclass(frozen=True)
class Live:
    """One LinuxCNC run of the program with the merged tables."""

    coordinates: str
    run: LinuxCNCRun
    tables: dict[str, np.ndarray]  # axis -> comp file rows (nominal, forward, reverse), mm
    plan_points_mm: np.ndarray  # (N, 3) every target of the plan, machine coordinates
    merged_ini: str


def _config(calibration: Path, coordinates: str) -> tuple[Path, Path, Path]:
    """Machine file, program and plan for one configuration.

    XYZ: the dry run's own program (every move in G53), joints from the INI.
    XYYZ: ``cnc.joints`` in the machine file and a program that sets and
    programs in its own work offset (G55), written by ``xmalign program``.
    """
    dry = calibration / "dry"
    if coordinates == "XYZ":
        return calibration / "machine.yaml", dry / "run.ngc", dry / "plan.json"
    folder = calibration / "gantry"
    folder.mkdir(exist_ok=True)
    machine = {**MACHINE, "cnc": {**MACHINE["cnc"], "joints": list(coordinates)}}
    machine["cnc"]["work_offset"] = {"code": "G55", "origin_mm": [120.0, 80.0, -40.0]}
    (folder / "machine.yaml").write_text(yaml.safe_dump(machine))
    result = run_cli(
        "program",
        *("--pose", str(dry / "pose.json"), "--machine", str(folder / "machine.yaml")),
        *("--dialect", "linuxcnc", "--out", str(folder / "run.ngc")),
        *("--plan-out", str(folder / "plan.json")),
    )
    assert result.returncode == 0, result.stderr
    return folder / "machine.yaml", folder / "run.ngc", folder / "plan.json"


@pytest.fixture(scope="module", params=["XYZ", "XYYZ"])
def live(request: pytest.FixtureRequest, calibration: Path) -> Iterator[Live]:
    coordinates = request.param
    machine, program, plan = _config(calibration, coordinates)
    folder = Path(tempfile.mkdtemp(prefix=f"xmalign-lcnc-{coordinates}-"))
    sim = SimMachine(
        coordinates=coordinates,
        travel_mm=TRAVEL_MM,
        max_velocity_mm_s=2000.0,
        max_acceleration_mm_s2=40000.0,
        max_feed_override=FEED_OVERRIDE,
        direction_latches=True,
    )
    ini = write_sim_config(folder / "config", sim)
    out = folder / "comp"
    result = run_cli(
        "comp",
        *("--errors", str(calibration / "dry" / "errors.csv"), "--machine", str(machine)),
        *("--controller", "linuxcnc", "--ini", str(ini), "--out", str(out)),
    )
    assert result.returncode == 0, result.stderr
    merged = out / "sim-xmalign.ini"
    shutil.copy(program, folder / "run.ngc")
    (folder / "run.ngc").chmod(0o644)
    folder.chmod(0o755)
    out.chmod(0o755)
    actions = [
        *standard_start(),
        *({"op": "mdi", "gcode": block} for block in OFFSETS_BEFORE_RUN),
        {"op": "mdi", "gcode": "G92 X5 Y-5 Z5", "label": "g92"},
        {
            "op": "run",
            "program": str(folder / "run.ngc"),
            "feed_override": FEED_OVERRIDE,
            "standstill_joints": len(coordinates),
            "timeout_s": 150,
            "label": "run",
        },
    ]
    run = run_linuxcnc(merged, actions, timeout_s=200)
    tables = {axis: np.loadtxt(out / f"{axis.lower()}.comp", ndmin=2) for axis in "XYZ"}
    points = np.vstack([line.target_points_mm() for line in read_plan(plan).lines])
    yield Live(coordinates, run, tables, points, merged.read_text())
    shutil.rmtree(folder, ignore_errors=True)


def _standstills(live: Live) -> np.ndarray:
    """(samples, joints, 4): pos_cmd, motor_pos_cmd, motor_offset, direction (+1/-1/0)."""
    samples = np.array(live.run.value("run")["standstills"], dtype=float)
    assert samples.ndim == 3 and samples.shape[1] == len(live.coordinates), samples.shape
    return samples


def _table_correction_mm(rows: np.ndarray, position_mm: np.ndarray, direction: np.ndarray):
    """LinuxCNC type 0: nominal - actual, interpolated, forward or reverse by direction."""
    nominal = rows[:, 0]
    forward = np.interp(position_mm, nominal, nominal - rows[:, 1])
    reverse = np.interp(position_mm, nominal, nominal - rows[:, 2])
    return np.where(direction > 0, forward, reverse)


def _servo_step_mm(merged_ini: str, joint: int) -> float:
    """The farthest the joint travels in one servo period: MAX_VELOCITY x SERVO_PERIOD, mm."""
    lines = merged_ini.splitlines()
    velocity = float(ini_value(lines, f"JOINT_{joint}", "MAX_VELOCITY"))
    return velocity * float(ini_value(lines, "EMCMOT", "SERVO_PERIOD")) * 1e-9


def _table_range_before_mm(rows: np.ndarray, stood: float, sign: float, reach_mm: float):
    """The least and greatest correction of the table (direction ``sign``) over the last
    servo period's travel before ``stood``. LinuxCNC keeps the correction of the last
    period in which it saw the joint move ("not moving, use whatever was there before",
    ``compute_screw_comp`` in src/emc/motion/control.c), which may lie that far back."""
    start = stood - sign * reach_mm
    inside = rows[(rows[:, 0] > min(start, stood)) & (rows[:, 0] < max(start, stood)), 0]
    where = np.concatenate([[start, stood], inside])
    values = _table_correction_mm(rows, where, np.full(where.shape, sign))
    return values.min(), values.max()


def test_the_program_runs_to_its_end_with_the_tables_in_the_merged_ini(live):
    program = live.run.value("run")
    print(f"{live.coordinates}: program {program['seconds']:.1f} s")
    assert program["resumes"] == 6  # one M0 per line
    assert program["feed_override"] == pytest.approx(FEED_OVERRIDE)
    assert live.run.report["state"]["enabled"], live.run.describe()
    lines = live.merged_ini.splitlines()
    for joint, axis in enumerate(live.coordinates):
        comp_file = Path(ini_value(lines, f"JOINT_{joint}", "COMP_FILE"))
        assert comp_file.is_absolute() and comp_file.name == f"{axis.lower()}.comp"
        assert ini_value(lines, f"JOINT_{joint}", "COMP_FILE_TYPE") == "0"


def test_the_applied_correction_equals_the_axis_table_at_every_standstill(live):
    samples = _standstills(live)
    deviations = []
    for joint, axis in enumerate(live.coordinates):
        position, motor, offset, direction = samples[:, joint].T
        assert np.all(offset == 0.0)  # homed where it stood: the correction alone
        known = direction != 0
        applied = motor[known] - position[known] - offset[known]
        expected = _table_correction_mm(live.tables[axis], position[known], direction[known])
        deviation = np.abs(applied - expected)
        reach_mm = _servo_step_mm(live.merged_ini, joint)
        for stood, sign, correction in zip(position[known], direction[known], applied, strict=True):
            low, high = _table_range_before_mm(live.tables[axis], stood, sign, reach_mm)
            assert low - TOLERANCE_MM <= correction <= high + TOLERANCE_MM, (
                joint, axis, stood, sign, correction, (low, high)
            )  # fmt: skip
        # the other axes' tables would not fit: the check can tell the axes apart
        for other in "XYZ".replace(axis, ""):
            wrong = _table_correction_mm(live.tables[other], position[known], direction[known])
            assert np.abs(applied - wrong).max() > 100 * TOLERANCE_MM, (joint, axis, other)
        # both directions and many positions along the axis were checked
        for sign in (1, -1):
            stood = np.unique(np.round(position[direction == sign], 3))
            assert len(stood) >= 4, (joint, axis, sign, stood)
        assert np.abs(applied).max() > 0.002  # corrections of micrometres, not zeros
        deviations.append(deviation.max())
    print(f"{live.coordinates}: {len(samples)} standstills, max deviation {max(deviations):.2e} mm")


def test_the_gantry_joints_get_the_same_y_correction(live):
    if live.coordinates != "XYYZ":
        pytest.skip("XYYZ only")
    samples = _standstills(live)
    np.testing.assert_array_equal(samples[:, 1], samples[:, 2])


def test_the_joints_stand_at_the_plans_targets_in_machine_coordinates(live):
    samples = _standstills(live)
    axes = ["XYZ".index(axis) for axis in live.coordinates]
    stood = np.zeros((len(samples), 3))
    stood[:, axes] = samples[:, :, 0]
    low = np.array([TRAVEL_MM[a][0] for a in "XYZ"])
    high = np.array([TRAVEL_MM[a][1] for a in "XYZ"])
    assert np.all((stood >= low - 1e-9) & (stood <= high + 1e-9))
    for point in live.plan_points_mm:
        gap = np.abs(stood - point).max(axis=1).min()
        assert gap < POSITION_TOLERANCE_MM, (point, gap)
