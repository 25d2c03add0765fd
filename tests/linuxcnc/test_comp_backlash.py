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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml
from cli_helpers import run_cli
from harness import SimMachine, run_linuxcnc, standard_start, write_sim_config

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


def _with_backlash(ini: Path, units_per_mm: float) -> None:
    text = ini.read_text()
    backlash = f"BACKLASH = {BACKLASH_MM * units_per_mm:.9f}"
    ini.write_text(text.replace("[JOINT_0]\n", f"[JOINT_0]\n{backlash}\n", 1))


def _moves() -> list[dict]:
    actions = [*standard_start()]
    for number, target in enumerate(TARGETS_MM):
        actions += [
            {"op": "mdi", "gcode": f"G21 G53 G1 F3000 X{target}"},
            {
                "op": "pins",
                "names": [f"joint.0.{pin}" for pin in ("pos-cmd", "motor-pos-cmd", "motor-offset")],
                "label": f"at{number}",
            },
        ]
    return actions


@dataclass(frozen=True)
class Config:
    """One comp --ini: the INI (BACKLASH on joint 0), its merged copy, what comp said."""

    ini: Path
    merged: Path
    stderr: str
    units_per_mm: float

    def applied_mm(self, ini: Path) -> np.ndarray:
        """(targets, 2): X's position command and the correction LinuxCNC applied there
        (``motor-pos-cmd - pos-cmd - motor-offset``), started with ``ini``, in mm."""
        run = run_linuxcnc(ini, _moves(), timeout_s=120)
        assert run.report is not None and run.report["state"]["enabled"], run.describe()
        rows = []
        for number in range(len(TARGETS_MM)):
            pins = run.value(f"at{number}")
            position = pins["joint.0.pos-cmd"]
            correction = pins["joint.0.motor-pos-cmd"] - position - pins["joint.0.motor-offset"]
            rows.append((position, correction))
        return np.array(rows) / self.units_per_mm

    def comp_rows_mm(self) -> np.ndarray:
        """x.comp's rows (nominal, forward, reverse), mm."""
        return np.loadtxt(self.merged.parent / "x.comp", ndmin=2) / self.units_per_mm


def _directions() -> np.ndarray:
    """+1 where a target is reached moving +, -1 moving - (homed at 0)."""
    return np.sign(np.diff((0.0, *TARGETS_MM)))


def _minus_error_mm(position_mm: np.ndarray) -> np.ndarray:
    """Minus X's error of the direction each target is reached in, mm."""
    error_um = np.interp(position_mm, NODES_MM, FORWARD_UM) + (_directions() < 0) * REVERSAL_UM
    return -error_um * 1e-3


#: name -> the machine file's cnc section and the INI's units
CASES = {
    "plain": ({}, "mm"),
    "folded": ({"backlash_um": {"X": BACKLASH_MM * 1e3}}, "mm"),
    "inch": ({"backlash_um": {"X": BACKLASH_MM * 1e3}}, "inch"),
}


@pytest.fixture(scope="module")
def configs() -> Iterator[dict[str, Config]]:
    """The tables and, per case, a sim INI with BACKLASH on joint 0 and comp --ini's files."""
    folder = Path(tempfile.mkdtemp(prefix="xmalign-lcnc-backlash-"))
    write_error_tables(folder / "errors.csv", _tables())
    found = {}
    for name, (cnc, units) in CASES.items():
        case = folder / name
        case.mkdir()
        (case / "machine.yaml").write_text(yaml.safe_dump({**MACHINE, "cnc": cnc}))
        sim = SimMachine(travel_mm=TRAVEL_MM, linear_units=units)
        ini = write_sim_config(case / "config", sim)
        _with_backlash(ini, sim.units_per_mm)
        result = run_cli(
            "comp",
            *("--errors", str(folder / "errors.csv"), "--machine", str(case / "machine.yaml")),
            *("--controller", "linuxcnc", "--ini", str(ini), "--out", str(case / "comp")),
        )
        assert result.returncode == 0, result.stderr
        for path in (folder, case, case / "comp"):
            path.chmod(0o755)
        told = " ".join(result.stderr.split())
        found[name] = Config(ini, case / "comp" / "sim-xmalign.ini", told, sim.units_per_mm)
    yield found
    shutil.rmtree(folder, ignore_errors=True)


def test_comp_warns_that_linuxcnc_ignores_a_backlash_the_tables_do_not_carry(configs):
    told = configs["plain"].stderr
    assert "[JOINT_0] BACKLASH = 0.05 (50 um): LinuxCNC ignores it once COMP_FILE" in told, told
    assert "give cnc.backlash_um {X: 50}" in told
    assert "BACKLASH" not in configs["folded"].stderr and "BACKLASH" not in configs["inch"].stderr


def test_with_the_comp_file_the_type_0_trim_of_the_direction_is_applied_and_backlash_ignored(
    configs,
):
    config = configs["plain"]
    applied = config.applied_mm(config.merged)
    np.testing.assert_allclose(applied[:, 0], TARGETS_MM, atol=1e-9)
    nominal, forward, reverse = config.comp_rows_mm().T
    directions = _directions()
    assert set(directions) == {1.0, -1.0}
    expected = np.where(
        directions > 0,
        np.interp(applied[:, 0], nominal, nominal - forward),
        np.interp(applied[:, 0], nominal, nominal - reverse),
    )
    np.testing.assert_allclose(applied[:, 1], expected, atol=TOLERANCE_MM)
    # the correction is minus the error of the direction: the table, not the BACKLASH
    np.testing.assert_allclose(applied[:, 1], _minus_error_mm(applied[:, 0]), atol=TOLERANCE_MM)
    print(f"applied at {TARGETS_MM}: {np.round(applied[:, 1] * 1e3, 4)} um")


def test_without_a_comp_file_backlash_is_half_plus_after_a_positive_move(configs):
    config = configs["plain"]
    applied = config.applied_mm(config.ini)
    np.testing.assert_allclose(applied[:, 1], _directions() * BACKLASH_MM / 2, atol=TOLERANCE_MM)


@pytest.mark.parametrize("name", ["folded", "inch"])
def test_cnc_backlash_um_in_the_tables_applies_what_backlash_did_and_the_table(configs, name):
    """The BACKLASH active while measuring, given as cnc.backlash_um, is applied as LinuxCNC's
    own BACKLASH applied it, on top of the table; an inch INI gets its table in inches."""
    config = configs[name]
    applied = config.applied_mm(config.merged)
    np.testing.assert_allclose(applied[:, 0], TARGETS_MM, atol=1e-6)
    expected = _minus_error_mm(applied[:, 0]) + _directions() * BACKLASH_MM / 2
    np.testing.assert_allclose(applied[:, 1], expected, atol=TOLERANCE_MM)
