"""What the virtual tracker and tracer get wrong besides noise (docs/formats.md).

- **Angle errors** (tracker): the azimuth and the elevation reading each carry a
  smooth error of the beam's direction in the tracker's frame, the same in every
  run at a station: ``sum_k=1,2 a_k cos k·az + b_k sin k·az + c_k cos k·el +
  d_k sin k·el``, eight coefficients drawn once per station with standard
  deviation ``s / 2`` (so the RMS over all directions is ``s``).
- **Scale** (tracker and tracer): every length a station measures in one run is
  off by one factor ``1 + u·N(0, 1)·1e-6`` (what is left of the air compensation).
- **Material temperature**: the machine's scales grow by ``α·(T − 20)`` about the
  CNC origin while their temperature drifts through a run; the rows carry
  ``material_c``.
- **Several SMR positions**: each SMR position is a run of its own (the SMR is
  changed between them, a tracer's count restarts).

Every draw comes from its own seeded generator, so a station's readings without
these errors are exactly what they were without the keywords.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from sim.machine import VirtualMachine
from xmalign.geometry import Vec

#: Streams of the seeded generators (kept apart from the noise's).
ANGLE_STREAM, SCALE_STREAM = 7001, 7002


def angle_coefficients(seed: int) -> Vec:
    """A station's unit angle-error coefficients, (2, 8): azimuth and elevation rows.

    Columns: ``cos az, sin az, cos el, sin el`` for k = 1, then for k = 2.
    Multiply by ``s / 2`` (urad) for the errors of a tracker with
    ``angle_systematic_urad: s``.
    """
    return np.random.default_rng([seed, ANGLE_STREAM]).normal(size=(2, 8))


def direction_basis(frame_mm: Vec) -> Vec:
    """The eight functions of the beam's direction at points in the tracker's frame, (N, 8)."""
    frame = np.atleast_2d(frame_mm)
    az = np.arctan2(frame[:, 1], frame[:, 0])
    el = np.arctan2(frame[:, 2], np.hypot(frame[:, 0], frame[:, 1]))
    return np.column_stack(
        [f(k * angle) for k in (1, 2) for angle in (az, el) for f in (np.cos, np.sin)]
    )


def with_angle_errors(frame_mm: Vec, coefficients: Vec, angle_systematic_urad: float) -> Vec:
    """Points in the tracker's frame as read with the angle errors, (N, 3); distances kept."""
    frame = np.atleast_2d(frame_mm)
    if angle_systematic_urad == 0.0:
        return frame
    errors_rad = direction_basis(frame) @ coefficients.T * angle_systematic_urad / 2 * 1e-6
    distance = np.linalg.norm(frame, axis=1)
    az = np.arctan2(frame[:, 1], frame[:, 0]) + errors_rad[:, 0]
    el = np.arctan2(frame[:, 2], np.hypot(frame[:, 0], frame[:, 1])) + errors_rad[:, 1]
    return distance[:, None] * np.column_stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    )


def scale_factor(seed: int, run: int, scale_ppm: float) -> float:
    """The length factor of a station's run (1 without a scale error)."""
    draw = np.random.default_rng([seed, run, SCALE_STREAM]).normal()
    return 1.0 + scale_ppm * 1e-6 * float(draw)


@dataclass(frozen=True)
class MaterialDrift:
    """The machine's scale temperature drifting linearly through each run, deg C."""

    start_c: float
    end_c: float
    expansion_ppm_per_k: float

    def temperatures_c(self, count: int) -> Vec:
        """The temperature at each of ``count`` readings in order, (count,)."""
        return np.linspace(self.start_c, self.end_c, count)

    def growth_mm(self, cnc_mm: Vec, temperatures_c: Vec) -> Vec:
        """How far the scales' growth moves each tool point, (N, 3)."""
        strain = self.expansion_ppm_per_k * 1e-6 * (np.asarray(temperatures_c) - 20.0)
        return strain[:, None] * np.atleast_2d(cnc_mm)


@dataclass(frozen=True)
class SmrBlock:
    """The readings of one SMR position: its name (None: the single offset), offset, points."""

    name: str | None
    offset_mm: Vec
    indices: npt.NDArray[np.intp]


def smr_blocks(
    count: int,
    smr_offset_mm: Vec,
    smr_offsets_mm: Mapping[str, Vec] | None,
    smr_of_point: Sequence[str] | None,
) -> list[SmrBlock]:
    """The SMR positions a program measures and with which of its ``count`` points.

    Without ``smr_offsets_mm``: one block, every point, ``smr_offset_mm``. With it:
    one block per name, each with every point, or the points ``smr_of_point``
    gives that name (a program that shares its points among the SMR positions).
    """
    if not smr_offsets_mm:
        return [SmrBlock(None, np.asarray(smr_offset_mm, float), np.arange(count))]
    names = np.asarray(smr_of_point) if smr_of_point is not None else None
    return [
        SmrBlock(
            name,
            np.asarray(offset, float),
            np.arange(count) if names is None else np.flatnonzero(names == name),
        )
        for name, offset in smr_offsets_mm.items()
    ]


def actual_smr_points(
    machine: VirtualMachine, cnc_mm: Vec, block: SmrBlock, material: MaterialDrift | None
) -> tuple[Vec, list[float | None]]:
    """Where the SMR of ``block`` really is at the commanded points, (N, 3), and the
    material temperature at each (None without a drift)."""
    actual, _ = machine.actual_functional_point(cnc_mm, np.ones_like(cnc_mm), block.offset_mm)
    if material is None:
        return actual, [None] * len(cnc_mm)
    temperatures = material.temperatures_c(len(cnc_mm))
    return actual + material.growth_mm(cnc_mm, temperatures), temperatures.tolist()
