"""A tracker's point export as users have it: SpatialAnalyzer's ASCII export, plain
``Name,X,Y,Z`` exports, and xmalign's point list.

SpatialAnalyzer (New River Kinematics / Hexagon) exports measured points as
plain text, one point per line. Its user manual ("Exporting ASCII Formatted
Points") lists the export's options: the point name as ``Collection Group
Target``, ``Group Target`` or ``Target``; the fields separated by spaces or
commas (tabs come from spreadsheets and other tools); optional columns after
the coordinates (tolerances, coordinate uncertainties, time stamps, offsets,
comments, measurement details); header lines that start with ``//``.
Coordinates are in the export's length unit (``--units``). Other tracker
software writes ``Name,X,Y,Z`` (one name, the coordinates, optional further
columns, an optional header line): :data:`NAMING` ``target``.

``xmalign import`` turns such a file into tracker points (docs/formats.md) with
the point list ``xmalign program --instrument tracker --points-out`` wrote: a
target's name is the index of its point, the export's groups are the runs in
the order they first appear (without groups: a name measured again starts the
next run), and the coordinates are in the tracker's frame (the tracker's own,
or any frame fixed to it: the fit finds the pose).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from xmalign.errors import InputError
from xmalign.formats.common import line_error, read_text
from xmalign.formats.instrument_checks import UNITS_MM, check_instrument_files
from xmalign.formats.instruments import MAX_COORDINATE_MM, TrackerFile, TrackerPoint
from xmalign.geometry import Vec
from xmalign.machine import Machine

#: The name fields before X Y Z, for each of SpatialAnalyzer's point-name options.
NAMING = {
    "collection-group-target": ("collection", "group", "target"),
    "group-target": ("group", "target"),
    "target": ("target",),
}
POINT_LIST_HEADER = "name,x_mm,y_mm,z_mm"


@dataclass(frozen=True)
class ExportedPoint:
    """One line of a SpatialAnalyzer ASCII export (mm) and where it was in the file."""

    collection: str
    group: str
    target: str
    point_mm: Vec
    line: int


def _fields(text: str) -> list[str]:
    """Comma, tab or space separated (in that order of precedence)."""
    if "," in text:
        return [field.strip() for field in next(csv.reader([text]))]
    if "\t" in text:
        return [field.strip() for field in text.split("\t")]
    return text.split()


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _coordinates(values: list[str], source: str, number: int) -> Vec:
    try:
        point = np.array([float(v) for v in values])
    except ValueError as error:
        raise line_error(source, number, f"'{' '.join(values)}' is not X Y Z") from error
    if not all(math.isfinite(v) for v in point) or np.any(np.abs(point) > MAX_COORDINATE_MM):
        raise line_error(source, number, f"{' '.join(values)} is not a finite point within 100 m")
    return point


def read_spatial_analyzer(
    path: str | Path, naming: str = "collection-group-target", units: str = "mm"
) -> list[ExportedPoint]:
    """The points of a SpatialAnalyzer ASCII export (or a ``Name,X,Y,Z`` list), in mm.

    ``naming`` is the export's point-name option (:data:`NAMING`), ``units`` its
    length unit (:data:`UNITS_MM`). Columns after X Y Z are ignored. A first line
    whose coordinates are not numbers is a header (``Name,X,Y,Z``).

    Raises
    ------
    InputError
        Naming the file and line: too few fields, coordinates that are not numbers,
        an empty target name, or no points at all.
    """
    source = str(path)
    names = NAMING[naming]
    scale = UNITS_MM[units]
    layout = " ".join(name.capitalize() for name in names) + " X Y Z"
    points: list[ExportedPoint] = []
    for number, line in enumerate(read_text(path).splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("//"):
            continue
        fields = _fields(text)
        if len(fields) < len(names) + 3:
            raise line_error(source, number, f"{len(fields)} fields; expected {layout}")
        values = dict(zip(names, fields, strict=False))
        xyz = fields[len(names) : len(names) + 3]
        if not points and not any(_is_number(v) for v in xyz):
            continue  # a header line: Name,X,Y,Z
        if not values["target"]:
            raise line_error(source, number, "empty target name")
        points.append(
            ExportedPoint(
                values.get("collection", ""),
                values.get("group", ""),
                values["target"],
                _coordinates(xyz, source, number) * scale,
                number,
            )
        )
    if not points:
        raise InputError(f"{source}: no points (expected lines {layout})")
    return points


@dataclass(frozen=True)
class ListedPoint:
    """One point of the point list: the SMR's nominal position (MCS, mm) and its SMR."""

    smr_mm: Vec
    smr: str | None = None


def read_point_list(path: str | Path) -> dict[str, ListedPoint]:
    """``name,x_mm,y_mm,z_mm[,smr]`` (``program --points-out``): name -> listed point."""
    source = str(path)
    lines = read_text(path).splitlines()
    headers = (POINT_LIST_HEADER, f"{POINT_LIST_HEADER},smr")
    if not lines or lines[0].strip() not in headers:
        raise line_error(source, 1, f"expected the header '{POINT_LIST_HEADER}[,smr]'")
    width = len(lines[0].split(","))
    points: dict[str, ListedPoint] = {}
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = next(csv.reader(io.StringIO(line)))
        if len(fields) != width:
            raise line_error(source, number, f"{len(fields)} fields, the header has {width}")
        name = fields[0].strip()
        if name in points:
            raise line_error(source, number, f"point '{name}' is listed twice")
        smr = (fields[4].strip() or None) if width == 5 else None
        points[name] = ListedPoint(_coordinates(fields[1:4], source, number), smr)
    return points


def tracker_points_from_export(
    exported: list[ExportedPoint],
    point_list: dict[str, ListedPoint],
    machine: Machine,
    station: str,
    source: str,
) -> list[TrackerPoint]:
    """Tracker points: each target's commanded tool point from the point list.

    Targets are matched by name to the list's whole-number names (the indices);
    the groups are the runs, numbered in the order they first appear (an export
    without groups: a target measured again starts the next run). A point the
    list gives an ``smr`` is taken with that SMR position of ``machine``.

    Raises
    ------
    InputError
        A target the point list does not name, a name that is not an index, a
        target measured twice in one group, or an SMR the machine file does not
        name (naming the export's line).
    """
    runs: dict[str, int] = {}
    seen: set[tuple[str, str]] = set()
    repeats: dict[str, int] = {}
    points = []
    for p in exported:
        if p.target not in point_list:
            raise line_error(source, p.line, f"target '{p.target}' is not in the point list")
        if not p.target.isdigit():
            raise line_error(
                source, p.line, f"target '{p.target}' is not a point index (a path's end?)"
            )
        if p.group:
            if (p.group, p.target) in seen:
                raise line_error(source, p.line, f"target '{p.target}' twice in group '{p.group}'")
            seen.add((p.group, p.target))
            run = runs.setdefault(p.group, len(runs))
        else:
            run = repeats.get(p.target, 0)
            repeats[p.target] = run + 1
        listed = point_list[p.target]
        if listed.smr is not None and listed.smr not in machine.smr_offsets_mm:
            raise line_error(
                source,
                p.line,
                f"target '{p.target}' is listed with SMR '{listed.smr}', which the machine"
                " file's smr_offsets_mm does not name (the point list of another machine file?)",
            )
        offset = machine.smr_offset if listed.smr is None else machine.smr_offsets()[listed.smr]
        commanded = listed.smr_mm - offset
        points.append(
            TrackerPoint(station, run, int(p.target), commanded, p.point_mm, smr=listed.smr)
        )
    return points


def tracker_file_from_export(
    machine: Machine,
    export: Path,
    point_list: dict[str, ListedPoint],
    station: str,
    naming: str = "collection-group-target",
    units: str = "mm",
) -> TrackerFile:
    """Tracker points from a tracker's export and the point list (:func:`read_point_list`),
    checked.

    Raises
    ------
    InputError
        As :func:`read_spatial_analyzer` and :func:`tracker_points_from_export`,
        and where the distances between the points contradict the commanded moves
        (another unit than ``units``, names shifted against the point list:
        :func:`xmalign.formats.instrument_checks.check_instrument_files`).
    """
    exported = read_spatial_analyzer(export, naming, units)

    def checked(points: list[ExportedPoint]) -> TrackerFile:
        rows = tracker_points_from_export(points, point_list, machine, station, str(export))
        file = TrackerFile(rows, str(export), lines=[p.line for p in points])
        check_instrument_files(machine, [file], [])
        return file

    listed = [p for p in exported if p.target in point_list]
    if listed and len(listed) < len(exported):  # names shifted: say where the points stop matching
        checked(listed)
    return checked(exported)


def unmeasured(point_list: dict[str, ListedPoint], file: TrackerFile) -> list[str]:
    """The names of the list's points (indices) that no row of ``file`` measured."""
    measured = {str(p.index) for p in file.points}
    return [name for name in point_list if name.isdigit() and name not in measured]
