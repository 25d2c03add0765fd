"""xmalign_volcomp in a real headless LinuxCNC: the corrections at the pins are the model's.

Each test writes a sim config (harness.py), a virtual machine's error tables and
a machine file, merges them with ``xmalign comp --controller
linuxcnc-volumetric --ini``, starts LinuxCNC on the merged INI and reads the
component's pins.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import harness
import numpy as np
import pytest
import yaml
from cli_helpers import run_cli
from harness import (
    SimMachine,
    halcompile_available,
    host_lock,
    run_linuxcnc,
    standard_start,
    write_sim_config,
)
from required_tools import skip_unless_required

from sim.machine import VirtualMachine
from xmalign.comp.linuxcnc_volumetric import (
    INSTANCE,
    TABLE_FILE,
    correction_mm,
    mean_model,
)
from xmalign.formats.error_tables import (
    ErrorTableSet,
    Table,
    read_error_tables,
    write_error_tables,
)
from xmalign.machine import parse_machine
from xmalign.rigid_body import Chain

pytestmark = pytest.mark.linuxcnc

ROOT = Path(__file__).resolve().parents[2]
COMPONENT_SOURCE = ROOT / "linuxcnc" / "xmalign_volcomp.comp"
MODULE = Path("/usr/lib/linuxcnc/modules/xmalign_volcomp.so")
#: every joint's drive answers a period late, as a real one (harness.SimMachine.drive_lag)
SIM = SimMachine(drive_lag=True)
TOOL_OFFSET_MM = [10.0, -5.0, -120.0]
#: 0.1 um, the required agreement of the pins with the model
TOLERANCE_MM = 1e-4


@dataclass(frozen=True)
class Model:
    """The rigid-body model of an error file, as xmalign.rigid_body predicts it."""

    chain: Chain
    errors: Path

    def correction(self, points_mm: np.ndarray | list[float]) -> np.ndarray:
        """Corrections at commanded points (N, 3), mm."""
        tables = mean_model(read_error_tables(self.errors))
        return correction_mm(self.chain, tables, TOOL_OFFSET_MM, points_mm)


@pytest.fixture(scope="module")
def component() -> None:
    """Build and install the component with the documented command (as root)."""
    if os.geteuid() == 0 and halcompile_available():
        with tempfile.TemporaryDirectory() as build, host_lock():
            shutil.copy(COMPONENT_SOURCE, build)
            subprocess.run(
                ["halcompile", "--install", COMPONENT_SOURCE.name],
                cwd=build,
                check=True,
                capture_output=True,
            )
    elif not MODULE.exists():
        skip_unless_required(
            "xmalign_volcomp is not installed and cannot be (not root or no halcompile)"
        )


def _machine_and_errors(
    folder: Path,
    chain: str,
    *,
    seed: int = 7,
    max_correction_um: float = 100.0,
    x_tables_to_mm: float | None = None,
) -> Model:
    """A machine file and a virtual machine's error tables (25 mm) in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    machine = {
        "name": "LinuxCNC sim",
        "chain": chain,
        "travel_mm": {axis: list(limits) for axis, limits in SIM.travel_mm.items()},
        "feed_mm_min": {"rapid": 8000, "measure": 2000},
        "controller": "linuxcnc",
        "receiver_offset_mm": [0, 0, -100],
        "cnc": {"tool_offset_mm": TOOL_OFFSET_MM, "max_correction_um": max_correction_um},
    }
    (folder / "machine.yaml").write_text(yaml.safe_dump(machine))
    tables = VirtualMachine(parse_machine(machine), seed=seed).truth_tables(25.0)
    if x_tables_to_mm is not None:
        tables = _cut_x_tables(tables, x_tables_to_mm)
    write_error_tables(folder / "errors.csv", tables)
    return Model(Chain.parse(chain), folder / "errors.csv")


def _merged(folder: Path, coordinates: str, chain: str, **machine: float) -> tuple[Path, Model]:
    """The merged INI of a sim config, and the model of the error tables it loads.

    LinuxCNC turns the machine off on a following error above 1 nm in any servo period.
    The sim config itself (uncompensated) is ``folder/sim.ini``.
    """
    ini = write_sim_config(folder, replace(SIM, coordinates=coordinates, ferror_mm=1e-6))
    model = _machine_and_errors(folder, chain, **machine)
    out = folder / "merged"
    result = run_cli(
        "comp",
        *("--errors", str(folder / "errors.csv"), "--out", str(out)),
        *("--machine", str(folder / "machine.yaml"), "--controller", "linuxcnc-volumetric"),
        *("--ini", str(ini)),
    )
    assert result.returncode == 0, result.stderr
    return out / "sim_volcomp.ini", model


def _cut_x_tables(tables: ErrorTableSet, high_mm: float) -> ErrorTableSet:
    cut = ErrorTableSet(squareness=tables.squareness)
    for name, table in tables.tables.items():
        keep = table.positions_mm <= high_mm if name[2] == "X" else slice(None)
        cut.tables[name] = Table(table.positions_mm[keep], table.values[keep], table.u95[keep])
    return cut


def _points(count: int, seed: int) -> np.ndarray:
    """Corners and seeded points across the sim's travel, (N, 3) mm."""
    low = np.array([SIM.travel_mm[a][0] for a in "XYZ"])
    high = np.array([SIM.travel_mm[a][1] for a in "XYZ"])
    inside = np.random.default_rng(seed).uniform(low, high, (count, 3))
    return np.round(np.vstack([low, high, inside]), 4)


def _goto(point: np.ndarray, label: str) -> dict:
    x, y, z = point
    return {"op": "mdi", "gcode": f"G53 G0 X{x:.4f} Y{y:.4f} Z{z:.4f}", "label": label}


def _pin_names(joints: int) -> list[str]:
    names = [f"{INSTANCE}.{pin}" for pin in ("fault", "tripped", "ok")]
    names += [f"{INSTANCE}.correction-{a}" for a in range(3)]
    for j in range(joints):
        names += [
            f"joint.{j}.pos-cmd",
            f"joint.{j}.motor-pos-cmd",
            f"{INSTANCE}.motor-pos-out-{j}",
            f"{INSTANCE}.motor-pos-fb-out-{j}",
        ]
    return names


def _program(folder: Path) -> Path:
    """Feed moves over the whole travel with an M0, in machine coordinates."""
    path = folder / "volumetric.ngc"
    path.write_text(
        "G21 G90 G40 G49 G94\n"
        "G53 G1 X400 Y300 Z-200 F30000\n"
        "G53 G1 X0 Y300 Z0\n"
        "M0\n"
        "G53 G1 X400 Y0 Z-100\n"
        "G53 G1 X150 Y150 Z-150\n"
        "M2\n"
    )
    return path


@pytest.mark.parametrize(("coordinates", "chain"), [("XYZ", "XFYZ"), ("XYYZ", "FYXZ")])
def test_corrections_at_the_pins_equal_the_model_and_add_no_following_error(
    component, linuxcnc_dir, coordinates, chain
):
    ini, volumetric = _merged(linuxcnc_dir, coordinates, chain)
    joints = len(coordinates)
    points = _points(8, seed=len(coordinates))
    actions = standard_start()
    for i, point in enumerate(points):
        actions += [
            _goto(point, f"go{i}"),
            {"op": "pins", "names": _pin_names(joints), "label": f"at{i}"},
        ]
    watch = [f"joint.{j}.f-error" for j in range(joints)]
    watch += [f"{INSTANCE}.correction-{a}" for a in range(3)] + [f"{INSTANCE}.tripped"]
    actions.append(
        {"op": "run", "program": str(_program(ini.parent)), "watch": watch, "label": "run"}
    )

    run = run_linuxcnc(ini, actions)

    expected = volumetric.correction(points)
    assert np.max(np.abs(expected)) > 0.010  # the machine's errors are tens of um
    for i, point in enumerate(points):
        pins = run.value(f"at{i}")
        assert not pins[f"{INSTANCE}.tripped"] and pins[f"{INSTANCE}.fault"] == 0
        for j, axis in enumerate(coordinates):
            a = "XYZ".index(axis)
            assert pins[f"joint.{j}.pos-cmd"] == pytest.approx(point[a], abs=1e-9)
            applied = pins[f"{INSTANCE}.motor-pos-out-{j}"] - pins[f"joint.{j}.motor-pos-cmd"]
            assert applied == pytest.approx(expected[i, a], abs=TOLERANCE_MM), (i, j)
            fed_back = pins[f"{INSTANCE}.motor-pos-fb-out-{j}"]
            assert fed_back == pytest.approx(pins[f"joint.{j}.motor-pos-cmd"], abs=1e-9)
    program = run.value("run")
    assert program["resumes"] == 1
    largest = program["max_abs"]
    assert all(largest[f"joint.{j}.f-error"] < 1e-9 for j in range(joints)), largest
    assert max(largest[f"{INSTANCE}.correction-{a}"] for a in range(3)) > 0.010
    assert largest[f"{INSTANCE}.tripped"] == 0
    assert run.report["state"]["enabled"]


#: the sim's position resolution (no encoder: a float), mm
RESOLUTION_MM = 1e-9


def _correction_pins() -> list[str]:
    return [f"{INSTANCE}.{pin}" for pin in ("target-0", "target-1", "target-2", "active")] + [
        f"{INSTANCE}.correction-{a}" for a in range(3)
    ]


def _drive_commands(joints: int) -> list[str]:
    """The smallest and largest command each drive was sent since the start."""
    return [f"drive-range-{j}.{end}" for j in range(joints) for end in ("min", "max")]


def _applied(pins: dict, coordinates: str) -> np.ndarray:
    """Correction on each joint's drive pin, mm."""
    return np.array(
        [
            pins[f"{INSTANCE}.motor-pos-out-{j}"] - pins[f"joint.{j}.motor-pos-cmd"]
            for j in range(len(coordinates))
        ]
    )


@pytest.mark.parametrize(("coordinates", "chain"), [("XYZ", "XFYZ"), ("XYYZ", "FYXZ")])
def test_no_correction_reaches_the_drives_before_homing_and_the_joints_home_as_without_it(
    component, linuxcnc_dir, coordinates, chain
):
    """Issue 22: motion.is-all-homed reads TRUE before LinuxCNC activates its joints.

    With drives that answer a period late, a correction sent then moved the homed
    motor-offsets by µm. The uncompensated sim (same drives) is the reference.
    """
    ini, volumetric = _merged(linuxcnc_dir, coordinates, chain)
    joints = len(coordinates)
    offsets = [f"joint.{j}.motor-offset" for j in range(joints)]
    home = [f"joint.{j}.pos-cmd" for j in range(joints)]

    plain = run_linuxcnc(
        linuxcnc_dir / "sim.ini",
        [*standard_start(), {"op": "pins", "names": offsets + home, "label": "homed"}],
    )
    run = run_linuxcnc(
        ini,
        [
            {"op": "pins", "names": _drive_commands(joints), "label": "start"},
            {"op": "estop_reset"},
            {"op": "machine_on"},
            {"op": "sleep", "seconds": 0.2},
            {"op": "pins", "names": _drive_commands(joints), "label": "on"},
            {"op": "home"},
            {"op": "pins", "names": offsets, "label": "homed"},
            {"op": "sleep", "seconds": 0.3},
            {"op": "pins", "names": _pin_names(joints) + _correction_pins(), "label": "after"},
        ],
    )

    for label in ("start", "on"):
        commands = run.value(label)
        assert all(value == 0.0 for value in commands.values()), (label, commands)
    reference = plain.value("homed")
    homed = run.value("homed")
    for name in offsets:
        assert homed[name] == pytest.approx(reference[name], abs=RESOLUTION_MM), (name, homed)
    at_home = np.array([[reference[f"joint.{coordinates.index(a)}.pos-cmd"] for a in "XYZ"]])
    expected = volumetric.correction(at_home)[0]
    assert np.abs(expected).max() > 0.001
    after = run.value("after")
    assert after[f"{INSTANCE}.active"]
    per_joint = [expected["XYZ".index(axis)] for axis in coordinates]
    np.testing.assert_allclose(_applied(after, coordinates), per_joint, rtol=0, atol=TOLERANCE_MM)


def test_the_correction_is_held_in_estop_and_returns_to_zero_when_the_joints_are_unhomed(
    component, linuxcnc_dir
):
    ini, volumetric = _merged(linuxcnc_dir, "XYZ", "XFYZ")
    point = np.array([250.0, 120.0, -80.0])
    names = _pin_names(3) + _correction_pins()
    run = run_linuxcnc(
        ini,
        [
            *standard_start(),
            _goto(point, "go"),
            {"op": "pins", "names": names, "label": "on"},
            {"op": "estop", "label": "estop"},
            {"op": "sleep", "seconds": 0.2},
            {"op": "pins", "names": names, "label": "off"},
            {"op": "estop_reset"},
            {"op": "machine_on"},
            {"op": "unhome", "label": "unhome"},
            {"op": "sleep", "seconds": 0.3},
            {"op": "pins", "names": names, "label": "unhomed"},
        ],
    )

    expected = volumetric.correction(point)[0]
    assert np.abs(expected).max() > 0.001
    on, off, unhomed = (run.value(label) for label in ("on", "off", "unhomed"))
    np.testing.assert_allclose(_applied(on, "XYZ"), expected, rtol=0, atol=TOLERANCE_MM)
    held = [on[f"{INSTANCE}.correction-{a}"] for a in range(3)]
    assert on[f"{INSTANCE}.active"] and not off[f"{INSTANCE}.active"]
    assert [off[f"{INSTANCE}.correction-{a}"] for a in range(3)] == held
    assert not unhomed[f"{INSTANCE}.active"]
    for a in range(3):
        assert unhomed[f"{INSTANCE}.correction-{a}"] == 0.0
        assert unhomed[f"{INSTANCE}.target-{a}"] == 0.0
    np.testing.assert_array_equal(_applied(unhomed, "XYZ"), 0.0)
    assert run.report["state"]["homed"] == [False] * 3


def test_leaving_the_tables_trips_the_estop_and_holds_the_correction(component, linuxcnc_dir):
    # the X tables end at 300 mm of the 400 mm travel
    ini, volumetric = _merged(linuxcnc_dir, "XYYZ", "FYXZ", x_tables_to_mm=300.0)
    inside, back = np.array([200.0, 100.0, -50.0]), np.array([100.0, 120.0, -60.0])
    names = _pin_names(4)
    run = run_linuxcnc(
        ini,
        [
            *standard_start(),
            _goto(inside, "inside"),
            {"op": "mdi", "gcode": "G53 G0 X350", "label": "leave"},
            {"op": "pins", "names": names, "label": "outside"},
            {"op": "estop_reset", "label": "reset"},
            {"op": "machine_on", "label": "on"},
            {"op": "pins", "names": names, "label": "reset-outside"},
            _goto(back, "back"),
            {"op": "pins", "names": names, "label": "back-inside"},
        ],
    )

    def model(point: list[float] | np.ndarray) -> np.ndarray:
        return volumetric.correction(point)[0]

    outside = run.value("outside")
    assert outside[f"{INSTANCE}.fault"] == 1 and outside[f"{INSTANCE}.tripped"]
    assert outside["joint.0.pos-cmd"] > 300.0
    held = np.array([outside[f"{INSTANCE}.correction-{a}"] for a in range(3)])
    # held where the tables end (one servo period of travel away at most)
    np.testing.assert_allclose(held, model([300.0, 100.0, -50.0]), atol=1e-3)
    reset = run.value("reset-outside")
    assert not reset[f"{INSTANCE}.tripped"] and reset[f"{INSTANCE}.fault"] == 1
    np.testing.assert_array_equal([reset[f"{INSTANCE}.correction-{a}"] for a in range(3)], held)
    pins = run.value("back-inside")
    assert pins[f"{INSTANCE}.fault"] == 0 and not pins[f"{INSTANCE}.tripped"]
    for j, axis in enumerate("XYYZ"):
        applied = pins[f"{INSTANCE}.motor-pos-out-{j}"] - pins[f"joint.{j}.motor-pos-cmd"]
        assert applied == pytest.approx(model(back)["XYZ".index(axis)], abs=TOLERANCE_MM)
    assert run.report["state"]["enabled"]


def test_a_correction_beyond_the_bound_trips_the_estop_before_it_is_applied(
    component, linuxcnc_dir
):
    probe = _machine_and_errors(linuxcnc_dir / "probe", "XFYZ")
    grid = _points(100, seed=5)
    largest = np.abs(probe.correction(grid)).max(1)
    worst = grid[np.argmax(largest)]
    bound_um = float(0.8 * largest.max() * 1e3)
    ini, _ = _merged(linuxcnc_dir, "XYZ", "XFYZ", max_correction_um=bound_um)
    run = run_linuxcnc(
        ini,
        [
            *standard_start(),
            {"op": "mdi", "gcode": "G53 G0 X{:.4f} Y{:.4f} Z{:.4f}".format(*worst), "label": "go"},
            {"op": "pins", "names": _pin_names(3), "label": "stopped"},
        ],
    )
    pins = run.value("stopped")
    assert pins[f"{INSTANCE}.fault"] == 2 and pins[f"{INSTANCE}.tripped"]
    applied = [pins[f"{INSTANCE}.correction-{a}"] for a in range(3)]
    assert 0.5 * bound_um * 1e-3 < np.max(np.abs(applied)) <= bound_um * 1e-3
    assert run.report["state"]["estop"]


def test_a_damaged_table_file_stops_linuxcnc_with_the_file_and_the_reason(component, linuxcnc_dir):
    ini, _ = _merged(linuxcnc_dir, "XYZ", "FYXZ")
    table = ini.parent / TABLE_FILE
    lines = table.read_text().splitlines(keepends=True)
    row = next(i for i, line in enumerate(lines) if line.startswith("table EYX")) + 3
    lines[row] = lines[row].replace(" ", " 1", 1)  # one value changed by a digit
    table.write_text("".join(lines))

    run = run_linuxcnc(ini, standard_start())

    assert run.report is None, "the display ran: LinuxCNC started with a damaged table"
    assert f"xmalign_volcomp: {table.resolve()} line {len(lines)}: CRC-32 mismatch" in run.output
    assert run.returncode != 0


UPSTREAM_GANTRY = Path("/usr/share/doc/linuxcnc/examples/sample-configs/sim/axis/gantry")


def test_merge_of_linuxcncs_own_gantry_sample_config(component, linuxcnc_dir):
    """LinuxCNC's gantry_mm sample (HAL file as shipped; INI: our display, faster moves)."""
    if not (UPSTREAM_GANTRY / "gantry_mm.hal").exists():
        skip_unless_required("LinuxCNC's sample configs are missing")
    for name in ("gantry_mm.hal", "gantry_mm.tbl"):
        shutil.copy(UPSTREAM_GANTRY / name, linuxcnc_dir)
    ini_text = (UPSTREAM_GANTRY / "gantry_mm.ini").read_text()
    ini_text = ini_text.replace("DISPLAY = axis", "DISPLAY = ./display.py")
    ini_text = re.sub(r"(?m)^INTRO_GRAPHIC = .*$", "", ini_text)  # a Tk splash: no X here
    for key in ("MAX_VELOCITY", "MAX_LINEAR_VELOCITY", "DEFAULT_LINEAR_VELOCITY"):
        ini_text = re.sub(rf"(?m)^{key} = .*$", f"{key} = 1000", ini_text)
    ini_text = re.sub(r"(?m)^(MAX|DEFAULT)(_LINEAR)?_ACCELERATION = .*$", r"\g<0>0", ini_text)
    (linuxcnc_dir / "gantry_mm.ini").write_text(ini_text)
    shutil.copy(harness.DISPLAY_SCRIPT, linuxcnc_dir / "display.py")
    (linuxcnc_dir / "display.py").chmod(0o755)
    machine = {
        "name": "LinuxCNC gantry_mm sample",
        "chain": "FYXZ",
        "travel_mm": {"X": [0, 400], "Y": [0, 2000], "Z": [0, 100]},
        "feed_mm_min": {"rapid": 8000, "measure": 2000},
        "controller": "linuxcnc",
        "receiver_offset_mm": [0, 0, -100],
        "cnc": {"tool_offset_mm": TOOL_OFFSET_MM},
    }
    (linuxcnc_dir / "machine.yaml").write_text(yaml.safe_dump(machine))
    truth = VirtualMachine(parse_machine(machine), seed=11)
    write_error_tables(linuxcnc_dir / "errors.csv", truth.truth_tables(50.0))
    out = linuxcnc_dir / "merged"
    result = run_cli(
        "comp",
        *("--errors", str(linuxcnc_dir / "errors.csv"), "--out", str(out)),
        *("--machine", str(linuxcnc_dir / "machine.yaml"), "--controller", "linuxcnc-volumetric"),
        *("--ini", str(linuxcnc_dir / "gantry_mm.ini")),
    )
    assert result.returncode == 0, result.stderr
    volumetric = Model(Chain.parse("FYXZ"), linuxcnc_dir / "errors.csv")
    points = np.array([[350.0, 1800.0, 20.0], [50.0, 700.0, 90.0]])
    actions = standard_start()
    for i, point in enumerate(points):
        actions += [
            _goto(point, f"go{i}"),
            {"op": "pins", "names": _pin_names(4), "label": f"at{i}"},
        ]

    run = run_linuxcnc(out / "gantry_mm_volcomp.ini", actions)

    expected = volumetric.correction(points)
    assert np.abs(expected).max() > 0.010
    for i in range(len(points)):
        pins = run.value(f"at{i}")
        for j, axis in enumerate("XYYZ"):
            applied = pins[f"{INSTANCE}.motor-pos-out-{j}"] - pins[f"joint.{j}.motor-pos-cmd"]
            assert applied == pytest.approx(expected[i, "XYZ".index(axis)], abs=TOLERANCE_MM)
