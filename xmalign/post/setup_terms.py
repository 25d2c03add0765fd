"""What the setup puts into the channels, as nuisance parameters of the fit.

Per line (docs/conventions.md, "Raw readings carry the setup"):

- straightness v and w: an offset and a slope along the line (the beam is not
  parallel to the line: the alignment slope);
- angles u, v, w: a constant each (mounting of the receiver and launch head);
- linear: a constant per run (dead path, and the run's own zero).

A line whose units were aligned again on a resume (rows of another setup
``segment``, docs/measurement-files.md) has these terms once per segment; a
segment with a single target distance has no slope (one point gives none).

Each term is a column of the design matrix; its estimate is reported, not
subtracted beforehand, so that it is fitted together with the error tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from xmalign.geometry import Vec
from xmalign.post.lines import LineData

N_CHANNELS = 6
_LINEAR, _STRAIGHT_V, _STRAIGHT_W = 0, 1, 2
#: Slopes are fitted per metre of travel, which keeps the columns well scaled.
_MM_PER_M = 1000.0


@dataclass
class SetupTerms:
    """The setup terms of one line, in file units.

    Attributes
    ----------
    line_id : str
    segment : int
        The setup segment of the line these terms belong to.
    straightness_offset_um : ndarray, shape (2,)
        Offset of straightness v and w at the line start.
    straightness_slope_urad : ndarray, shape (2,)
        Beam misalignment: slope of straightness v and w along the line.
    angle_offset_urad : ndarray, shape (3,)
        Constants of angle u, v, w.
    linear_offset_um : dict of int to float
        Constant of the linear channel, per run.
    """

    line_id: str
    straightness_offset_um: Vec
    straightness_slope_urad: Vec
    angle_offset_urad: Vec
    linear_offset_um: dict[int, float] = field(default_factory=dict)
    segment: int = 0


@dataclass
class Triplets:
    """Sparse matrix entries being collected (rows, columns, values)."""

    rows: list[np.ndarray] = field(default_factory=list)
    cols: list[np.ndarray] = field(default_factory=list)
    vals: list[np.ndarray] = field(default_factory=list)

    def add(self, rows: np.ndarray, cols: np.ndarray | int, vals: np.ndarray | float) -> None:
        rows = np.asarray(rows)
        self.rows.append(rows)
        self.cols.append(np.broadcast_to(cols, rows.shape).copy())
        self.vals.append(np.broadcast_to(np.asarray(vals, dtype=float), rows.shape).copy())

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.concatenate(self.rows), np.concatenate(self.cols), np.concatenate(self.vals)


@dataclass
class _SegmentLayout:
    line_id: str
    segment: int
    first_column: int
    runs: list[int]
    has_slope: bool

    @property
    def n_columns(self) -> int:
        return (7 if self.has_slope else 5) + len(self.runs)


class SetupLayout:
    """Columns of the setup terms of every line and segment, from ``first_column`` on.

    Column order per line segment: straightness offsets (v, w), slopes (v, w;
    only with two or more target distances), angle offsets (u, v, w), then one
    linear offset per run.
    """

    def __init__(self, lines: list[LineData], first_column: int) -> None:
        self._layouts: list[list[_SegmentLayout]] = []
        column = first_column
        for data in lines:
            segments = []
            for segment in sorted({int(s) for s in data.segment}):
                mine = data.segment == segment
                runs = sorted({int(r) for r in data.run[mine]})
                has_slope = len(np.unique(data.distance_mm[mine])) > 1
                layout = _SegmentLayout(data.label, segment, column, runs, has_slope)
                segments.append(layout)
                column += layout.n_columns
            self._layouts.append(segments)
        self.first_column = first_column
        self.n_columns = column - first_column

    def add_columns(self, lines: list[LineData], first_rows: list[int], out: Triplets) -> None:
        """Add the setup columns of each line (its rows start at ``first_rows[i]``)."""
        for data, segments, first_row in zip(lines, self._layouts, first_rows, strict=True):
            all_rows = first_row + N_CHANNELS * np.arange(len(data.run))
            for layout in segments:
                mine = data.segment == layout.segment
                point_rows = all_rows[mine]
                c = layout.first_column
                for k in (0, 1):
                    out.add(point_rows + _STRAIGHT_V + k, c + k, 1.0)
                if layout.has_slope:
                    for k in (0, 1):
                        slope = data.distance_mm[mine] / _MM_PER_M
                        out.add(point_rows + _STRAIGHT_V + k, c + 2 + k, slope)
                    c += 2
                for k in range(3):
                    out.add(point_rows + 3 + k, c + 2 + k, 1.0)
                for i, run in enumerate(layout.runs):
                    out.add(point_rows[data.run[mine] == run] + _LINEAR, c + 5 + i, 1.0)

    def line_of(self, column: int) -> str | None:
        """The line whose setup term a column is; None if not a setup column."""
        for layout in (layout for segments in self._layouts for layout in segments):
            if 0 <= column - layout.first_column < layout.n_columns:
                return layout.line_id
        return None

    def unpack(self, x: Vec) -> list[SetupTerms]:
        """The fitted setup terms from the solution vector (mm, rad, mm/m) in file units."""
        terms = []
        for layout in (layout for segments in self._layouts for layout in segments):
            p = x[layout.first_column : layout.first_column + layout.n_columns]
            slope = p[2:4] if layout.has_slope else np.zeros(2)
            rest = p[4:] if layout.has_slope else p[2:]
            terms.append(
                SetupTerms(
                    line_id=layout.line_id,
                    straightness_offset_um=p[0:2] * 1e3,
                    straightness_slope_urad=slope * 1e3,
                    angle_offset_urad=rest[0:3] * 1e6,
                    linear_offset_um={
                        run: float(v) * 1e3 for run, v in zip(layout.runs, rest[3:], strict=True)
                    },
                    segment=layout.segment,
                )
            )
        return terms
