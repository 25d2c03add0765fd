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

import numpy as np

from trajectories.gcode.base import Dialect
from trajectories.gcode.machine_time import MachineTime, MachineTimer
from xmalign.formats.instruments import (
    TracerFile,
    TracerLength,
    TrackerFile,
    TrackerPoint,
)
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
#: The operator mounts another SMR (machine time at the programmed stop), s.
SMR_CHANGE_S = 60.0
#: Proposed SMR positions where the machine file names none: its ``smr_offset_mm`` and
#: this far beside it along the spindle frame's X and Y (an SMR nest on an arm), mm.
SMR_ARM_MM = 100.0
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


def plan_smr_positions(machine: Machine) -> tuple[dict[str, Vec], bool]:
    """The SMR positions to measure with, and whether they were proposed here.

    The machine file's ``smr_offsets_mm``; where it names none, three: its
    ``smr_offset_mm`` and :data:`SMR_ARM_MM` beside it along the spindle frame's X
    and Y, not on one line through the tool point (every one of the 21 errors is
    then determined, docs/formats.md).
    """
    named = machine.smr_offsets()
    if named:
        return named, False
    base = machine.smr_offset
    arm_x, arm_y = np.array([SMR_ARM_MM, 0.0, 0.0]), np.array([0.0, SMR_ARM_MM, 0.0])
    return {"A": base, "B": base + arm_x, "C": base + arm_y}, True


def shared_points_program(
    machine: Machine, n_random: int, smr_offsets_mm: dict[str, Vec], seed: int = 0
) -> InstrumentProgram:
    """Seed 000's grid and random points, shared among the SMR positions.

    Each SMR position measures the grid and every ``len(smr_offsets_mm)``-th random
    point, the positions one after another, each in nearest-neighbour order (the
    machine time grows by the grid, not by the number of positions). Without SMR
    positions: the grid and every random point, as :func:`tracker_points`.
    """
    low, high = machine.travel_min_mm, machine.travel_max_mm
    points = grid_and_random_points(low, high, TRACKER_GRID, n_random, seed)
    names = list(smr_offsets_mm) or [""]
    grid = int(np.prod(TRACKER_GRID))
    start = program_start_mm(machine)
    blocks, labels = [], []
    for k, name in enumerate(names):
        share = points[grid + k :: len(names)]
        blocks.append(visiting_order(np.concatenate([points[:grid], share]), start))
        start = blocks[-1][-1]
        labels += [name] * len(blocks[-1])
    return InstrumentProgram(
        points_mm=np.concatenate(blocks),
        smr_names=labels if smr_offsets_mm else [],
        smr_offsets_mm=dict(smr_offsets_mm),
    )


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
    """What a tracker or tracer measures: points at a standstill or paths on the fly.

    ``smr_names`` (one per point, or empty: the machine file's single
    ``smr_offset_mm``) says which SMR position measures each point; the points of
    one SMR follow each other, and ``smr_offsets_mm`` gives each name's offset
    (spindle frame, mm).
    """

    points_mm: Vec = field(default_factory=lambda: np.zeros((0, 3)))
    paths_mm: list[tuple[Vec, Vec]] = field(default_factory=list)
    dwell_s: float = POINT_DWELL_S
    fly_feed_mm_min: float = FLY_FEED_MM_MIN
    smr_names: list[str] = field(default_factory=list)
    smr_offsets_mm: dict[str, Vec] = field(default_factory=dict)

    @property
    def smr_order(self) -> list[str]:
        """The SMR positions in the order the program mounts them."""
        return list(dict.fromkeys(self.smr_names))

    def run_of(self, index: int, repeat: int) -> int:
        """The file's run of point ``index`` in the ``repeat``-th run of the program: each
        SMR position is a run of its own (a tracer's count restarts at the change)."""
        if not self.smr_names:
            return repeat
        order = self.smr_order
        return repeat * len(order) + order.index(self.smr_names[index])

    def smr_offset_mm(self, index: int, single_mm: Vec) -> Vec:
        """The SMR offset of point ``index`` (``single_mm`` without SMR names), (3,)."""
        if not self.smr_names:
            return np.asarray(single_mm, dtype=float)
        return np.asarray(self.smr_offsets_mm[self.smr_names[index]], dtype=float)


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
    blocks = [*dialect.begin(), dialect.comment(title), dialect.retract({"Z": top})]
    mounted: str | None = None
    for index, point in enumerate(plan.points_mm):
        if plan.smr_names and plan.smr_names[index] != mounted:
            mounted = plan.smr_names[index]
            blocks += _smr_change(dialect, mounted, plan.smr_offsets_mm[mounted], top)
            timer.move(np.array([*timer.position_mm[:2], top]), rapid)
            timer.dwell(SMR_CHANGE_S)
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


def _smr_change(dialect: Dialect, name: str, offset_mm: Vec, top_mm: float) -> list[str]:
    """Up to the top of Z and a programmed stop: the operator mounts SMR ``name``."""
    where = ", ".join(f"{v:g}" for v in offset_mm)
    text = f"mount SMR {name} at {where} mm from the tool point (spindle frame), then start"
    return [dialect.retract({"Z": top_mm}), dialect.comment(text), dialect.message(text),
            dialect.stop()]  # fmt: skip


def point_list_csv(plan: InstrumentProgram, smr_offset_mm: Vec) -> str:
    """The nominal SMR positions for a tracker's own software: ``name,x_mm,y_mm,z_mm``.

    Names are the point indices (paths: ``path N start`` / ``end``); the
    coordinates are machine coordinates of the SMR (tool point plus the SMR
    offset). A program with several SMR positions adds the column ``smr``.
    """
    lines = ["name,x_mm,y_mm,z_mm" + (",smr" if plan.smr_names else "")]
    offset = np.asarray(smr_offset_mm, dtype=float)
    for index, point in enumerate(plan.points_mm):
        smr = f",{plan.smr_names[index]}" if plan.smr_names else ""
        at = point + plan.smr_offset_mm(index, smr_offset_mm)
        lines.append(f"{index}," + ",".join(f"{v:.3f}" for v in at) + smr)
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


def _smr_name(program: InstrumentProgram, index: int) -> str | None:
    return program.smr_names[index] if program.smr_names else None


def _exact_tracker_rows(
    program: InstrumentProgram, tracker_mm: Vec, smr_mm: Vec, run: int
) -> list[TrackerPoint]:
    """What a tracker at ``tracker_mm`` (frame along the MCS) reads on a perfect machine."""
    rows = [
        TrackerPoint(
            "T1", program.run_of(index, run), index, point,
            point + program.smr_offset_mm(index, smr_mm) - tracker_mm,
            smr=_smr_name(program, index),
        )
        for index, point in enumerate(program.points_mm)
    ]  # fmt: skip
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
        TracerLength(
            f"P{i + 1}", programs[i].run_of(index, run), index, point,
            float(np.linalg.norm(point + programs[i].smr_offset_mm(index, smr) - pivot)),
            smr=_smr_name(programs[i], index),
        )
        for i, pivot in enumerate(pivots_mm or [])
        for run in range(runs)
        for index, point in enumerate(programs[i].points_mm)
    ]  # fmt: skip
    tracers = tracer_places([TracerFile(lengths, "plan")]) if lengths else []
    chain = Chain.parse(machine.chain)
    named = {name: o for program in programs for name, o in program.smr_offsets_mm.items()}
    joint = fit_joint(
        [], trackers, tracers, chain, np.ones(6), smr, machine.tracker, machine.tracer,
        (machine.travel_min_mm, machine.travel_max_mm), PLAN_KNOT_SPACING_MM,
        smr_offsets_mm=named,
    )  # fmt: skip
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 8)
    return joint.volumetric_u_um(chain, grid)


@dataclass
class InstrumentPlan:
    """A tracker or tracer calibration as ``xmalign program --instrument`` plans it.

    ``runs`` is how often the program is run: a tracker's repeats, a tracer's places
    one after another, or once for tracers at once (``simultaneous``).
    """

    instrument: str
    program: InstrumentProgram
    runs: int
    limit_um: float
    notes: list[str]
    tracker_mm: Vec | None = None
    pivots_mm: list[Vec] = field(default_factory=list)
    simultaneous: bool = False


def _triple(values: Vec) -> str:
    return ", ".join(f"{v:.0f}" for v in values)


def _smr_notes(program: InstrumentProgram, proposed: bool) -> list[str]:
    """Which SMR to mount when (the program stops for each), and where they come from."""
    if not program.smr_names:
        return []
    firsts = {name: program.smr_names.index(name) for name in program.smr_order}
    when = ", ".join(
        f"SMR {name} ({_triple(program.smr_offsets_mm[name])} mm) before point {first}"
        for name, first in firsts.items()
    )
    origin = (
        "proposed: the machine file names no smr_offsets_mm; add these to it before post"
        if proposed
        else "the machine file's smr_offsets_mm"
    )
    return [
        f"SMR positions ({origin}): mount {when}; the program stops for each change,"
        " and each SMR position is a run of its own in the readings"
    ]


def plan_instrument(
    machine: Machine,
    instrument: str,
    on_the_fly: bool = False,
    places: int = 4,
    simultaneous: bool = False,
) -> InstrumentPlan:
    """Plan a tracker (points with several SMR positions, or paths on the fly) or tracer
    (``places`` places, the same points from each; ``simultaneous``: every tracer
    following the SMR in the same run) calibration over the whole travel.

    Raises
    ------
    GeometryError
        The plan cannot determine the errors (:func:`information_limit_um`).
    """
    smr_offsets, proposed = plan_smr_positions(machine)
    if instrument == "tracker":
        if on_the_fly:
            program, runs = InstrumentProgram(paths_mm=fly_paths(machine)), 1
            what = f"{len(program.paths_mm)} paths on the fly, the SMR at smr_offset_mm"
        else:
            program, runs = shared_points_program(machine, TRACKER_RANDOM, smr_offsets), 2
            what = f"{len(program.points_mm)} points, run it twice"
        where = tracker_place(machine)
        limit = information_limit_um(machine, [program], tracker_mm=where, runs=runs)
        notes = [f"tracker: {what}; stand it on the table near {_triple(where)} mm (MCS)"]
        return InstrumentPlan(
            instrument, program, runs, limit, notes + _smr_notes(program, proposed), where
        )
    pivots = propose_tracer_places(machine, places)
    program = shared_points_program(machine, TRACER_RANDOM, smr_offsets)
    limit = information_limit_um(machine, [program] * len(pivots), pivots_mm=pivots)
    if simultaneous:
        notes = [
            f"tracers at once: stand one at each of the {len(pivots)} places and let every one"
            " follow the SMR through the same run; run the program once (one station per"
            " tracer in the lengths file)"
        ]
    else:
        notes = [f"tracer: run the program once at each of the {len(pivots)} places"]
    notes += [
        f"tracer place P{i + 1}: pivot near {_triple(p)} mm (MCS)" for i, p in enumerate(pivots)
    ]
    notes.append(f"tracer: {len(program.points_mm)} points from each place")
    runs = 1 if simultaneous else len(pivots)
    return InstrumentPlan(
        instrument, program, runs, limit, notes + _smr_notes(program, proposed), None, pivots,
        simultaneous,
    )  # fmt: skip


def machine_time_note(plan: InstrumentPlan, time: MachineTime) -> str:
    """The plan's machine time and how well it determines the volumetric error."""
    return (
        f"machine time: {time.total_s / 60:.1f} min per run, {plan.runs * time.total_s / 60:.1f}"
        f" min in all; the volumetric error over the whole travel to about {plan.limit_um:.2f} um"
        " (standard uncertainty from the machine file's instrument uncertainty, RMS over the"
        " travel; the machine's repeatability and the tables' model error come on top)"
    )
