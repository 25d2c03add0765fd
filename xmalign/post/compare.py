"""Compare two error models by the volumetric error they predict, up to a rigid motion.

The six lines (like any measurement with the machine's own axes as reference)
cannot see where the machine as a whole stands and how it is turned, so two
models are the same machine when their volumetric errors differ by a rigid
motion ``a + w x p`` only.
"""

from __future__ import annotations

import numpy as np

from xmalign.formats.error_tables import ErrorTableSet
from xmalign.geometry import Vec, skew
from xmalign.post.ranges import measured_range_mm
from xmalign.rigid_body import (
    AXES,
    Chain,
    ErrorModel,
    deviation,
    squareness_deviation,
)


def rigid_motion_design(points_mm: Vec) -> Vec:
    """Columns of a rigid motion ``a + w x p`` at points (rows 3 i + c), shape (3N, 6)."""
    centred = points_mm - points_mm.mean(axis=0)
    return np.concatenate(
        [np.tile(np.eye(3), (len(points_mm), 1)), np.concatenate([-skew(p) for p in centred])],
        axis=1,
    )


def remove_rigid_motion(points_mm: Vec, difference_mm: Vec) -> Vec:
    """``difference`` minus its least-squares rigid motion ``a + w x p``, shape (N, 3).

    Parameters
    ----------
    points_mm : ndarray, shape (N, 3)
    difference_mm : ndarray, shape (N, 3)
    """
    design = rigid_motion_design(points_mm)
    solution, *_ = np.linalg.lstsq(design, difference_mm.ravel(), rcond=None)
    return (difference_mm.ravel() - design @ solution).reshape(-1, 3)


def grid_points(low_mm: Vec, high_mm: Vec, n: int = 6) -> Vec:
    """A regular n x n x n grid of CNC points in a box, shape (n**3, 3)."""
    axes = [np.linspace(lo, hi, n) for lo, hi in zip(low_mm, high_mm, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def volumetric_rms_um(
    chain: Chain,
    points_mm: Vec,
    model: ErrorModel,
    reference: ErrorModel,
    reference_offset_mm: Vec | None = None,
) -> float:
    """RMS length of the volumetric difference of two models after removing a rigid motion, um.

    Both are evaluated for the tool point (``t = 0``), or the reference at
    ``reference_offset_mm`` (tables fitted for another functional point, such as
    an SMR's, compared with the truth there).
    """
    dp_model, _ = deviation(chain, points_mm, np.zeros(3), model)
    offset = np.zeros(3) if reference_offset_mm is None else reference_offset_mm
    dp_reference, _ = deviation(chain, points_mm, offset, reference)
    residual = remove_rigid_motion(points_mm, dp_model - dp_reference)
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))) * 1e3)


def measured_box_mm(tables: ErrorTableSet) -> tuple[Vec, Vec]:
    """Per axis, the measured range of its positioning table: lower and upper, (3,) each."""
    low, high = np.zeros(3), np.zeros(3)
    for k, axis in enumerate(AXES):
        low[k], high[k] = measured_range_mm(tables.positioning_table(axis))
    return low, high


def _shears(points_mm: Vec, dp_mm: Vec) -> Vec:
    """The shears (xy, yz, xz) of a field's least-squares linear part, shape (3,)."""
    design = np.concatenate([np.ones((len(points_mm), 1)), points_mm], axis=1)
    coefficients, *_ = np.linalg.lstsq(design, dp_mm, rcond=None)
    gradient = coefficients[1:].T  # gradient[i, j] = d dp_i / d p_j
    return np.array(
        [
            gradient[0, 1] + gradient[1, 0],
            gradient[1, 2] + gradient[2, 1],
            gradient[0, 2] + gradient[2, 0],
        ],
        dtype=float,
    )


def tool_point_squareness_rad(chain: Chain, points_mm: Vec, model: ErrorModel) -> Vec:
    """The squareness ``[EC0Y, EA0Z, EB0Z]`` the tool point shows over ``points``, rad (3,).

    The shear of the volumetric error's linear part (a rigid rotation has none),
    in the units of the three squareness errors: the machine's squareness plus
    what the angular errors' Abbe terms and any loaded compensation add to it.
    Comparable between a machine as found and as left; equal to the model's own
    squareness only when nothing else is linear across the axes.
    """
    unit = np.column_stack(
        [_shears(points_mm, squareness_deviation(points_mm, e)) for e in np.eye(3)]
    )
    dp_mm, _ = deviation(chain, points_mm, np.zeros(3), model)
    return np.asarray(np.linalg.solve(unit, _shears(points_mm, dp_mm)), dtype=np.float64)
