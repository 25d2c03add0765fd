"""Where to put the launch unit for a second station so the lines cover every stroke.

From one launch position the lines stop short of the strokes: the receiver
must stay the stand-off away from the launch cp, so the axis lines leave out
the stretch next to the launch unit (X and Y) and, with the launch unit at
the lowest height the receiver reaches, the lower part of Z. The diagonals
from a station at the opposite corner reach the far X and Y ends; a station
lower by the stand-off lets the Z line run over the whole Z stroke (its X, Y
and XY lines cannot run through the launch cp there, so that station measures
only the lines that can).

Coverage of an axis is the union, over both stations, of the coordinate
ranges its lines sweep: the axis line and the diagonals that move the axis
(``post`` places compensation points wherever a line measured, see
:func:`xmalign.post.solve.compensation_points`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from trajectories.lines import LINE_IDS, LineLayout, plan_line, receiver_offset_mcs
from xmalign.errors import GeometryError
from xmalign.geometry import Vec
from xmalign.machine import AXES, Machine

#: Coverage the two stations should reach on every stroke.
TARGET_COVERAGE = 0.95
#: How much farther below the lowest receiver cp than the stand-off a low station stands, mm.
_LOW_MARGIN_MM = 10.0


@dataclass(frozen=True)
class StationProposal:
    """A launch-unit station and what its lines measure.

    Attributes
    ----------
    position_mm : ndarray, shape (3,)
        Launch cp in the MCS (mm).
    line_ids : tuple of str
        The lines that run through the launch cp from there.
    coverage : dict of str to float
        Per axis, the fraction of the stroke the lines of both stations sweep.
    """

    position_mm: Vec
    line_ids: tuple[str, ...]
    coverage: dict[str, float]

    @property
    def covers(self) -> bool:
        return min(self.coverage.values()) >= TARGET_COVERAGE


def station_lines(machine: Machine, position_mm: Vec) -> dict[str, LineLayout]:
    """The lines that run through the launch cp at ``position_mm`` (no sideways shift)."""
    layouts = {}
    for line_id in LINE_IDS:
        try:
            layout = plan_line(line_id, position_mm, machine)
        except GeometryError:
            continue
        if not np.any(layout.shift_mm):
            layouts[line_id] = layout
    return layouts


def coverage(machine: Machine, layouts: list[LineLayout]) -> dict[str, float]:
    """Per axis, the fraction of its stroke that the lines together sweep."""
    stroke = machine.travel_max_mm - machine.travel_min_mm
    result: dict[str, float] = {}
    for k, axis in enumerate(AXES):
        intervals = sorted(
            (
                float(layout.target_points_mm()[:, k].min()),
                float(layout.target_points_mm()[:, k].max()),
            )
            for layout in layouts
            if axis in layout.id
        )
        result[axis] = _union_length(intervals) / float(stroke[k])
    return result


def _union_length(intervals: list[tuple[float, float]]) -> float:
    total, end = 0.0, -np.inf
    for low, high in intervals:
        if high > end:
            total += high - max(low, end)
            end = high
    return total


def _candidates(machine: Machine, first_mm: Vec) -> list[Vec]:
    """Opposite corner first, then the other two corners; each at the first station's
    height and lower by the stand-off (so that the Z line reaches the bottom of Z)."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    offset = receiver_offset_mcs(machine)
    mirrored = low + high - first_mm
    lowest_receiver_z = low[2] + offset[2]
    measurement = machine.measurement
    low_z = lowest_receiver_z - measurement.standoff_mm - measurement.overrun_mm - _LOW_MARGIN_MM
    candidates = []
    for (mx, my), z in itertools.product(
        ((True, True), (True, False), (False, True)), (first_mm[2], min(low_z, first_mm[2]))
    ):
        x = mirrored[0] if mx else first_mm[0]
        y = mirrored[1] if my else first_mm[1]
        candidates.append(np.array([x, y, z]))
    return candidates


def propose_second_station(machine: Machine, first_position_mm: Vec) -> StationProposal:
    """The second launch-unit station whose lines, with the first's, best cover the strokes.

    Pure: tries the opposite corner and the two other corners of the travel, at
    the first station's height and lower by the stand-off, and returns the
    first candidate whose lines bring every stroke to :data:`TARGET_COVERAGE`,
    or else the one with the best worst-axis coverage.

    Parameters
    ----------
    machine : Machine
    first_position_mm : ndarray, shape (3,)
        Launch cp of the first station (mm).
    """
    first = np.asarray(first_position_mm, dtype=float)
    first_layouts = list(station_lines(machine, first).values())
    best: StationProposal | None = None
    for position in _candidates(machine, first):
        layouts = station_lines(machine, position)
        if not layouts:
            continue
        proposal = StationProposal(
            position_mm=position,
            line_ids=tuple(layouts),
            coverage=coverage(machine, first_layouts + list(layouts.values())),
        )
        if proposal.covers:
            return proposal
        if best is None or min(proposal.coverage.values()) > min(best.coverage.values()):
            best = proposal
    if best is None:
        raise GeometryError("no corner of the travel leaves room for a second launch-unit station")
    return best
