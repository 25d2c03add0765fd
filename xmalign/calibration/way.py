"""Where xmalign's program moves the machine between its stops, and a stop off that way."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from xmalign.errors import DeviceError
from xmalign.formats.plan import PlanLine
from xmalign.geometry import Vec


@dataclass(frozen=True)
class ProgramWay:
    """Where the program ``xmalign program`` writes moves the machine between its stops.

    Within a line, on the line's axis between the pre-position (``overrun_mm``
    before the first target) and the overrun past the last one. From a line's
    last stop (or wherever the program starts) to the next line's pre-position:
    up to ``safe_z_mm`` (the top of the Z travel), across at that height (a
    rapid, straight or not: anywhere between the two ends in X and Y), down.
    A program stopped (paused, the machine at rest) on this way is held there
    (a feed hold); anywhere else it is not the plan's program.
    """

    overrun_mm: float
    safe_z_mm: float

    def pre_position_mm(self, line: PlanLine) -> Vec:
        return pre_position_mm(line, self.overrun_mm)

    def on_line(self, line: PlanLine) -> Callable[[Vec], float]:
        """Distance from the line's part of the program, mm."""
        points = line.target_points_mm()
        start = self.pre_position_mm(line)
        end = points[-1] + self.overrun_mm * line.frame[0]
        return partial(_off_segment_mm, start=start, end=end)

    def to_line(
        self, from_mm: Vec, passed: Sequence[PlanLine], line: PlanLine
    ) -> Callable[[Vec], float]:
        """Distance from the program's way from a stop at ``from_mm`` to ``line``'s
        pre-position, through the lines ``passed`` (recorded: the program still runs them)."""
        pieces = []
        for done in passed:
            pieces += [self._transit(from_mm, self.pre_position_mm(done)), self.on_line(done)]
            from_mm = done.target_points_mm()[0]  # its drift check
        pieces.append(self._transit(from_mm, self.pre_position_mm(line)))
        return lambda position_mm: min(piece(position_mm) for piece in pieces)

    def _transit(self, from_mm: Vec, to_mm: Vec) -> Callable[[Vec], float]:
        up, down = _with_z(from_mm, self.safe_z_mm), _with_z(to_mm, self.safe_z_mm)

        def off_mm(position_mm: Vec) -> float:
            low, high = np.minimum(up, down), np.maximum(up, down)
            across = float(np.linalg.norm(position_mm - np.clip(position_mm, low, high)))
            return min(
                _off_segment_mm(position_mm, from_mm, up),
                across,
                _off_segment_mm(position_mm, down, to_mm),
            )

        return off_mm


def _with_z(point_mm: Vec, z_mm: float) -> Vec:
    return np.array([point_mm[0], point_mm[1], z_mm])


def _off_segment_mm(position_mm: Vec, start: Vec, end: Vec) -> float:
    """Distance of a point from the segment ``start`` to ``end``, mm."""
    step = end - start
    length2 = float(step @ step)
    along = 0.0 if length2 == 0.0 else float(np.clip((position_mm - start) @ step / length2, 0, 1))
    return float(np.linalg.norm(position_mm - (start + along * step)))


def check_stop_on_way(
    position_mm: Vec, target_mm: Vec, way: Callable[[Vec], float], tolerance_mm: float, what: str
) -> None:
    """Refuse a program stopped with the machine at rest off its way to ``target_mm`` (its
    next stop, ``what``): a program that is not the plan's. On the way it is held there."""
    if way(position_mm) <= tolerance_mm:
        return
    miss = float(np.linalg.norm(position_mm - target_mm))
    raise DeviceError(
        f"the program stopped with the machine at {np.round(position_mm, 4).tolist()} mm,"
        f" {miss:.4f} mm from {what} (tolerance {tolerance_mm} mm): program and plan do not"
        " match"
    )


def pre_position_mm(line: PlanLine, overrun_mm: float) -> Vec:
    """Where the program stops before a line: its first target less the overrun, mm (3,)."""
    return line.target_points_mm()[0] - overrun_mm * line.frame[0]
