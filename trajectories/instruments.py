"""Point sets for a laser tracker or tracer: a regular grid plus random points (seed 000).

Seed 000 measures a grid of stationary points on the edges of the working
volume and homogeneously distributed random points inside it; the random
points separate the errors of one axis from those of the others at positions
the grid does not combine.
"""

from __future__ import annotations

import numpy as np

from trajectories.gcode.machine_time import move_time_s
from xmalign.geometry import Vec


def grid_and_random_points(
    low_mm: Vec, high_mm: Vec, grid: tuple[int, int, int], n_random: int, seed: int = 0
) -> Vec:
    """A regular ``grid`` over the box plus ``n_random`` uniform points, rounded to 1 um.

    Parameters
    ----------
    low_mm, high_mm : ndarray, shape (3,)
        The box (CNC coordinates).
    grid : (int, int, int)
        Points along X, Y and Z (each at least 2).
    n_random : int
    seed : int
        Seeds the random points (a plan must be reproducible).

    Returns
    -------
    ndarray, shape (grid[0] * grid[1] * grid[2] + n_random, 3)
        The grid first (X fastest... Z slowest), then the random points.
    """
    low, high = np.asarray(low_mm, dtype=float), np.asarray(high_mm, dtype=float)
    axes = [np.linspace(lo, hi, n) for lo, hi, n in zip(low, high, grid, strict=True)]
    regular = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    random = low + rng.random((n_random, 3)) * (high - low)
    return np.round(np.concatenate([regular, random]), 3)


def visiting_order(points_mm: Vec, start_mm: Vec) -> Vec:
    """The points in the order a greedy nearest-neighbour tour from ``start_mm`` visits them.

    Random points in their drawn order cost the machine twice the moving time.
    """
    remaining = np.asarray(points_mm, dtype=float)
    here = np.asarray(start_mm, dtype=float)
    order = []
    left = np.ones(len(remaining), dtype=bool)
    for _ in range(len(remaining)):
        distance = np.where(left, np.linalg.norm(remaining - here, axis=1), np.inf)
        nearest = int(np.argmin(distance))
        order.append(nearest)
        left[nearest] = False
        here = remaining[nearest]
    return remaining[order]


#: Dwell at each point for a tracker or tracer reading (seed 000: 3 s), s.
POINT_DWELL_S = 3.0


def point_list_time_s(
    points_mm: Vec,
    start_mm: Vec,
    feed_mm_min: float,
    accel_mm_s2: float | None,
    dwell_s: float = POINT_DWELL_S,
) -> float:
    """Machine time to visit the points in order and dwell at each, s.

    Every move runs from rest to rest on a straight path at ``feed_mm_min``
    (:func:`trajectories.gcode.machine_time.move_time_s`).
    """
    path = np.vstack([np.asarray(start_mm, dtype=float), np.asarray(points_mm, dtype=float)])
    lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    moving = sum(move_time_s(float(length), feed_mm_min, accel_mm_s2) for length in lengths)
    return moving + dwell_s * len(points_mm)
