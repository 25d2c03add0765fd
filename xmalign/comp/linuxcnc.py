"""LinuxCNC: screw compensation files (``COMP_FILE``, ``COMP_FILE_TYPE = 0``) per joint.

From the LinuxCNC INI configuration manual, section ``[JOINT_<num>]``, and the
sample file ``screwcompX.dat`` LinuxCNC ships (kept in tests):

- ``COMP_FILE`` is a text file of triplets, one per line, separated by
  spaces, in machine units, in ascending order of the first value: the nominal
  (commanded) joint position, then two values that depend on ``COMP_FILE_TYPE``;
- type 0: the second value is the *actual* position when the joint moves in
  the positive direction, the third the actual position moving negative;
- at most 256 triplets per joint; reading stops at the first line that is not
  three numbers (so the file has no comment line).

So LinuxCNC takes measured positions, not corrections: ``nominal + E+`` and
``nominal + E-`` of the fitted per-axis pitch table (bidirectional where the
error file is). Nominal positions are joint (machine) coordinates, in the
INI's ``[TRAJ] LINEAR_UNITS`` (mm without an INI). LinuxCNC ignores a joint's
``BACKLASH`` once it has a COMP_FILE (``compute_screw_comp`` in
src/emc/motion/control.c, v2.9.4), so the BACKLASH active while measuring
(``cnc.backlash_um``) goes into the columns as LinuxCNC applied it: ``-B/2``
forward, ``+B/2`` reverse (docs/controllers.md; tests/linuxcnc/test_comp_backlash.py). Joints map
to axes as the machine file's ``cnc.joints`` says, else as the INI's trivkins
``coordinates=`` / ``[TRAJ] COORDINATES``, else X, Y, Z: every joint of an axis
(both Y joints of a gantry) gets that axis's table.

``xmalign comp --ini MACHINE.ini`` writes a merged copy of the INI with
``COMP_FILE`` and ``COMP_FILE_TYPE`` inside the existing ``[JOINT_n]``
sections (LinuxCNC reads only the first section of a name, so appended
sections would be ignored silently).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from xmalign.comp.common import Comment, Loading, check_count, has_reversal, with_history
from xmalign.comp.fit import PITCH, CompensationFit, CompModel
from xmalign.errors import InputError
from xmalign.formats.common import read_text
from xmalign.formats.provenance import FileSource
from xmalign.machine import AXES, Machine

NAME = "linuxcnc"
MODEL = CompModel(pairs=PITCH, directional=True)
MAX_TRIPLETS = 256
FORMAT = "xmalign.comp.linuxcnc/1"
#: INI files take ``#`` comments; a COMP_FILE takes none (LinuxCNC 2.9 stops reading it
#: at the first line that is not three numbers), so each gets ``x.comp.history``.
COMMENTS = {"*.ini": Comment("# ")}
_SECTION = re.compile(r"^\s*\[([^\]]+)\]")
_KEY = re.compile(r"^\s*([A-Za-z0-9_]+)\s*=\s*(.*?)\s*$")


def render_axis(
    fit: CompensationFit, axis: str, backlash_um: float = 0.0, units_per_mm: float = 1.0
) -> str:
    """The comp file of the joints of ``axis``: ``nominal forward reverse`` per line.

    In machine units (``units_per_mm``, [TRAJ] LINEAR_UNITS). ``backlash_um``: the
    control's BACKLASH active during the measurement (``cnc.backlash_um``), which
    LinuxCNC applied as +B/2 moving + and -B/2 moving - and ignores once a COMP_FILE
    is loaded: the columns carry it (actual - B/2 forward, actual + B/2 reverse).
    """
    positions, forward = fit.table(axis, axis, "+")
    _, reverse = fit.table(axis, axis, "-")
    check_count(len(positions), MAX_TRIPLETS, f"the {axis} joints", "LinuxCNC")
    half_mm = backlash_um * 1e-3 / 2
    digits = 6 if units_per_mm >= 1.0 else 8  # 1e-8 inch = 0.25 nm
    rows = np.column_stack(
        [positions, positions + forward - half_mm, positions + reverse + half_mm]
    )
    lines = [" ".join(f"{value:.{digits}f}" for value in row) for row in rows * units_per_mm]
    return "\n".join(lines) + "\n"


def comp_file(axis: str) -> str:
    return f"{axis.lower()}.comp"


def render(
    fit: CompensationFit,
    machine: Machine,
    joints: list[str] | None = None,
    units_per_mm: float = 1.0,
) -> dict[str, str]:
    """File name -> text of one comp file per axis (machine units, ``units_per_mm``) and
    the keys for each joint."""
    files = {
        comp_file(axis): render_axis(fit, axis, machine.cnc.backlash(axis) or 0.0, units_per_mm)
        for axis in AXES
    }
    keys = render_keys(list(joints or machine.cnc.joints or AXES))
    notes = "\n".join(loading(fit, machine).lines("# "))
    files["joints.ini"] = keys.replace("\n\n", f"\n{notes}\n\n", 1)
    return with_history(files, FORMAT, fit.sources, COMMENTS)


def loading(fit: CompensationFit, machine: Machine) -> Loading:
    """Reversal and the check on the machine (the format is LinuxCNC's own, tested live)."""
    carried = [axis for axis in AXES if has_reversal(fit, axis)]
    folded = {axis: um for axis in AXES if (um := machine.cnc.backlash(axis))}
    reversal = [
        f"the COMP_FILE reverse column carries the reversal of {', '.join(carried)}"
        if carried
        else "no direction data: forward and reverse columns are equal"
    ]
    if folded:
        reversal.append(
            "the columns carry the BACKLASH active while measuring (cnc.backlash_um "
            + ", ".join(f"{axis} {um:g} um" for axis, um in folded.items())
            + ") as LinuxCNC applied it, +B/2 moving + and -B/2 moving -"
        )
    reversal.append(
        "LinuxCNC ignores BACKLASH in a [JOINT_n] section with a COMP_FILE: set it to 0"
        " there (one that was active while measuring belongs in cnc.backlash_um)"
    )
    return Loading(
        reversal="; ".join(reversal),
        check=(
            "after homing, move each joint to a table point in both directions and read"
            " joint.N.backlash-filt (halcmd getp): it must equal nominal minus actual of the"
            " table for that direction"
        ),
        warnings=fit.warnings,
    )


def render_keys(joints: list[str]) -> str:
    """The keys to put into each existing ``[JOINT_n]`` section (not to append)."""
    out = [
        "# xmalign: put these keys INTO the existing [JOINT_n] sections of the INI",
        "# (LinuxCNC reads only the first section of a name: appended sections are ignored);",
        "# or let `xmalign comp --ini MACHINE.ini` write a merged copy.",
    ]
    for number, axis in enumerate(joints):
        out += ["", f"[JOINT_{number}]", f"COMP_FILE = {comp_file(axis)}", "COMP_FILE_TYPE = 0"]
    return "\n".join(out) + "\n"


def _sections(lines: list[str]) -> dict[str, tuple[int, int]]:
    """Section name (upper case) -> (header line, end line) of its first occurrence."""
    found: dict[str, tuple[int, int]] = {}
    headers = [
        (i, m.group(1).strip().upper())
        for i, line in enumerate(lines)
        if (m := _SECTION.match(line))
    ]
    for index, (start, name) in enumerate(headers):
        end = headers[index + 1][0] if index + 1 < len(headers) else len(lines)
        found.setdefault(name, (start, end))
    return found


def ini_value(lines: list[str], section: str, key: str) -> str | None:
    """The first value of ``key`` in the first ``[section]``, or None."""
    span = _sections(lines).get(section.upper())
    if span is None:
        return None
    for line in lines[span[0] + 1 : span[1]]:
        match = _KEY.match(line)
        if match and match.group(1).upper() == key.upper():
            return match.group(2)
    return None


def joints_of_ini(lines: list[str], source: str) -> list[str] | None:
    """Joint axes from trivkins ``coordinates=`` or ``[TRAJ] COORDINATES`` (None if neither)."""
    kinematics = ini_value(lines, "KINS", "KINEMATICS") or ""
    match = re.search(r"coordinates=([A-Za-z]+)", kinematics)
    letters = (
        match.group(1)
        if match
        else (ini_value(lines, "TRAJ", "COORDINATES") or "").replace(" ", "")
    )
    if not letters:
        return None
    joints = list(letters.upper())
    if set(joints) != set(AXES):
        raise InputError(
            f"{source}: joints {''.join(joints)} must give X, Y and Z"
            " (xmalign compensates linear XYZ machines)"
        )
    return joints


def resolve_joints(machine: Machine, ini_lines: list[str] | None, source: str) -> list[str]:
    """Joint axes: machine file, else INI, else X, Y, Z; the two must agree when both are given."""
    from_ini = joints_of_ini(ini_lines, source) if ini_lines is not None else None
    from_machine = machine.cnc.joints
    if from_machine and from_ini and list(from_machine) != from_ini:
        raise InputError(
            f"{source}: the INI's joints {''.join(from_ini)} differ from the machine file's"
            f" cnc.joints {''.join(from_machine)}"
        )
    return list(from_machine or from_ini or AXES)


def absolute_path(value: str, folder: Path) -> str:
    """A relative path that names an existing file or folder in ``folder`` made absolute."""
    if not value or " " in value or Path(value).is_absolute() or ":" in value:
        return value
    candidate = folder / value
    return str(candidate.resolve()) if candidate.exists() else value


def check_joint_sections(
    lines: list[str], joints: list[str], source: str
) -> dict[str, tuple[int, int]]:
    """The INI's sections (:func:`_sections`), refused unless each joint has its own.

    Raises
    ------
    InputError
        Naming ``source``: ``[KINS] JOINTS`` is not the number of ``joints``, or a
        ``[JOINT_n]`` section is missing.
    """
    sections = _sections(lines)
    count = ini_value(lines, "KINS", "JOINTS")
    if count is not None and count.strip().isdigit() and int(count) != len(joints):
        raise InputError(
            f"{source}: [KINS] JOINTS = {count} but {len(joints)} joints are mapped"
            f" ({''.join(joints)})"
        )
    missing = [n for n in range(len(joints)) if f"JOINT_{n}" not in sections]
    if missing:
        raise InputError(f"{source}: no [JOINT_{missing[0]}] section to put COMP_FILE into")
    return sections


#: [TRAJ] LINEAR_UNITS by name: machine units per mm (LinuxCNC 2.9, src/emc/ini/emcIniFile.cc;
#: a number is taken as units per mm, as ``loadTraj`` in src/emc/ini/initraj.cc reads it)
LINEAR_UNITS = {"mm": 1.0, "metric": 1.0, "in": 1 / 25.4, "inch": 1 / 25.4, "imperial": 1 / 25.4}


def units_per_mm(lines: list[str], source: str) -> float:
    """Machine units per mm of the INI's ``[TRAJ] LINEAR_UNITS`` (mm when it is not given).

    Raises
    ------
    InputError
        Naming the INI: neither a name LinuxCNC knows nor a positive number.
    """
    value = ini_value(lines, "TRAJ", "LINEAR_UNITS")
    if value is None:
        return 1.0
    if value.lower() in LINEAR_UNITS:
        return LINEAR_UNITS[value.lower()]
    try:
        number = float(value)
    except ValueError:
        number = 0.0
    if not 0.0 < number < float("inf"):
        raise InputError(
            f"{source}: [TRAJ] LINEAR_UNITS = {value}: not one of {', '.join(LINEAR_UNITS)}"
            " nor a number of units per mm"
        )
    return number


@dataclass(frozen=True)
class MachineIni:
    """A LinuxCNC INI read for ``comp --ini``: its text, the axis of each joint and its
    machine units (the COMP_FILE's and BACKLASH's), units per mm."""

    path: Path
    text: str
    joints: list[str]
    units_per_mm: float

    @property
    def merged_name(self) -> str:
        """The merged copy's file name: ``MACHINE.ini`` -> ``MACHINE-xmalign.ini``."""
        return f"{self.path.stem}-xmalign{self.path.suffix}"


def read_machine_ini(machine: Machine, path: Path) -> MachineIni:
    """The INI at ``path`` with its joints and units resolved and checked (before any fit).

    Raises
    ------
    InputError
        Naming the INI: unreadable, joints that are not X, Y and Z or that differ from
        ``cnc.joints``, a missing ``[JOINT_n]`` section (:func:`check_joint_sections`),
        unknown ``LINEAR_UNITS``.
    """
    text = read_text(path)
    lines = text.splitlines()
    joints = resolve_joints(machine, lines, str(path))
    check_joint_sections(lines, joints, str(path))
    return MachineIni(path, text, joints, units_per_mm(lines, str(path)))


def ini_files(
    fit: CompensationFit, machine: Machine, ini: MachineIni, out_dir: Path
) -> dict[str, str]:
    """File name -> text: the comp files for ``ini``'s joints in its machine units and its
    merged copy, whose ``COMP_FILE`` keys name the comp files in ``out_dir`` (history: the
    tables and the INI)."""
    files = render(fit, machine, ini.joints, ini.units_per_mm)
    inputs = (*fit.sources, FileSource.of("ini", ini.path))
    files[ini.merged_name] = merge_ini(
        ini.text, ini.joints, out_dir, str(ini.path), ini.path.resolve().parent, inputs
    )
    return files


def backlash_joints(text: str, joints: list[str]) -> dict[int, float]:
    """Joint number -> the non-zero ``BACKLASH`` its section sets (machine units)."""
    lines = text.splitlines()
    found = {}
    for number in range(len(joints)):
        value = ini_value(lines, f"JOINT_{number}", "BACKLASH")
        try:
            if value is not None and float(value) != 0.0:
                found[number] = float(value)
        except ValueError:
            continue
    return found


def backlash_warnings(ini: MachineIni, machine: Machine) -> list[str]:
    """A warning per joint whose non-zero ``BACKLASH`` (which LinuxCNC ignores once a
    ``COMP_FILE`` is loaded, ``compute_screw_comp`` in src/emc/motion/control.c) is not
    the machine file's ``cnc.backlash_um`` the tables carry."""
    warnings = []
    for joint, value in backlash_joints(ini.text, ini.joints).items():
        axis, um = ini.joints[joint], value / ini.units_per_mm * 1e3
        given = machine.cnc.backlash(axis)
        where = f"{ini.path}: [JOINT_{joint}] BACKLASH = {value:g} ({um:g} um)"
        if given is None:
            warnings.append(
                f"{where}: LinuxCNC ignores it once COMP_FILE is loaded; if it was active while"
                f" measuring, give cnc.backlash_um {{{axis}: {um:g}}} and run comp again so that"
                " the tables carry it"
            )
        elif abs(given - um) > 1e-3:  # 1 nm: an inch INI rounds
            warnings.append(
                f"{where} is not cnc.backlash_um {axis} {given:g} um, which the tables carry:"
                " give the one that was active while measuring"
            )
    return warnings


def merge_ini(
    text: str,
    joints: list[str],
    folder: Path,
    source: str,
    ini_folder: Path | None = None,
    inputs: Sequence[FileSource] = (),
) -> str:
    """The INI with ``COMP_FILE`` (absolute paths in ``folder``) in each ``[JOINT_n]`` section.

    Existing ``COMP_FILE`` / ``COMP_FILE_TYPE`` keys of those sections are replaced;
    everything else is kept as it was, except that with ``ini_folder`` (the
    original INI's folder) every relative path naming an existing file there
    (HAL files, the display, the tool table) is made absolute, so the copy
    can live in another folder. InputError naming the INI when a joint's
    section is missing. The copy starts with its history (``#`` lines: ``inputs``, the
    INI and the error tables, hashed).
    """
    lines = text.splitlines()
    sections = check_joint_sections(lines, joints, source)
    inserts: dict[int, list[str]] = {}
    dropped: set[int] = set()
    for number, axis in enumerate(joints):
        start, end = sections[f"JOINT_{number}"]
        for index in range(start + 1, end):
            match = _KEY.match(lines[index])
            if match and match.group(1).upper() in ("COMP_FILE", "COMP_FILE_TYPE"):
                dropped.add(index)
        last = max(
            (i for i in range(start, end) if lines[i].strip() and i not in dropped), default=start
        )
        inserts[last] = [
            f"COMP_FILE = {(folder / comp_file(axis)).resolve()}",
            "COMP_FILE_TYPE = 0",
        ]
    out = []
    for index, line in enumerate(lines):
        if index not in dropped:
            out.append(_absolute_line(line, ini_folder) if ini_folder is not None else line)
        out.extend(inserts.get(index, []))
    merged = "\n".join(out) + "\n"
    return with_history({"merged.ini": merged}, FORMAT, inputs, COMMENTS)["merged.ini"]


def _absolute_line(line: str, folder: Path) -> str:
    match = _KEY.match(line)
    if match is None or line.lstrip().startswith(("#", ";")):
        return line
    absolute = absolute_path(match.group(2), folder)
    return line if absolute == match.group(2) else f"{match.group(1)} = {absolute}"
