"""The measurement rows of one plan line, as arrays, checked against the plan."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from xmalign.errors import InputError
from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec, rot_z
from xmalign.rigid_body import AXES

UM_PER_MM = 1e3
URAD_PER_RAD = 1e6
#: Scale of each channel from file units (um, urad) to mm and rad.
CHANNEL_TO_SI = np.array([1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6])
#: A commanded point farther than this from its plan target is refused.
POINT_TOLERANCE_MM = 0.01
_PARALLEL = 1.0 - 1e-9


@dataclass
class LineData:
    """Every captured point of one line.

    Attributes
    ----------
    line : PlanLine
    run : ndarray of int, shape (N,)
    sign : ndarray of float, shape (N,)
        +1 for the ``+`` pass, -1 for the ``-`` pass.
    index : ndarray of int, shape (N,)
        Target index in the plan.
    distance_mm : ndarray, shape (N,)
        Target distance from the line start along u.
    machine_mm : ndarray, shape (N, 3)
        Commanded CNC tool point.
    channels : ndarray, shape (N, 6)
        Channels in mm and rad (linear, straightness v, w, angle u, v, w).
    segment : ndarray of int, shape (N,)
        Setup segment of each point (0 unless the units were re-aligned on a resume).
    tool_offset_mm : ndarray, shape (3,)
        Receiver cp from the CNC tool point in the MCS during the measurement.
    station : int
        Launch-unit station the line was measured from (0 for the first).
    """

    line: PlanLine
    run: np.ndarray
    sign: Vec
    index: np.ndarray
    distance_mm: Vec
    machine_mm: Vec
    channels: Vec
    segment: np.ndarray
    tool_offset_mm: Vec
    station: int = 0

    @property
    def label(self) -> str:
        """The line id, with its station from the second station on (``X``, ``X@2``)."""
        return self.line.id if self.station == 0 else f"{self.line.id}@{self.station + 1}"

    @property
    def frame(self) -> Vec:
        """Rows u, v, w of the line frame, shape (3, 3)."""
        return self.line.frame

    @property
    def bidirectional(self) -> bool:
        return bool(np.any(self.sign > 0) and np.any(self.sign < 0))

    def axis(self) -> str | None:
        """The axis the line is parallel to, or None for a diagonal."""
        u = self.frame[0]
        for i, name in enumerate(AXES):
            if abs(u[i]) >= _PARALLEL:
                return name
        return None

    def moving_axes(self) -> list[str]:
        """Axes whose coordinate changes along the line."""
        return [name for i, name in enumerate(AXES) if abs(self.frame[0][i]) > 1e-9]

    def without(self, points: Sequence[int]) -> LineData:
        """The line without the points numbered ``points`` (0-based, in row order)."""
        kept = np.ones(len(self.run), dtype=bool)
        kept[list(points)] = False
        return replace(
            self,
            run=self.run[kept],
            sign=self.sign[kept],
            index=self.index[kept],
            distance_mm=self.distance_mm[kept],
            machine_mm=self.machine_mm[kept],
            channels=self.channels[kept],
            segment=self.segment[kept],
        )


def tool_offset_mm(plan: Plan) -> Vec:
    """Receiver cp from the CNC tool point in the MCS during the measurement, mm (3,)."""
    return rot_z(plan.spindle_angle_rad) @ plan.receiver_offset_mm


def _at(source: str, row: MeasurementRow) -> str:
    """The file and, for a row read from it, its line: where a row's problem is."""
    return f"{source}: line {row.file_line}" if row.file_line else source


def is_dead_row(row: MeasurementRow) -> bool:
    """All six channels exactly zero: no instrument reads that (its noise alone moves the
    last digit); the beam was lost or the software wrote a row it had no reading for."""
    return not np.any(row.channels)


def dead_row_warning(source: str, row: MeasurementRow) -> str:
    """The warning naming a dead row (:func:`is_dead_row`), left out of the fit."""
    return (
        f"{_at(source, row)}: line {row.line} run {row.run} direction {row.direction} index"
        f" {row.index}: all six channels read exactly 0 (a dead row: a lost beam or a"
        " reading the instrument did not take): left out of the fit and the figures"
    )


def _line_data(
    plan: Plan, line: PlanLine, rows: list[MeasurementRow], source: str, station: int
) -> LineData:
    index = np.array([row.index for row in rows])
    if np.any((index < 0) | (index >= len(line.targets_mm))):
        bad = rows[int(np.argmax((index < 0) | (index >= len(line.targets_mm))))]
        raise InputError(
            f"{_at(source, bad)}: line {line.id} run {bad.run}: target index {bad.index} is not"
            f" in the plan ({len(line.targets_mm)} targets)"
        )
    runs = np.array([row.run for row in rows])
    if np.any((runs < 0) | (runs > line.runs)):
        bad = rows[int(np.argmax((runs < 0) | (runs > line.runs)))]
        raise InputError(
            f"{_at(source, bad)}: line {line.id} run {bad.run} index {bad.index}: the plan has runs"
            f" 1..{line.runs} of this line (run 0 is its drift check)"
        )
    machine = np.array([row.machine_mm for row in rows])
    expected = line.target_points_mm()[index]
    off = np.linalg.norm(machine - expected, axis=1)
    if np.any(off > POINT_TOLERANCE_MM):
        bad = rows[int(np.argmax(off))]
        raise InputError(
            f"{_at(source, bad)}: line {line.id} run {bad.run} index {bad.index}: commanded point"
            f" {np.round(bad.machine_mm, 3).tolist()} is {off.max():.3f} mm off the plan target"
        )
    return LineData(
        line=line,
        run=runs,
        sign=np.array([1.0 if row.direction == "+" else -1.0 for row in rows]),
        index=index,
        distance_mm=line.targets_mm[index],
        machine_mm=machine,
        channels=np.array([row.channels for row in rows]) * CHANNEL_TO_SI,
        segment=np.array([row.segment for row in rows]),
        tool_offset_mm=tool_offset_mm(plan),
        station=station,
    )


def group_by_line(
    plan: Plan, rows: list[MeasurementRow], source: str, station: int = 0
) -> list[LineData]:
    """The rows of every plan line that has data, in plan order (``station`` 0-based).

    Raises
    ------
    InputError
        A row names a line the plan does not have, a run or a target index outside
        the plan, or a commanded point off its plan target; or no row at all.
    """
    known = {line.id for line in plan.lines}
    by_line: dict[str, list[MeasurementRow]] = {line.id: [] for line in plan.lines}
    for row in rows:
        if row.line not in known:
            raise InputError(
                f"{_at(source, row)}: line '{row.line}' (run {row.run}, index {row.index}) is not"
                f" in the plan (lines {', '.join(sorted(known))})"
            )
        by_line[row.line].append(row)
    if not rows:
        raise InputError(f"{source}: no measurement rows")
    return [
        _line_data(plan, line, by_line[line.id], source, station)
        for line in plan.lines
        if by_line[line.id]
    ]
