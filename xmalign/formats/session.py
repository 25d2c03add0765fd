"""Identification session (``xmalign.identify-session/1``) of FORMATS.md."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from xmalign.formats.common import read_json, validate, write_json
from xmalign.geometry import Vec

SESSION_FORMAT = "xmalign.identify-session/1"


class _AlignmentModel(BaseModel):
    model_config = ConfigDict(extra="ignore")
    machine_mm: Annotated[list[float], Field(min_length=3, max_length=3)]
    launch_deg: Annotated[list[float], Field(min_length=2, max_length=2)]
    receiver_deg: Annotated[list[float], Field(min_length=2, max_length=3)]
    distance_mm: Annotated[float, Field(gt=0)] | None = None
    straightness_um: Annotated[list[float], Field(min_length=2, max_length=2)] | None = None


class _SessionModel(BaseModel):
    model_config = ConfigDict(extra="ignore")
    format: str
    spindle_angle_deg: float = 0.0
    receiver_offset_mm: Annotated[list[float], Field(min_length=3, max_length=3)]
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


def parse_session(data: dict, source: str) -> Session:
    """Build a Session from a decoded JSON document (format already checked)."""
    model = validate(_SessionModel, data, source)
    return Session(
        receiver_offset_mm=np.array(model.receiver_offset_mm, dtype=float),
        spindle_angle_rad=math.radians(model.spindle_angle_deg),
        alignments=[_alignment_from_model(a) for a in model.alignments],
    )


def read_session(path: str | Path) -> Session:
    """Read and validate an identification session file."""
    return parse_session(read_json(path, SESSION_FORMAT), str(path))


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


def write_session(path: str | Path, session: Session) -> None:
    """Write a session file atomically (safe to call after every alignment)."""
    write_json(path, session_to_dict(session))
