"""Where the error tables were measured and where they are extrapolated (for reports)."""

from __future__ import annotations

from xmalign.formats.error_tables import ErrorTableSet, Table
from xmalign.rigid_body import AXES, TRANSLATION_NAMES

RANGES_HEADER = ["axis", "measured / mm", "extrapolated / mm"]


def measured_range_mm(table: Table) -> tuple[float, float]:
    """First and last measured position of a table, mm."""
    positions = table.positions_mm[table.measured_mask()]
    return float(positions[0]), float(positions[-1])


def extrapolated_spans_mm(table: Table) -> list[tuple[float, float]]:
    """The stretches (from, to) in mm beyond the measured range, below and above it."""
    low, high = measured_range_mm(table)
    spans = ((float(table.positions_mm[0]), low), (high, float(table.positions_mm[-1])))
    return [(a, b) for a, b in spans if b > a]


def range_rows(tables: ErrorTableSet) -> list[list[str]]:
    """Per axis (from its positioning table): measured range and extrapolated stretches."""
    rows = []
    for k, axis in enumerate(AXES):
        table = tables.tables.get(TRANSLATION_NAMES[axis][k])
        if table is None:
            continue
        low, high = measured_range_mm(table)
        spans = ", ".join(f"{a:g} to {b:g}" for a, b in extrapolated_spans_mm(table))
        rows.append([axis, f"{low:g} to {high:g}", spans or "none"])
    return rows
