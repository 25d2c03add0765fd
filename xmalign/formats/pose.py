"""Launch-unit pose (``xmalign.launch-pose/1``) of FORMATS.md."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from xmalign.errors import InputError
from xmalign.formats.common import read_json, validate, write_json
from xmalign.geometry import Vec
from xmalign.kinematics import EncoderOffsets

POSE_FORMAT = "xmalign.launch-pose/1"
OFFSET_NAMES = ("c2", "c3", "c4")


class _PoseModel(BaseModel):
    model_config = ConfigDict(extra="ignore")
    format: str
    position_mm: Annotated[list[float], Field(min_length=3, max_length=3)]
    gamma_deg: float
    covariance: Annotated[
        list[Annotated[list[float], Field(min_length=4, max_length=4)]],
        Field(min_length=4, max_length=4),
    ]
    encoder_offsets_deg: dict[str, float] = {}
    method: str = "unknown"
    residual_rms_um: float | None = None
    n_alignments: int | None = None


@dataclass
class LaunchPose:
    """Identified launch-unit pose.

    ``covariance`` is of ``(x mm, y mm, z mm, gamma rad)``, shape (4, 4);
    ``encoder_offsets_rad`` holds only the offsets that were estimated.
    """

    position_mm: Vec
    gamma_rad: float
    covariance: Vec
    encoder_offsets_rad: dict[str, float] = field(default_factory=dict)
    method: str = "joint"
    residual_rms_um: float = 0.0
    n_alignments: int = 0

    @property
    def offsets(self) -> EncoderOffsets:
        return EncoderOffsets(**{k: v for k, v in self.encoder_offsets_rad.items()})


def parse_pose(data: dict, source: str) -> LaunchPose:
    model = validate(_PoseModel, data, source)
    unknown = set(model.encoder_offsets_deg) - set(OFFSET_NAMES)
    if unknown:
        raise InputError(
            f"{source}: key 'encoder_offsets_deg': unknown offset {sorted(unknown)[0]}"
            f" (known: {', '.join(OFFSET_NAMES)})"
        )
    covariance = np.array(model.covariance, dtype=float)
    if not np.allclose(covariance, covariance.T, rtol=1e-6, atol=1e-15):
        raise InputError(f"{source}: key 'covariance' is not symmetric")
    return LaunchPose(
        position_mm=np.array(model.position_mm, dtype=float),
        gamma_rad=math.radians(model.gamma_deg),
        covariance=covariance,
        encoder_offsets_rad={k: math.radians(v) for k, v in model.encoder_offsets_deg.items()},
        method=model.method,
        residual_rms_um=model.residual_rms_um or 0.0,
        n_alignments=model.n_alignments or 0,
    )


def read_pose(path: str | Path) -> LaunchPose:
    """Read and validate a launch-pose file."""
    return parse_pose(read_json(path, POSE_FORMAT), str(path))


def pose_to_dict(pose: LaunchPose) -> dict:
    return {
        "format": POSE_FORMAT,
        "position_mm": [float(v) for v in pose.position_mm],
        "gamma_deg": math.degrees(pose.gamma_rad),
        "covariance": [[float(v) for v in row] for row in pose.covariance],
        "encoder_offsets_deg": {k: math.degrees(v) for k, v in pose.encoder_offsets_rad.items()},
        "method": pose.method,
        "residual_rms_um": float(pose.residual_rms_um),
        "n_alignments": int(pose.n_alignments),
    }


def write_pose(path: str | Path, pose: LaunchPose) -> None:
    write_json(path, pose_to_dict(pose))
