"""Measurement plan (``xmalign.plan/1``) of FORMATS.md."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from xmalign.formats.common import read_json, validate, write_json
from xmalign.geometry import Vec

PLAN_FORMAT = "xmalign.plan/1"
_V3 = Annotated[list[float], Field(min_length=3, max_length=3)]
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


class _FrameModel(BaseModel):
    u: _V3
    v: _V3
    w: _V3


class _LineModel(BaseModel):
    model_config = ConfigDict(extra="allow")
    id: str
    start_mm: _V3
    end_mm: _V3
    frame: _FrameModel
    launch_deg: Annotated[list[float], Field(min_length=2, max_length=2)]
    receiver_deg: Annotated[list[float], Field(min_length=3, max_length=3)]
    targets_mm: Annotated[list[float], Field(min_length=2)]
    runs: Annotated[int, Field(ge=1, le=5)] = 1
    bidirectional: bool = False
    dwell_s: Annotated[float, Field(ge=0)] = 0.0


class _PlanModel(BaseModel):
    model_config = ConfigDict(extra="allow")
    format: str
    machine: str
    receiver_offset_mm: _V3
    spindle_angle_deg: float = 0.0
    lines: Annotated[list[_LineModel], Field(min_length=1)]


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
    machine: str
    receiver_offset_mm: Vec
    spindle_angle_rad: float
    lines: list[PlanLine]
    extra: dict[str, Any] = field(default_factory=dict)

    def line(self, line_id: str) -> PlanLine:
        for line in self.lines:
            if line.id == line_id:
                return line
        raise KeyError(line_id)


def parse_plan(data: dict, source: str) -> Plan:
    model = validate(_PlanModel, data, source)
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
    )


def read_plan(path: str | Path) -> Plan:
    return parse_plan(read_json(path, PLAN_FORMAT), str(path))


def _floats(values: Vec) -> list[float]:
    return [float(v) for v in values]


def plan_to_dict(plan: Plan) -> dict:
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


def write_plan(path: str | Path, plan: Plan) -> None:
    write_json(path, plan_to_dict(plan))
