"""A tracker's point export as users have it: SpatialAnalyzer's ASCII export, and point lists.

SpatialAnalyzer (New River Kinematics / Hexagon) exports measured points as
plain text, one point per line: ``Collection Group Target X Y Z``, the fields
separated by spaces or by commas, with optional header lines that start with
``//``. Coordinates are in the export's length unit; xmalign takes millimetres
(choose mm in the export). ``xmalign import`` turns such a file into tracker
points (docs/formats.md) with the point list ``xmalign program --instrument
tracker --points-out`` wrote: a target's name is the index of its point, the
export's groups are the runs in the order they first appear, and the
coordinates are in the tracker's frame (the tracker's own, or any frame fixed
to it: the fit finds the pose).
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
from xmalign.formats.instruments import MAX_COORDINATE_MM, TrackerPoint
from xmalign.geometry import Vec

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
    if "," in text:
        return [field.strip() for field in next(csv.reader([text]))]
    return text.split()


def _coordinates(values: list[str], source: str, number: int) -> Vec:
    try:
        point = np.array([float(v) for v in values])
    except ValueError as error:
        raise line_error(source, number, f"'{' '.join(values)}' is not X Y Z") from error
    if not all(math.isfinite(v) for v in point) or np.any(np.abs(point) > MAX_COORDINATE_MM):
        raise line_error(source, number, f"{' '.join(values)} is not a finite point within 100 m")
    return point


def read_spatial_analyzer(path: str | Path) -> list[ExportedPoint]:
    """The points of a SpatialAnalyzer ASCII export; InputError naming the file and line."""
    source = str(path)
    points = []
    for number, line in enumerate(read_text(path).splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("//"):
            continue
        fields = _fields(text)
        if len(fields) != 6:
            raise line_error(
                source, number, f"{len(fields)} fields; expected Collection Group Target X Y Z"
            )
        collection, group, target = fields[:3]
        if not target:
            raise line_error(source, number, "empty target name")
        points.append(
            ExportedPoint(
                collection, group, target, _coordinates(fields[3:], source, number), number
            )
        )
    if not points:
        raise InputError(f"{source}: no points (expected lines Collection Group Target X Y Z)")
    return points


def read_point_list(path: str | Path) -> dict[str, Vec]:
    """``name,x_mm,y_mm,z_mm`` (``program --points-out``): name -> SMR point in the MCS, mm."""
    source = str(path)
    lines = read_text(path).splitlines()
    if not lines or lines[0].strip() != POINT_LIST_HEADER:
        raise line_error(source, 1, f"expected the header '{POINT_LIST_HEADER}'")
    points: dict[str, Vec] = {}
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = next(csv.reader(io.StringIO(line)))
        if len(fields) != 4:
            raise line_error(source, number, f"{len(fields)} fields, the header has 4")
        name = fields[0].strip()
        if name in points:
            raise line_error(source, number, f"point '{name}' is listed twice")
        points[name] = _coordinates(fields[1:], source, number)
    return points


def tracker_points_from_export(
    exported: list[ExportedPoint],
    point_list: dict[str, Vec],
    smr_offset_mm: Vec,
    station: str,
    source: str,
) -> list[TrackerPoint]:
    """Tracker points: each target's commanded tool point from the point list.

    Targets are matched by name to the list's whole-number names (the indices);
    the groups are the runs, numbered in the order they first appear.

    Raises
    ------
    InputError
        A target the point list does not name, a name that is not an index, or a
        target measured twice in one group (naming the export's line).
    """
    runs: dict[str, int] = {}
    seen: set[tuple[str, str]] = set()
    points = []
    for p in exported:
        if p.target not in point_list:
            raise line_error(source, p.line, f"target '{p.target}' is not in the point list")
        if not p.target.isdigit():
            raise line_error(
                source, p.line, f"target '{p.target}' is not a point index (a path's end?)"
            )
        if (p.group, p.target) in seen:
            raise line_error(source, p.line, f"target '{p.target}' twice in group '{p.group}'")
        seen.add((p.group, p.target))
        run = runs.setdefault(p.group, len(runs))
        commanded = point_list[p.target] - np.asarray(smr_offset_mm, dtype=float)
        points.append(TrackerPoint(station, run, int(p.target), commanded, p.point_mm))
    return points
