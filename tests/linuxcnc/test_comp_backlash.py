"""COMP_FILE_TYPE 0 and BACKLASH as a real headless LinuxCNC 2.9 applies them.

LinuxCNC's source (``src/emc/motion/usrmotintf.cc``, ``usrmotLoadComp``; and
``src/emc/motion/control.c``, ``compute_screw_comp``, tag v2.9.4) says: a type 0
COMP_FILE line ``nominal forward reverse`` holds *actual* positions, loaded as the
trims ``nominal - forward`` and ``nominal - reverse``; the trim of the direction of
the joint's last commanded velocity, interpolated, is added to the joint's position
command (``motor-pos-cmd = pos-cmd + backlash-filt + motor-offset``); ``BACKLASH``
is used only when a joint has no COMP_FILE (then ``+BACKLASH/2`` after a positive
move, ``-BACKLASH/2`` after a negative one). Here the real thing settles it: an
X table with a 12 um reversal, written by ``xmalign comp --controller linuxcnc
--ini`` into an INI whose ``[JOINT_0]`` keeps ``BACKLASH = 0.05``; LinuxCNC started
once with the merged INI and once with the original, X moved to table points and
between them from both sides.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_helpers import run_cli
from harness import LinuxCNCRun, SimMachine, run_linuxcnc, standard_start, write_sim_config

from xmalign.formats.error_tables import ErrorTableSet, Table, write_error_tables
from xmalign.rigid_body import MOTION_NAMES, SQUARENESS_NAMES

pytestmark = pytest.mark.linuxcnc

TRAVEL_MM = {"X": (0.0, 400.0), "Y": (0.0, 300.0), "Z": (-200.0, 0.0)}
MACHINE = {
    "name": "LinuxCNC backlash check",
    "chain": "FYXZ",
    "travel_mm": {axis: list(limits) for axis, limits in TRAVEL_MM.items()},
    "feed_mm_min": {"rapid": 8000, "measure": 2000},
    "controller": "linuxcnc",
    "receiver_offset_mm": [0, 0, -180],
}
BACKLASH_MM = 0.05
#: X's positioning error moving + (um) at the table's nodes, and the reversal (- minus +)
NODES_MM = np.linspace(0.0, 400.0, 9)
FORWARD_UM = 8.0 * np.sin(NODES_MM / 400.0 * np.pi) - 3.0
REVERSAL_UM = 12.0
#: X targets (G53), each reached from the side the previous one leaves it on
TARGETS_MM = (100.0, 275.0, 350.0, 150.0, 37.5, 250.0, 120.0)
#: agreement of the applied correction with the table's trim, mm (float trims in LinuxCNC)
TOLERANCE_MM = 1e-6


def _tables() -> ErrorTableSet:
    """Every error zero but X's positioning, +/- with the reversal (um, rad)."""
    tables = ErrorTableSet()
    zeros = np.zeros_like(NODES_MM)
    for name in MOTION_NAMES:
        low, high = TRAVEL_MM[name[2]]
        positions = np.linspace(low, high, len(NODES_MM))
        tables.tables[name] = Table(positions, zeros, zeros)
    tables.tables["EXX+"] = Table(NODES_MM, FORWARD_UM * 1e-3, zeros)
    tables.tables["EXX-"] = Table(NODES_MM, (FORWARD_UM + REVERSAL_UM) * 1e-3, zeros)
    tables.squareness = {name: (0.0, 0.0) for name in SQUARENESS_NAMES}
    return tables


def _with_backlash(ini: Path) -> None:
    text = ini.read_text()
    ini.write_text(text.replace("[JOINT_0]\n", f"[JOINT_0]\nBACKLASH = {BACKLASH_MM}\n", 1))


def _moves() -> list[dict]:
    actions = [*standard_start()]
    for number, target in enumerate(TARGETS_MM):
        actions += [
            {"op": "mdi", "gcode": f"G53 G1 F3000 X{target}"},
            {
                "op": "pins",
                "names": [f"joint.0.{pin}" for pin in ("pos-cmd", "motor-pos-cmd", "motor-offset")],
                "label": f"at{number}",
            },
        ]
    return actions


def _applied_mm(run: LinuxCNCRun) -> np.ndarray:
    """(targets, 2): X's position command and the correction LinuxCNC applied there."""
    rows = []
    for number in range(len(TARGETS_MM)):
        pins = run.value(f"at{number}")
        position = pins["joint.0.pos-cmd"]
        rows.append(
            (position, pins["joint.0.motor-pos-cmd"] - position - pins["joint.0.motor-offset"])
        )
    return np.array(rows)


def _directions() -> np.ndarray:
    """+1 where a target is reached moving +, -1 moving - (homed at 0)."""
    return np.sign(np.diff((0.0, *TARGETS_MM)))


@pytest.fixture(scope="module")
def setup() -> Iterator[dict]:
    """The tables, the sim INI with BACKLASH on joint 0, and comp --ini's files."""
    folder = Path(tempfile.mkdtemp(prefix="xmalign-lcnc-backlash-"))
    (folder / "machine.yaml").write_text(yaml.safe_dump(MACHINE))
    write_error_tables(folder / "errors.csv", _tables())
    ini = write_sim_config(folder / "config", SimMachine(travel_mm=TRAVEL_MM))
    _with_backlash(ini)
    out = folder / "comp"
    result = run_cli(
        "comp",
        *("--errors", str(folder / "errors.csv"), "--machine", str(folder / "machine.yaml")),
        *("--controller", "linuxcnc", "--ini", str(ini), "--out", str(out)),
    )
    assert result.returncode == 0, result.stderr
    folder.chmod(0o755)
    out.chmod(0o755)
    yield {"ini": ini, "merged": out / "sim-xmalign.ini", "out": out, "stderr": result.stderr}
    shutil.rmtree(folder, ignore_errors=True)


def test_comp_warns_that_linuxcnc_ignores_the_backlash(setup):
    told = " ".join(setup["stderr"].split())
    assert "[JOINT_0] BACKLASH is set: LinuxCNC ignores it once COMP_FILE is loaded" in told, told


def test_with_the_comp_file_the_type_0_trim_of_the_direction_is_applied_and_backlash_ignored(
    setup,
):
    run = run_linuxcnc(setup["merged"], _moves(), timeout_s=120)
    assert run.report is not None and run.report["state"]["enabled"], run.describe()
    applied = _applied_mm(run)
    np.testing.assert_allclose(applied[:, 0], TARGETS_MM, atol=1e-9)
    rows = np.loadtxt(setup["out"] / "x.comp", ndmin=2)
    nominal, forward, reverse = rows.T
    directions = _directions()
    assert set(directions) == {1.0, -1.0}
    expected = np.where(
        directions > 0,
        np.interp(applied[:, 0], nominal, nominal - forward),
        np.interp(applied[:, 0], nominal, nominal - reverse),
    )
    np.testing.assert_allclose(applied[:, 1], expected, atol=TOLERANCE_MM)
    # the correction is minus the error of the direction: the table, not the BACKLASH
    error_um = np.interp(applied[:, 0], NODES_MM, FORWARD_UM) + (directions < 0) * REVERSAL_UM
    np.testing.assert_allclose(applied[:, 1], -error_um * 1e-3, atol=TOLERANCE_MM)
    print(f"applied at {TARGETS_MM}: {np.round(applied[:, 1] * 1e3, 4)} um")


def test_without_a_comp_file_backlash_is_half_plus_after_a_positive_move(setup):
    run = run_linuxcnc(setup["ini"], _moves(), timeout_s=120)
    assert run.report is not None and run.report["state"]["enabled"], run.describe()
    applied = _applied_mm(run)
    np.testing.assert_allclose(applied[:, 1], _directions() * BACKLASH_MM / 2, atol=TOLERANCE_MM)
