"""Measurement plan (``xmalign.plan/1``) of docs/formats.md.

The history keys (:mod:`xmalign.formats.provenance`) are kept apart from the
plan's content: they are not part of its identity (``plan_identity`` in a
measurement file, :func:`xmalign.formats.measurements.plan_sha256`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import ConfigDict, Field, field_validator, model_validator

from xmalign.errors import OutputError
from xmalign.formats.common import (
    Angle_deg,
    FileModel,
    Finite,
    Length_mm,
    Vector3_mm,
    located,
    read_json,
    validate,
    write_json,
)
from xmalign.formats.provenance import (
    FileSource,
    Provenance,
    json_history,
    read_json_history,
    without_history,
)
from xmalign.geometry import Vec

PLAN_FORMAT = "xmalign.plan/1"
#: How far a line frame may be from orthonormal (rounding of the written digits).
FRAME_TOLERANCE = 1e-6
#: How far the targets may reach beyond the line's end (rounding), mm.
TARGET_TOLERANCE_MM = 1e-3
_V3 = Vector3_mm
#: A line id: letters, digits and ``_ . + -`` (it is a field of every measurement row and
#: a word of the CSV's setup comments: a comma, a quote, a space or a newline would break them).
LINE_ID = re.compile(r"[\w.+-]+")


def line_id_problem(line_id: str) -> str | None:
    """What makes ``line_id`` unusable as a line id, or None."""
    if not line_id:
        return "a line id must not be empty"
    if LINE_ID.fullmatch(line_id) is None or not line_id.isprintable():
        bad = next(c for c in line_id if LINE_ID.fullmatch(c) is None or not c.isprintable())
        return (
            f"line id {line_id!r} holds {bad!r}; a line id is letters, digits and _ . + -"
            " (it is a field of every measurement row)"
        )
    return None


_KNOWN_LINE_KEYS = {
    "id",
    "start_mm",
    "end_mm",
    "frame",
    "launch_deg",
    "receiver_deg",
    "targets_mm",
    "runs",
    "bidirectional",
    "dwell_s",
}


class _FrameModel(FileModel):
    u: Annotated[list[Finite], Field(min_length=3, max_length=3)]
    v: Annotated[list[Finite], Field(min_length=3, max_length=3)]
    w: Annotated[list[Finite], Field(min_length=3, max_length=3)]

    @model_validator(mode="after")
    def _orthonormal(self) -> _FrameModel:
        frame = np.array([self.u, self.v, self.w])
        if np.max(np.abs(frame @ frame.T - np.eye(3))) > FRAME_TOLERANCE:
            raise ValueError("u, v, w are not orthonormal")
        if np.linalg.det(frame) < 0:
            raise ValueError("u, v, w are a left-handed frame (w must be u x v)")
        return self


class _LineModel(FileModel):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    id: Annotated[str, Field(min_length=1)]
    start_mm: _V3
    end_mm: _V3
    frame: _FrameModel
    launch_deg: Annotated[list[Angle_deg], Field(min_length=2, max_length=2)]
    receiver_deg: Annotated[list[Angle_deg], Field(min_length=3, max_length=3)]
    targets_mm: Annotated[list[Length_mm], Field(min_length=2)]
    runs: Annotated[int, Field(ge=1, le=5)] = 1
    bidirectional: bool = False
    dwell_s: Annotated[float, Field(ge=0, le=3600, allow_inf_nan=False)] = 0.0

    @field_validator("id")
    @classmethod
    def _usable_id(cls, line_id: str) -> str:
        problem = line_id_problem(line_id)
        if problem is not None:
            raise ValueError(problem)
        return line_id

    @field_validator("targets_mm")
    @classmethod
    def _increasing(cls, targets: list[float]) -> list[float]:
        if np.any(np.diff(targets) <= 0):
            raise ValueError("targets must increase strictly")
        return targets

    @model_validator(mode="after")
    def _targets_on_the_line(self) -> _LineModel:
        length_mm = float(np.linalg.norm(np.subtract(self.end_mm, self.start_mm)))
        low, high = self.targets_mm[0], self.targets_mm[-1]
        if low < -TARGET_TOLERANCE_MM or high > length_mm + TARGET_TOLERANCE_MM:
            raise ValueError(
                f"targets_mm [{low:g} .. {high:g}] leave the line (0 .. {length_mm:g} mm)"
            )
        return self


class _PlanModel(FileModel):
    model_config = ConfigDict(extra="allow", allow_inf_nan=False)
    format: str
    machine: str
    receiver_offset_mm: _V3
    spindle_angle_deg: Angle_deg = 0.0
    lines: Annotated[list[_LineModel], Field(min_length=1)]

    @field_validator("lines")
    @classmethod
    def _unique_ids(cls, lines: list[_LineModel]) -> list[_LineModel]:
        ids = [line.id for line in lines]
        repeated = sorted({i for i in ids if ids.count(i) > 1})
        if repeated:
            raise ValueError(f"line id '{repeated[0]}' is given twice")
        return lines


@dataclass
class PlanLine:
    """One measuring line. ``frame`` rows are u, v, w (3, 3); angles are reported, rad.

    ``extra`` keeps keys the spec does not list (e.g. the predicted beam margins).
    """

    id: str
    start_mm: Vec
    end_mm: Vec
    frame: Vec
    launch_rad: Vec
    receiver_rad: Vec
    targets_mm: Vec
    runs: int = 1
    bidirectional: bool = False
    dwell_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def target_points_mm(self) -> Vec:
        """CNC tool points of the targets, shape (M, 3)."""
        return self.start_mm + np.outer(self.targets_mm, self.frame[0])


@dataclass
class Plan:
    """A measurement plan; ``source`` and ``history`` are set when it was read from a file."""

    machine: str
    receiver_offset_mm: Vec
    spindle_angle_rad: float
    lines: list[PlanLine]
    extra: dict[str, Any] = field(default_factory=dict)
    source: FileSource | None = field(default=None, compare=False)
    history: Provenance | None = field(default=None, compare=False)

    def line(self, line_id: str) -> PlanLine:
        for line in self.lines:
            if line.id == line_id:
                return line
        raise KeyError(line_id)


def parse_plan(data: dict, source: str) -> Plan:
    """A Plan from a decoded document (format checked); history keys kept apart."""
    history = read_json_history(data, source)
    model = validate(_PlanModel, without_history(data), source)
    lines = [
        PlanLine(
            id=m.id,
            start_mm=np.array(m.start_mm),
            end_mm=np.array(m.end_mm),
            frame=np.array([m.frame.u, m.frame.v, m.frame.w]),
            launch_rad=np.radians(m.launch_deg),
            receiver_rad=np.radians(m.receiver_deg),
            targets_mm=np.array(m.targets_mm),
            runs=m.runs,
            bidirectional=m.bidirectional,
            dwell_s=m.dwell_s,
            extra=dict(m.model_extra or {}),
        )
        for m in model.lines
    ]
    return Plan(
        machine=model.machine,
        receiver_offset_mm=np.array(model.receiver_offset_mm),
        spindle_angle_rad=math.radians(model.spindle_angle_deg),
        lines=lines,
        extra=dict(model.model_extra or {}),
        history=history,
    )


def read_plan(path: str | Path) -> Plan:
    """Read and validate a plan file; ``source`` records its SHA-256."""
    plan = parse_plan(read_json(path, PLAN_FORMAT), str(path))
    plan.source = FileSource.of("plan", path)
    return plan


def _floats(values: Vec) -> list[float]:
    return [float(v) for v in values]


def plan_to_dict(plan: Plan) -> dict:
    """The plan's content as JSON (no history: this is what its identity is made of)."""
    return {
        "format": PLAN_FORMAT,
        "machine": plan.machine,
        "receiver_offset_mm": _floats(plan.receiver_offset_mm),
        "spindle_angle_deg": math.degrees(plan.spindle_angle_rad),
        **plan.extra,
        "lines": [
            {
                "id": line.id,
                "start_mm": _floats(line.start_mm),
                "end_mm": _floats(line.end_mm),
                "frame": dict(zip("uvw", (_floats(r) for r in line.frame), strict=True)),
                "launch_deg": _floats(np.degrees(line.launch_rad)),
                "receiver_deg": _floats(np.degrees(line.receiver_rad)),
                "targets_mm": _floats(line.targets_mm),
                "runs": line.runs,
                "bidirectional": line.bidirectional,
                "dwell_s": line.dwell_s,
                **{k: v for k, v in line.extra.items() if k not in _KNOWN_LINE_KEYS},
            }
            for line in plan.lines
        ],
    }


def write_plan(path: str | Path, plan: Plan, inputs: Iterable[FileSource] = ()) -> None:
    """Write the plan with its history (``inputs``: the pose and machine files); a line id
    the reader would refuse (:func:`line_id_problem`) is refused."""
    for number, line in enumerate(plan.lines):
        problem = line_id_problem(line.id)
        if problem is not None:
            raise OutputError(located(path, f"key 'lines.{number}.id'", problem))
    write_json(path, json_history(PLAN_FORMAT, inputs) | plan_to_dict(plan))
