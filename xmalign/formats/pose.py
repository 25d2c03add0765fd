"""Launch-unit pose (``xmalign.launch-pose/1``) of docs/formats.md."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field

from xmalign.formats.common import (
    Angle_deg,
    FileModel,
    Finite,
    Vector3_mm,
    key_error,
    read_json,
    validate,
    write_json,
)
from xmalign.formats.provenance import FileSource, Provenance, json_history, read_json_history
from xmalign.geometry import Vec
from xmalign.kinematics import EncoderOffsets

POSE_FORMAT = "xmalign.launch-pose/1"
OFFSET_NAMES = ("c2", "c3", "c4")


class _PoseModel(FileModel):
    format: str
    position_mm: Vector3_mm
    gamma_deg: Angle_deg
    covariance: Annotated[
        list[Annotated[list[Finite], Field(min_length=4, max_length=4)]],
        Field(min_length=4, max_length=4),
    ]
    encoder_offsets_deg: dict[str, Angle_deg] = {}
    method: str = "unknown"
    residual_rms_um: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] | None = None
    n_alignments: Annotated[int, Field(ge=0)] | None = None
    machine: str | None = None
    machine_sha256: str | None = None


def check_covariance(covariance: Vec, source: str, key: str) -> None:
    """Refuse a covariance that is not symmetric positive semi-definite, naming the key."""
    scale = float(np.max(np.abs(covariance))) or 1.0
    if not np.allclose(covariance, covariance.T, rtol=1e-6, atol=1e-12 * scale):
        raise key_error(source, key, "not symmetric")
    if np.any(np.diag(covariance) < 0):
        raise key_error(source, key, "a variance on the diagonal is negative")
    if np.min(np.linalg.eigvalsh((covariance + covariance.T) / 2)) < -1e-9 * scale:
        raise key_error(source, key, "not positive semi-definite (a negative eigenvalue)")


@dataclass
class LaunchPose:
    """Identified launch-unit pose.

    ``covariance`` is of ``(x mm, y mm, z mm, gamma rad)``, shape (4, 4);
    ``encoder_offsets_rad`` holds only the offsets that were estimated; ``source``
    is the file it was read from (its SHA-256), None for a pose identified now, and
    ``history`` what that file says of its making. ``machine`` and ``machine_sha256``
    (:meth:`Machine.geometry_sha256`) name the machine it was identified on (None: a
    pose written before poses named it, or identified without a machine file).
    """

    position_mm: Vec
    gamma_rad: float
    covariance: Vec
    encoder_offsets_rad: dict[str, float] = field(default_factory=dict)
    method: str = "joint"
    residual_rms_um: float = 0.0
    n_alignments: int = 0
    source: FileSource | None = field(default=None, compare=False)
    machine: str | None = field(default=None, compare=False)
    machine_sha256: str | None = field(default=None, compare=False)
    history: Provenance | None = field(default=None, compare=False)

    @property
    def offsets(self) -> EncoderOffsets:
        return EncoderOffsets(**{k: v for k, v in self.encoder_offsets_rad.items()})


def parse_pose(data: dict, source: str) -> LaunchPose:
    model = validate(_PoseModel, data, source)
    unknown = set(model.encoder_offsets_deg) - set(OFFSET_NAMES)
    if unknown:
        raise key_error(
            source,
            f"encoder_offsets_deg.{sorted(unknown)[0]}",
            f"not a known offset (known: {', '.join(OFFSET_NAMES)})",
        )
    covariance = np.array(model.covariance, dtype=float)
    check_covariance(covariance, source, "covariance")
    return LaunchPose(
        position_mm=np.array(model.position_mm, dtype=float),
        gamma_rad=math.radians(model.gamma_deg),
        covariance=covariance,
        encoder_offsets_rad={k: math.radians(v) for k, v in model.encoder_offsets_deg.items()},
        method=model.method,
        residual_rms_um=model.residual_rms_um or 0.0,
        n_alignments=model.n_alignments or 0,
        machine=model.machine,
        machine_sha256=model.machine_sha256,
    )


def read_pose(path: str | Path) -> LaunchPose:
    """Read and validate a launch-pose file; ``source`` records its SHA-256, ``history``
    its history."""
    data = read_json(path, POSE_FORMAT)
    pose = parse_pose(data, str(path))
    pose.source = FileSource.of("pose", path)
    pose.history = read_json_history(data, str(path))
    return pose


def pose_to_dict(pose: LaunchPose) -> dict:
    identity = {"machine": pose.machine, "machine_sha256": pose.machine_sha256}
    return {
        "format": POSE_FORMAT,
        **{key: value for key, value in identity.items() if value is not None},
        "position_mm": [float(v) for v in pose.position_mm],
        "gamma_deg": math.degrees(pose.gamma_rad),
        "covariance": [[float(v) for v in row] for row in pose.covariance],
        "encoder_offsets_deg": {k: math.degrees(v) for k, v in pose.encoder_offsets_rad.items()},
        "method": pose.method,
        "residual_rms_um": float(pose.residual_rms_um),
        "n_alignments": int(pose.n_alignments),
    }


def write_pose(path: str | Path, pose: LaunchPose, inputs: Iterable[FileSource] = ()) -> None:
    """Write the pose with its history (``inputs``: the session and machine files)."""
    write_json(path, json_history(POSE_FORMAT, inputs) | pose_to_dict(pose))
