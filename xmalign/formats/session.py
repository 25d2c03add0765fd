"""Identification session (``xmalign.identify-session/1``) of docs/formats.md."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from xmalign.formats.common import (
    Angle_deg,
    Distance_mm,
    FileModel,
    Finite,
    Vector3_mm,
    read_json,
    validate,
    write_json,
)
from xmalign.formats.provenance import FileSource, json_history
from xmalign.geometry import Vec

SESSION_FORMAT = "xmalign.identify-session/1"
#: The nominal straightness range of the instrument, um (a machine file may set another).
NOMINAL_STRAIGHTNESS_RANGE_UM = 250.0


class _AlignmentModel(FileModel):
    machine_mm: Vector3_mm
    launch_deg: Annotated[list[Angle_deg], Field(min_length=2, max_length=2)]
    receiver_deg: Annotated[list[Angle_deg], Field(min_length=2, max_length=3)]
    distance_mm: Distance_mm | None = None
    straightness_um: Annotated[list[Finite], Field(min_length=2, max_length=2)] | None = None

    @field_validator("straightness_um")
    @classmethod
    def _within_twice_the_range(
        cls, value: list[float] | None, info: ValidationInfo
    ) -> list[float] | None:
        limit = 2 * (info.context or {}).get("straightness_range_um", NOMINAL_STRAIGHTNESS_RANGE_UM)
        if value is not None and max(abs(v) for v in value) > limit:
            raise ValueError(f"{value} is more than twice the instrument's range ({limit:g} um)")
        return value


class _SessionModel(FileModel):
    format: str
    spindle_angle_deg: Angle_deg = 0.0
    receiver_offset_mm: Vector3_mm
    alignments: list[_AlignmentModel]


@dataclass(frozen=True)
class Alignment:
    """The units aligned at one machine position (angles reported by the encoders).

    ``launch_rad`` is ``[phi1, phi2]``, ``receiver_rad`` ``[phi3, phi4, phi5]``;
    ``straightness_um`` the residual ``[sv, sw]`` after fine alignment.
    """

    machine_mm: Vec
    launch_rad: Vec
    receiver_rad: Vec
    distance_mm: float | None = None
    straightness_um: Vec | None = None


@dataclass
class Session:
    """An identification session: spindle angle, receiver offset and alignments."""

    receiver_offset_mm: Vec
    spindle_angle_rad: float = 0.0
    alignments: list[Alignment] = field(default_factory=list)


def _alignment_from_model(m: _AlignmentModel) -> Alignment:
    receiver = list(m.receiver_deg) + [0.0] * (3 - len(m.receiver_deg))
    return Alignment(
        machine_mm=np.array(m.machine_mm, dtype=float),
        launch_rad=np.radians(m.launch_deg),
        receiver_rad=np.radians(receiver),
        distance_mm=m.distance_mm,
        straightness_um=None if m.straightness_um is None else np.array(m.straightness_um),
    )


def parse_session(
    data: dict, source: str, straightness_range_um: float = NOMINAL_STRAIGHTNESS_RANGE_UM
) -> Session:
    """Build a Session from a decoded JSON document (format already checked).

    A straightness residual beyond twice ``straightness_range_um`` is refused.
    """
    context = {"straightness_range_um": straightness_range_um}
    model = validate(_SessionModel, data, source, context)
    return Session(
        receiver_offset_mm=np.array(model.receiver_offset_mm, dtype=float),
        spindle_angle_rad=math.radians(model.spindle_angle_deg),
        alignments=[_alignment_from_model(a) for a in model.alignments],
    )


def read_session(
    path: str | Path, straightness_range_um: float = NOMINAL_STRAIGHTNESS_RANGE_UM
) -> Session:
    """Read and validate an identification session file."""
    return parse_session(read_json(path, SESSION_FORMAT), str(path), straightness_range_um)


def session_to_dict(session: Session) -> dict:
    """The JSON document of a session."""
    return {
        "format": SESSION_FORMAT,
        "spindle_angle_deg": math.degrees(session.spindle_angle_rad),
        "receiver_offset_mm": [float(v) for v in session.receiver_offset_mm],
        "alignments": [
            {
                "machine_mm": [float(v) for v in a.machine_mm],
                "launch_deg": [float(v) for v in np.degrees(a.launch_rad)],
                "receiver_deg": [float(v) for v in np.degrees(a.receiver_rad)],
                "distance_mm": a.distance_mm,
                "straightness_um": None
                if a.straightness_um is None
                else [float(v) for v in a.straightness_um],
            }
            for a in session.alignments
        ],
    }


def write_session(path: str | Path, session: Session, inputs: Iterable[FileSource] = ()) -> None:
    """Write a session file atomically (safe to call after every alignment), with its
    history (``inputs``: the machine file)."""
    write_json(path, json_history(SESSION_FORMAT, inputs) | session_to_dict(session))
