"""LinuxCNC volumetric compensation: the table file of ``xmalign_volcomp`` and the INI/HAL merge.

The HAL component ``linuxcnc/xmalign_volcomp.comp`` applies the whole rigid-body
model (18 error motions, 3 squareness errors, the chain, the tool offset) to
the commanded tool point of a trivkins machine. This module writes what it
reads (docs/linuxcnc-volumetric.md describes the file) and a merged copy of
the user's INI and HAL files that loads and wires it:

- each HAL file that names ``joint.N.motor-pos-cmd`` (the drive command),
  ``joint.N.motor-pos-fb`` (the drive feedback) or ``iocontrol.0.emc-enable-in``
  (the E-stop chain) is copied with those pins replaced by the component's
  ``motor-pos-out-N``, ``motor-pos-fb-in-N`` and ``enable-in``; the first copy
  loads the component, its ``feedback`` function goes into the servo thread
  right before ``motion-controller`` and its ``command`` function right after;
- a last HAL file wires the motion controller's side: ``joint.N.pos-cmd``,
  ``joint.N.motor-pos-cmd``, ``joint.N.motor-pos-fb``, ``joint.N.homed``,
  ``motion.is-all-homed``, ``motion.motion-enabled`` and
  ``iocontrol.0.emc-enable-in``;
- the INI copy names the copies and the new HAL file; its other relative
  paths that name an existing file are made absolute, so the copy may live in
  another folder.
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from xmalign.comp import linuxcnc
from xmalign.comp.common import Comment, table_sources, with_history
from xmalign.errors import FormatError, InputError
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.formats.provenance import FileSource
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.rigid_body import (
    AXES,
    MOTION_NAMES,
    SQUARENESS_NAMES,
    Chain,
    ErrorTables,
    deviation,
)

NAME = "linuxcnc-volumetric"
COMPONENT = "xmalign_volcomp"
INSTANCE = "xmalign-volcomp.0"
TABLE_FILE = "xmalign_volcomp.tbl"
WIRING_FILE = "xmalign_volcomp.hal"
FORMAT_LINE = "xmalign-volcomp 1"
#: The history of the merged files: ``#`` comments in the INI and HAL copies; the table
#: file (its lines have a fixed length in the component) gets its ``.history``.
FORMAT = "xmalign.comp.linuxcnc-volumetric/1"
COMMENTS = {"*.hal": Comment("# "), "*.ini": Comment("# ")}
MAX_POINTS = 4096
#: Fixed-point steps of ``c = -dp(k + c)``, as the component takes them.
ITERATIONS = 3


# -- the table file ----------------------------------------------------------------------


@dataclass(frozen=True)
class VolumetricTable:
    """What the component reads: the model, the chain's lever arms, joints and bound."""

    model: ErrorTables
    chain: Chain
    coordinates: str
    tool_offset_mm: Vec
    max_correction_um: float

    def coverage_mm(self, axis: str) -> tuple[float, float]:
        """The range of ``axis`` that all six of its tables cover, mm."""
        names = [n for n in MOTION_NAMES if n[2] == axis]
        low = max(self.model.tables[n][0][0] for n in names)
        high = min(self.model.tables[n][0][-1] for n in names)
        return float(low), float(high)


def _file_value(name: str, value: float) -> float:
    """mm -> um for translations, rad -> urad for rotations."""
    return value * (1e3 if name[1] in "XYZ" else 1e6)


def mean_model(tables: ErrorTableSet) -> ErrorTables:
    """The 18 tables as one model: the mean table, or the mean of ``+`` and ``-``."""
    chosen = {}
    for name in MOTION_NAMES:
        forward, reverse = tables.tables.get(name + "+"), tables.tables.get(name + "-")
        if name in tables.tables:
            chosen[name] = (tables.tables[name].positions_mm, tables.tables[name].values)
        elif forward is not None and reverse is not None:
            reverse_values = np.interp(forward.positions_mm, reverse.positions_mm, reverse.values)
            chosen[name] = (forward.positions_mm, 0.5 * (forward.values + reverse_values))
        else:
            raise InputError(f"the error tables have no {name} (run xmalign post on all six lines)")
    return ErrorTables(chosen, tables.model("").squareness)


def render_table(
    tables: ErrorTableSet,
    chain: Chain,
    coordinates: str,
    tool_offset_mm: ArrayLike,
    max_correction_um: float,
) -> str:
    """The component's table file (mean tables, um and urad), ending in its CRC-32."""
    model = mean_model(tables)
    offset = np.asarray(tool_offset_mm, dtype=float)
    square = model.squareness_rad() * 1e6
    lines = [
        FORMAT_LINE,
        f"# xmalign volumetric compensation, chain {chain}; mean of both directions",
        f"coordinates {coordinates}",
        f"chain {chain}",
        *(
            f"lever {axis} "
            + " ".join("1" if a in chain.lever_arm_axes(axis) else "0" for a in AXES)
            for axis in AXES
        ),
        "tool_offset_mm " + " ".join(repr(float(v)) for v in offset),
        "squareness_urad " + " ".join(repr(float(v)) for v in square),
        f"max_correction_um {float(max_correction_um)!r}",
    ]
    for name in MOTION_NAMES:
        positions, values = model.tables[name]
        if len(positions) > MAX_POINTS:
            raise InputError(
                f"{name}: {len(positions)} points, more than the component's {MAX_POINTS}"
            )
        lines.append(f"table {name} {len(positions)}")
        lines += [
            f"{float(p)!r} {float(_file_value(name, v))!r}"
            for p, v in zip(positions, values, strict=True)
        ]
    body = "\n".join(lines) + "\n"
    return body + f"crc32 {zlib.crc32(body.encode()):08x}\n"


def parse_table(text: str, source: str = TABLE_FILE) -> VolumetricTable:
    """Read a table file as the component does; FormatError naming the line otherwise."""
    lines = text.splitlines(keepends=True)
    if not lines or not lines[-1].startswith("crc32 "):
        raise FormatError(f"{source}: no crc32 line at the end (truncated)")
    body = "".join(lines[:-1])
    if f"{zlib.crc32(body.encode()):08x}" != lines[-1].split()[1].lower():
        raise FormatError(f"{source} line {len(lines)}: CRC-32 mismatch: the file is damaged")
    if lines[0].strip() != FORMAT_LINE:
        raise FormatError(f"{source} line 1: not an {FORMAT_LINE} table file")
    try:
        return _parse_body(lines[:-1])
    except (ValueError, KeyError, IndexError) as exc:
        raise FormatError(f"{source}: not a complete table file ({exc})") from exc


def _parse_body(lines: list[str]) -> VolumetricTable:
    keys: dict[str, list[str]] = {}
    tables: dict[str, tuple[Vec, Vec]] = {}
    number = 1
    while number < len(lines):
        words = lines[number].split()
        number += 1
        if not words or words[0].startswith("#"):
            continue
        if words[0] == "table":
            name, count = words[1], int(words[2])
            rows = np.array([line.split() for line in lines[number : number + count]], dtype=float)
            number += count
            scale = 1e-3 if name[1] in "XYZ" else 1e-6
            tables[name] = (rows[:, 0], rows[:, 1] * scale)
        else:
            keys[words[0] if words[0] != "lever" else "lever " + words[1]] = words[1:]
    square = np.array(keys["squareness_urad"], dtype=float) * 1e-6
    return VolumetricTable(
        model=ErrorTables(tables, dict(zip(SQUARENESS_NAMES, square, strict=True))),
        chain=Chain.parse(keys["chain"][0]),
        coordinates=keys["coordinates"][0],
        tool_offset_mm=np.array(keys["tool_offset_mm"], dtype=float),
        max_correction_um=float(keys["max_correction_um"][0]),
    )


def correction_mm(
    chain: Chain, model: ErrorTables, tool_offset_mm: ArrayLike, commanded_mm: ArrayLike
) -> Vec:
    """The correction ``c`` with ``c = -dp(k + c)`` at commanded tool points ``k``, mm.

    The joints go to ``k + c``, where the model puts the tool on ``k``.

    Parameters
    ----------
    commanded_mm : array_like, shape (N, 3)

    Returns
    -------
    ndarray, shape (N, 3)
    """
    k = np.atleast_2d(np.asarray(commanded_mm, dtype=float))
    c = np.zeros_like(k)
    for _ in range(ITERATIONS):
        dp, _ = deviation(chain, k + c, tool_offset_mm, model)
        c = -dp
    return c


# -- the INI and HAL files ------------------------------------------------------------------

_SECTION = re.compile(r"^\s*\[([^\]]+)\]")
_KEY = re.compile(r"^\s*([A-Za-z0-9_]+)\s*=\s*(.*?)\s*$")


@dataclass(frozen=True)
class IniLine:
    """One line of a LinuxCNC INI file, with its section and key (None for other lines)."""

    text: str
    section: str
    key: str | None
    value: str | None


def read_ini(path: Path) -> list[IniLine]:
    """The INI's lines with their sections; InputError when the file cannot be read."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the INI file ({exc})") from exc
    section, result = "", []
    for line in text.splitlines():
        if header := _SECTION.match(line):
            section = header.group(1).strip()
        key = _KEY.match(line) if not line.lstrip().startswith(("#", ";")) else None
        result.append(
            IniLine(line, section, key.group(1) if key else None, key.group(2) if key else None)
        )
    return result


def ini_values(lines: list[IniLine], section: str, key: str) -> list[str]:
    """Every value of ``[section] key`` (HALFILE may repeat)."""
    return [
        line.value
        for line in lines
        if line.section == section and line.key == key and line.value is not None
    ]


def ini_value(lines: list[IniLine], section: str, key: str, source: Path) -> str:
    """The first value of ``[section] key`` (as LinuxCNC reads it); InputError when missing."""
    values = ini_values(lines, section, key)
    if not values:
        raise InputError(f"{source}: [{section}] {key} is missing")
    return values[0]


def joint_coordinates(lines: list[IniLine], source: Path, machine: Machine) -> str:
    """Each joint's axis letter (``XYZ``, ``XYYZ``) of a trivkins machine.

    As the pitch tables: the machine file's ``cnc.joints``, else the INI's
    ``coordinates=`` / ``[TRAJ] COORDINATES``, else X, Y, Z.
    """
    kinematics = ini_value(lines, "KINS", "KINEMATICS", source).split()
    if not kinematics or kinematics[0] != "trivkins":
        raise InputError(
            f"{source}: [KINS] KINEMATICS is '{' '.join(kinematics)}'; the volumetric component"
            " supports trivkins machines only"
        )
    coordinates = "".join(linuxcnc.resolve_joints(machine, [x.text for x in lines], str(source)))
    joints = ini_value(lines, "KINS", "JOINTS", source)
    if not joints.isdigit() or int(joints) != len(coordinates):
        raise InputError(
            f"{source}: [KINS] JOINTS = {joints} but {len(coordinates)} joints are mapped"
            f" ({coordinates})"
        )
    return coordinates


def _pin_pattern(pin: str) -> re.Pattern[str]:
    return re.compile(r"(?<![\w.\-])" + re.escape(pin) + r"(?![\w.\-])")


def _rewrites(joints: int) -> dict[str, str]:
    """User pins -> the component's pins that take their place in the user's HAL files."""
    pins = {"iocontrol.0.emc-enable-in": f"{INSTANCE}.enable-in"}
    for j in range(joints):
        pins[f"joint.{j}.motor-pos-cmd"] = f"{INSTANCE}.motor-pos-out-{j}"
        pins[f"joint.{j}.motor-pos-fb"] = f"{INSTANCE}.motor-pos-fb-in-{j}"
    return pins


def _sources(joints: int) -> dict[str, str]:
    """Motion controller output pins the component reads -> the component's input pin."""
    pins = {
        "motion.is-all-homed": "all-homed",
        "motion.motion-enabled": "motion-enabled",
        "iocontrol.0.user-request-enable": "reset",
    }
    for j in range(joints):
        pins[f"joint.{j}.pos-cmd"] = f"joint-pos-cmd-{j}"
        pins[f"joint.{j}.motor-pos-cmd"] = f"motor-pos-cmd-{j}"
        pins[f"joint.{j}.homed"] = f"joint-homed-{j}"
    return pins


def _signal_of(hal_files: dict[str, str], pin: str) -> str | None:
    """The signal a ``net`` line of the user's HAL files already puts ``pin`` on.

    InputError when the pin is named otherwise (``linkps`` ...): it cannot be
    shared safely.
    """
    for name, text in hal_files.items():
        for number, line in enumerate(text.splitlines(), start=1):
            if not _pin_pattern(pin).search(line.split("#", 1)[0]):
                continue
            words = line.split()
            if words[0] != "net":
                raise InputError(
                    f"{name} line {number}: {pin} is wired other than by 'net'; the volumetric"
                    " compensation needs to read it (use 'net SIGNAL ...')"
                )
            return words[1]
    return None


def wiring_hal(joints: int, signals: dict[str, str | None]) -> str:
    """The HAL file that wires the motion controller's side of the component.

    ``signals`` names, for a pin the user's HAL files already put on a signal,
    that signal (the component joins it rather than making its own).
    """
    lines = [
        "# xmalign: motion controller side of the volumetric compensation (xmalign_volcomp)",
        f"net xmalign-enable {INSTANCE}.enable-out => iocontrol.0.emc-enable-in",
    ]
    for pin, component_pin in _sources(joints).items():
        signal = signals.get(pin)
        if signal:
            lines.append(f"net {signal} => {INSTANCE}.{component_pin}")
        else:
            own = "xmalign-" + component_pin
            lines.append(f"net {own} {pin} => {INSTANCE}.{component_pin}")
    for j in range(joints):
        lines.append(
            f"net xmalign-fb-{j} {INSTANCE}.motor-pos-fb-out-{j} => joint.{j}.motor-pos-fb"
        )
    return "\n".join(lines) + "\n"


def _merged_name(path: str) -> str:
    return f"{Path(path).stem}_volcomp{Path(path).suffix}"


_MOTION_CONTROLLER = re.compile(r"^\s*addf\s+motion-controller\s+servo-thread\b")


def merge_hal(hal_files: dict[str, str], joints: int, table_path: Path) -> dict[str, str]:
    """Copies of the user's HAL files (name -> text) rewired through the component.

    The first file loads the component (its pins stand where the drive pins
    stood, so it must exist before any of them is named); its ``feedback``
    function goes right before ``motion-controller`` (after the drives' reads)
    and its ``command`` function right after it.
    """
    rewrites = _rewrites(joints)
    seen = dict.fromkeys(rewrites, False)
    placed = False
    merged: dict[str, str] = {}
    for name, text in hal_files.items():
        if _pin_pattern(COMPONENT).search(text):
            raise InputError(f"{name}: loads {COMPONENT} already (merge the original files)")
        out = [] if merged else [f"loadrt {COMPONENT} table={table_path}"]
        for line in text.splitlines():
            for pin, replacement in rewrites.items():
                line, count = _pin_pattern(pin).subn(replacement, line)
                seen[pin] = seen[pin] or count > 0
            if _MOTION_CONTROLLER.match(line) and not placed:
                out += [f"addf {INSTANCE}.feedback servo-thread", line]
                out.append(f"addf {INSTANCE}.command servo-thread")
                placed = True
            else:
                out.append(line)
        merged[name] = "\n".join(out) + "\n"
    if not placed:
        raise InputError(
            f"{', '.join(hal_files)}: no 'addf motion-controller servo-thread' line to add the"
            " component's functions around"
        )
    missing = [pin for pin, found in seen.items() if not found]
    if missing:
        raise InputError(
            f"{', '.join(hal_files)}: {missing[0]} is not wired in the HAL files; the component"
            " goes between it and the drive"
        )
    return merged


@dataclass(frozen=True)
class MergedConfig:
    """File name -> text of everything to write, and warnings for the user."""

    files: dict[str, str]
    ini_name: str
    warnings: list[str]


def merge_config(
    ini_path: Path, tables: ErrorTableSet, machine: Machine, out_dir: Path
) -> MergedConfig:
    """The table file, the merged INI and HAL copies and the wiring file for ``out_dir``.

    The chain, the tool offset (``cnc.tool_offset_mm``), the bound
    (``cnc.max_correction_um``) and the joints come from the machine file. An INI whose
    ``[TRAJ] LINEAR_UNITS`` is not mm is refused (the component's table is in mm).
    """
    lines = read_ini(ini_path)
    folder = ini_path.resolve().parent
    coordinates = joint_coordinates(lines, ini_path, machine)
    if linuxcnc.units_per_mm([line.text for line in lines], str(ini_path)) != 1.0:
        raise InputError(
            f"{ini_path}: [TRAJ] LINEAR_UNITS is not mm; the volumetric component works in mm"
            " (--controller linuxcnc writes its comp files in the INI's units)"
        )
    halfiles = ini_values(lines, "HAL", "HALFILE")
    if not halfiles:
        raise InputError(f"{ini_path}: [HAL] HALFILE is missing")
    for name in halfiles:
        if name.startswith("LIB:") or not name.endswith(".hal"):
            raise InputError(
                f"{ini_path}: [HAL] HALFILE = {name}: only .hal files of the configuration can be"
                " merged; copy the library file into the configuration and name the copy"
            )
    sources = {}
    for name in halfiles:
        path = Path(name) if Path(name).is_absolute() else folder / name
        try:
            sources[name] = path.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"{ini_path}: [HAL] HALFILE = {name}: cannot read it ({exc})") from exc
    table_text = render_table(
        tables,
        Chain.parse(machine.chain),
        coordinates,
        machine.cnc.tool_offset_mm,
        machine.cnc.max_correction_um,
    )
    table_path = out_dir.resolve() / TABLE_FILE
    if any(c.isspace() for c in str(table_path)):
        raise InputError(f"{table_path}: HAL's loadrt cannot take a path with spaces; use --out")
    merged = merge_hal(sources, len(coordinates), table_path)
    # a pin the copies no longer name (the drive command) gets a signal of its own
    rewritten = _rewrites(len(coordinates))
    signals = {
        pin: None if pin in rewritten else _signal_of(sources, pin)
        for pin in _sources(len(coordinates))
    }
    files = {_merged_name(name): text for name, text in merged.items()}
    files[WIRING_FILE] = wiring_hal(len(coordinates), signals)
    files[TABLE_FILE] = table_text
    ini_name = _merged_name(ini_path.name)
    files[ini_name], warnings = _merged_ini(lines, folder)
    warnings += _coverage_warnings(lines, parse_table(table_text), ini_path)
    inputs = (*table_sources(tables), FileSource.of("ini", ini_path))
    return MergedConfig(with_history(files, FORMAT, inputs, COMMENTS), ini_name, warnings)


#: Per-joint pitch tables: the component corrects positioning too, so they would count twice.
PITCH_KEYS = ("COMP_FILE", "COMP_FILE_TYPE")


def _merged_ini(lines: list[IniLine], folder: Path) -> tuple[str, list[str]]:
    """The INI copy's text, and a warning per pitch table it leaves out."""
    out, warnings = [], []
    last_halfile = max(
        i for i, line in enumerate(lines) if line.section == "HAL" and line.key == "HALFILE"
    )
    for index, line in enumerate(lines):
        if line.section == "HAL" and line.key == "HALFILE" and line.value is not None:
            out.append(f"HALFILE = {_merged_name(line.value)}")
        elif line.section.startswith("JOINT_") and line.key in PITCH_KEYS:
            out.append(f"# xmalign: the volumetric compensation replaces: {line.text.strip()}")
            if line.key == "COMP_FILE":
                warnings.append(
                    f"[{line.section}] COMP_FILE = {line.value} left out of the copy: the"
                    " volumetric component corrects the positioning error too"
                )
        elif line.key is not None and line.value:
            absolute = linuxcnc.absolute_path(line.value, folder)
            out.append(line.text if absolute == line.value else f"{line.key} = {absolute}")
        else:
            out.append(line.text)
        if index == last_halfile:
            out += [
                f"# xmalign: volumetric compensation ({TABLE_FILE})",
                f"HALFILE = {WIRING_FILE}",
            ]
    return "\n".join(out) + "\n", warnings


def _coverage_warnings(
    lines: list[IniLine], volumetric: VolumetricTable, source: Path
) -> list[str]:
    warnings = []
    for joint, axis in enumerate(volumetric.coordinates):
        low, high = volumetric.coverage_mm(axis)
        section = f"JOINT_{joint}"
        limits = [ini_values(lines, section, key) for key in ("MIN_LIMIT", "MAX_LIMIT")]
        if not all(limits):
            continue
        min_limit, max_limit = float(limits[0][0]), float(limits[1][0])
        if min_limit < low - 1e-6 or max_limit > high + 1e-6:
            warnings.append(
                f"{source}: [{section}] limits {min_limit:g} .. {max_limit:g} mm reach beyond the"
                f" tables of {axis} ({low:g} .. {high:g} mm): the component faults the machine"
                " (E-stop) there"
            )
    return warnings
