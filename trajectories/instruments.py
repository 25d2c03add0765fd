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


def axis_paths(low_mm: Vec, high_mm: Vec, grid: tuple[int, int, int]) -> list[tuple[Vec, Vec]]:
    """Straight paths over the whole travel along each axis, at the grid's other coordinates.

    Seed 001's strategy for a tracker on the fly: every axis moves end to end at
    each grid position of the two others, so its errors are seen across the path
    at several lever arms, and each path's offset carries the standing axes' errors.
    Paths alternate in direction (a serpentine), which saves the return moves.
    """
    low, high = np.asarray(low_mm, dtype=float), np.asarray(high_mm, dtype=float)
    ticks = [np.linspace(lo, hi, n) for lo, hi, n in zip(low, high, grid, strict=True)]
    paths = []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        for number, (a, b) in enumerate((a, b) for a in ticks[others[0]] for b in ticks[others[1]]):
            start, end = np.empty(3), np.empty(3)
            start[others], end[others] = (a, b), (a, b)
            start[axis], end[axis] = (low[axis], high[axis])
            if number % 2:
                start, end = end, start
            paths.append((np.round(start, 3), np.round(end, 3)))
    return paths


def paths_time_s(
    paths_mm: list[tuple[Vec, Vec]],
    start_mm: Vec,
    feed_mm_min: float,
    rapid_mm_min: float,
    accel_mm_s2: float | None,
) -> float:
    """Machine time of the paths at ``feed_mm_min``, with rapid moves between them, s."""
    here = np.asarray(start_mm, dtype=float)
    total = 0.0
    for start, end in paths_mm:
        total += move_time_s(float(np.linalg.norm(start - here)), rapid_mm_min, accel_mm_s2)
        total += move_time_s(float(np.linalg.norm(end - start)), feed_mm_min, accel_mm_s2)
        here = end
    return total


def diagonal_paths(low_mm: Vec, high_mm: Vec, n: int, seed: int = 0) -> list[tuple[Vec, Vec]]:
    """``n`` straight paths across the box, each from a random point of one face to one of
    the opposite face (X, Y, Z faces in turn), rounded to 1 um.

    A path oblique to an axis sees that axis's positioning error across it
    (seed 001: the positioning error is inferred from diagonal paths and paths
    perpendicular to the axis); axis-parallel paths alone see it only at the
    coordinates where they stand.
    """
    low, high = np.asarray(low_mm, dtype=float), np.asarray(high_mm, dtype=float)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(n):
        axis = i % 3
        start = low + rng.random(3) * (high - low)
        end = low + rng.random(3) * (high - low)
        start[axis], end[axis] = (low[axis], high[axis]) if i % 2 == 0 else (high[axis], low[axis])
        paths.append((np.round(start, 3), np.round(end, 3)))
    return paths
