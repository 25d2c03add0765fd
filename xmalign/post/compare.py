"""Compare two error models by the volumetric error they predict, up to a rigid motion.

The six lines (like any measurement with the machine's own axes as reference)
cannot see where the machine as a whole stands and how it is turned, so two
models are the same machine when their volumetric errors differ by a rigid
motion ``a + w x p`` only.
"""

from __future__ import annotations

import numpy as np

from xmalign.geometry import Vec, skew
from xmalign.rigid_body import Chain, ErrorModel, deviation


def remove_rigid_motion(points_mm: Vec, difference_mm: Vec) -> Vec:
    """``difference`` minus its least-squares rigid motion ``a + w x p``, shape (N, 3).

    Parameters
    ----------
    points_mm : ndarray, shape (N, 3)
    difference_mm : ndarray, shape (N, 3)
    """
    centred = points_mm - points_mm.mean(axis=0)
    design = np.concatenate(
        [np.tile(np.eye(3), (len(points_mm), 1)), np.concatenate([-skew(p) for p in centred])],
        axis=1,
    )
    solution, *_ = np.linalg.lstsq(design, difference_mm.ravel(), rcond=None)
    return (difference_mm.ravel() - design @ solution).reshape(-1, 3)


def grid_points(low_mm: Vec, high_mm: Vec, n: int = 6) -> Vec:
    """A regular n x n x n grid of CNC points in a box, shape (n**3, 3)."""
    axes = [np.linspace(lo, hi, n) for lo, hi in zip(low_mm, high_mm, strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def volumetric_rms_um(
    chain: Chain, points_mm: Vec, model: ErrorModel, reference: ErrorModel
) -> float:
    """RMS length of the volumetric difference of two models after removing a rigid motion, um.

    Both are evaluated for the tool point (``t = 0``).
    """
    dp_model, _ = deviation(chain, points_mm, np.zeros(3), model)
    dp_reference, _ = deviation(chain, points_mm, np.zeros(3), reference)
    residual = remove_rigid_motion(points_mm, dp_model - dp_reference)
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))) * 1e3)
