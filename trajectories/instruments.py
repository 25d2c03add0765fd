"""Programs for a laser tracker or tracer: points, paths on the fly, tracer places.

- Seed 000 measures a grid of stationary points and homogeneously distributed
  random points over the whole working volume; the random points separate the
  errors of one axis from those of the others at positions the grid does not
  combine (:func:`grid_and_random_points`).
- Seed 001 measures on the fly along straight paths: along every axis at the
  grid's coordinates of the others, and diagonal paths, which see the
  positioning errors across them (:func:`axis_paths`, :func:`diagonal_paths`).
- Seed 004 measures the same points from several tracer places around the
  volume (:func:`propose_tracer_places`).

:func:`write_instrument_program` writes the G-code (every dialect, machine
coordinates) and adds up its machine time as it goes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from trajectories.gcode.base import Dialect
from trajectories.gcode.machine_time import MachineTime, MachineTimer
from xmalign.formats.instruments import (
    TracerFile,
    TracerLength,
    TrackerFile,
    TrackerPoint,
)
from xmalign.formats.provenance import history_file
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.post.compare import grid_points
from xmalign.post.instruments import fit_joint, tracer_places, tracker_stations
from xmalign.rigid_body import Chain


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


#: Dwell at each point for a tracker or tracer reading (seed 000: 3 s), s.
POINT_DWELL_S = 3.0
#: The formats in the history of an instrument program and of a point list.
INSTRUMENT_PROGRAM_FORMAT = "xmalign.instrument-program/1"
POINT_LIST_FORMAT = "xmalign.point-list/1"
#: Seed 000's strategy: a 5 x 4 x 3 grid over the travel and 190 random points.
TRACKER_GRID = (5, 4, 3)
TRACKER_RANDOM = 190
#: Per tracer place: the grid and 380 random points (about 440, seed 004's density).
TRACER_RANDOM = 380
#: On the fly: diagonal paths besides the axis paths, and the feed (seed 001: 2500-15000).
FLY_DIAGONALS = 24
FLY_FEED_MM_MIN = 5000.0


def program_start_mm(machine: Machine) -> Vec:
    """Where a program starts: the top of Z above the X and Y minimum (as ``program``)."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    return np.array([low[0], low[1], high[2]])


def tracker_points(machine: Machine, seed: int = 0) -> Vec:
    """Seed 000's points over the whole travel, in nearest-neighbour order, (250, 3)."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    points = grid_and_random_points(low, high, TRACKER_GRID, TRACKER_RANDOM, seed)
    return visiting_order(points, program_start_mm(machine))


def tracer_points(machine: Machine, seed: int = 0) -> Vec:
    """The points one tracer place measures, in nearest-neighbour order, (440, 3)."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    points = grid_and_random_points(low, high, TRACKER_GRID, TRACER_RANDOM, seed)
    return visiting_order(points, program_start_mm(machine))


def fly_paths(machine: Machine, seed: int = 0) -> list[tuple[Vec, Vec]]:
    """Seed 001's paths: every axis end to end at the grid's coordinates, and diagonals."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    return axis_paths(low, high, TRACKER_GRID) + diagonal_paths(low, high, FLY_DIAGONALS, seed)


def propose_tracer_places(machine: Machine, n: int) -> list[Vec]:
    """``n`` tracer pivots around the volume: on the table, 10 % in from its edges.

    Evenly round the rectangle of the X/Y travel (corners first), at two heights
    150 and 250 mm below the lowest tool point in turn, so the pivots are not in
    one plane (docs/post.md: the points' height is then determined).
    """
    low, high = machine.travel_min_mm, machine.travel_max_mm
    inset = 0.1 * (high - low)
    corners = [
        (low[0] + inset[0], low[1] + inset[1]),
        (high[0] - inset[0], low[1] + inset[1]),
        (high[0] - inset[0], high[1] - inset[1]),
        (low[0] + inset[0], high[1] - inset[1]),
    ]
    places = []
    for i in range(n):
        a = np.array(corners[i % 4])
        b = np.array(corners[(i + 1) % 4])
        x, y = a + (b - a) * ((i // 4) / max(1, (n + 3) // 4))
        places.append(np.array([x, y, low[2] - (150.0 if i % 2 == 0 else 250.0)]))
    return places


@dataclass
class InstrumentProgram:
    """What a tracker or tracer measures: points at a standstill or paths on the fly."""

    points_mm: Vec = field(default_factory=lambda: np.zeros((0, 3)))
    paths_mm: list[tuple[Vec, Vec]] = field(default_factory=list)
    dwell_s: float = POINT_DWELL_S
    fly_feed_mm_min: float = FLY_FEED_MM_MIN


def _axes(point_mm: Vec) -> dict[str, float]:
    return {axis: float(v) for axis, v in zip("XYZ", point_mm, strict=True)}


def write_instrument_program(
    plan: InstrumentProgram, machine: Machine, dialect: Dialect, title: str
) -> tuple[str, MachineTime]:
    """The G-code (machine coordinates) and its machine time.

    Points: a straight move at the rapid feed to each (the tracker keeps its line
    of sight, no retract), a comment naming the point's index, a dwell. Paths: a
    straight move at the rapid feed to the start, then the path at the feed on
    the fly. The program starts and ends at the top of Z.
    """
    rapid = machine.feed_mm_min.rapid
    timer = MachineTimer(program_start_mm(machine), machine.cnc.acceleration_mm_s2)
    top = float(machine.travel_max_mm[2])
    blocks = [
        *dialect.begin(),
        dialect.comment(title),
        *dialect.history(INSTRUMENT_PROGRAM_FORMAT),
        dialect.retract({"Z": top}),
    ]
    for index, point in enumerate(plan.points_mm):
        blocks.append(dialect.comment(f"point {index}"))
        blocks.append(dialect.feed(_axes(point), rapid))
        timer.move(point, rapid)
        blocks.extend(dialect.dwell(plan.dwell_s))
        timer.dwell(plan.dwell_s)
    for number, (start, end) in enumerate(plan.paths_mm):
        blocks.append(dialect.comment(f"path {number}"))
        blocks.append(dialect.feed(_axes(start), rapid))
        timer.move(start, rapid)
        blocks.append(dialect.feed(_axes(end), plan.fly_feed_mm_min))
        timer.move(end, plan.fly_feed_mm_min)
    blocks.extend(dialect.end({"Z": top}))
    return dialect.render(blocks), timer.result()


def point_list_files(path: Path, plan: InstrumentProgram, smr_offset_mm: Vec) -> dict[Path, bytes]:
    """The point list (:func:`point_list_csv`) and ``NAME.history`` beside it, as bytes to
    write: a tracker's software reads the list, so it takes no comment (docs/formats.md)."""
    data = point_list_csv(plan, smr_offset_mm).encode("utf-8")
    history = history_file(POINT_LIST_FORMAT, path.name, data, ())
    return {path: data, path.with_name(f"{path.name}.history"): history.encode()}


def point_list_csv(plan: InstrumentProgram, smr_offset_mm: Vec) -> str:
    """The nominal SMR positions for a tracker's own software: ``name,x_mm,y_mm,z_mm``.

    Names are the point indices (paths: ``path N start`` / ``end``); the
    coordinates are machine coordinates of the SMR (tool point plus the SMR offset).
    """
    lines = ["name,x_mm,y_mm,z_mm"]
    offset = np.asarray(smr_offset_mm, dtype=float)
    for index, point in enumerate(plan.points_mm):
        lines.append(f"{index}," + ",".join(f"{v:.3f}" for v in point + offset))
    for number, (start, end) in enumerate(plan.paths_mm):
        for end_name, point in (("start", start), ("end", end)):
            lines.append(
                f"path {number} {end_name}," + ",".join(f"{v:.3f}" for v in point + offset)
            )
    return "\n".join(lines) + "\n"


def tracker_place(machine: Machine) -> Vec:
    """Where the tracker is assumed to stand for planning: on the table in the middle of
    the travel, 300 mm below the lowest tool point (its noise grows with the distance)."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    return np.array([(low[0] + high[0]) / 2, (low[1] + high[1]) / 2, low[2] - 300.0])


#: Compensation-point spacing of the planned fit, mm: exact readings cannot cross-validate
#: a spacing (post chooses it from the real readings' scatter; docs/post.md).
PLAN_KNOT_SPACING_MM = 200.0
#: Samples per mm of path for a planned tracker on the fly (one every 20 mm).
FLY_SPACING_MM = 20.0


def _exact_tracker_rows(
    program: InstrumentProgram, tracker_mm: Vec, smr_mm: Vec, run: int
) -> list[TrackerPoint]:
    """What a tracker at ``tracker_mm`` (frame along the MCS) reads on a perfect machine."""
    rows = [
        TrackerPoint("T1", run, index, point, point + smr_mm - tracker_mm)
        for index, point in enumerate(program.points_mm)
    ]
    for start, end in program.paths_mm:
        count = max(2, int(np.linalg.norm(end - start) / FLY_SPACING_MM) + 1)
        for fraction in np.linspace(0.0, 1.0, count):
            point = start + fraction * (end - start)
            rows.append(TrackerPoint("T1", run, None, start, point + smr_mm - tracker_mm, end))
    return rows


def information_limit_um(
    machine: Machine,
    programs: list[InstrumentProgram],
    tracker_mm: Vec | None = None,
    pivots_mm: list[Vec] | None = None,
    runs: int = 1,
) -> float:
    """How well a plan determines the volumetric error over the whole travel, um (k = 1).

    Fits the exact readings a perfect machine would give (a tracker at
    ``tracker_mm`` with its frame along the MCS measuring every program, or the
    tracer at ``pivots_mm[i]`` measuring ``programs[i]``; ``runs`` times each)
    and returns the RMS standard uncertainty that the fit's covariance gives the
    volumetric error over an 8 x 8 x 8 grid of the travel, rigid motion removed
    (:meth:`xmalign.post.instruments.JointFit.volumetric_u_um`): the noise of
    the machine file's uncertainty models, propagated; not the tables' model error.

    Raises
    ------
    GeometryError
        The plan cannot determine the errors or a setup (the fit's message).
    """
    smr = machine.smr_offset
    trackers = []
    if tracker_mm is not None:
        rows = [
            row
            for run in range(runs)
            for program in programs
            for row in _exact_tracker_rows(program, np.asarray(tracker_mm, float), smr, run)
        ]
        trackers = tracker_stations([TrackerFile(rows, "plan")])
    lengths = [
        TracerLength(f"P{i + 1}", run, index, point, float(np.linalg.norm(point + smr - pivot)))
        for i, pivot in enumerate(pivots_mm or [])
        for run in range(runs)
        for index, point in enumerate(programs[i].points_mm)
    ]
    tracers = tracer_places([TracerFile(lengths, "plan")]) if lengths else []
    chain = Chain.parse(machine.chain)
    joint = fit_joint(
        [], trackers, tracers, chain, np.ones(6), smr, machine.tracker, machine.tracer,
        (machine.travel_min_mm, machine.travel_max_mm), PLAN_KNOT_SPACING_MM,
    )  # fmt: skip
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 8)
    return joint.volumetric_u_um(chain, grid)
