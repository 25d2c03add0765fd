"""Small error-table sets and a matching machine for the compensation tests."""

from __future__ import annotations

import numpy as np
import pytest

from xmalign.formats.error_tables import ErrorTableSet, Table
from xmalign.machine import Machine, parse_machine
from xmalign.rigid_body import MOTION_NAMES, SQUARENESS_NAMES

TRAVEL = {"X": (0.0, 400.0), "Y": (0.0, 300.0), "Z": (-200.0, 0.0)}


def make_machine(chain: str = "FYXZ", controller: str = "linuxcnc", **cnc: object) -> Machine:
    return parse_machine(
        {
            "name": "comp test machine",
            "chain": chain,
            "travel_mm": {axis: list(limits) for axis, limits in TRAVEL.items()},
            "feed_mm_min": {"rapid": 6000, "measure": 1000},
            "controller": controller,
            "receiver_offset_mm": [0, 0, -100],
            "cnc": cnc,
        },
        "test",
    )


def make_tables(
    values: dict[str, list[float]] | None = None,
    n: int | dict[str, int] = 5,
    **squareness: float,
) -> ErrorTableSet:
    """Zero tables on ``n`` points per axis over TRAVEL (an int, or per axis: {"X": 257}
    and 5 on the others); ``values`` overrides (um or urad).

    The fit's grid is the product of the axes' nodes: a long table on one axis only
    keeps it small (257 on every axis is 17 million points and 100 s)."""
    values = values or {}
    result = ErrorTableSet()
    for name in MOTION_NAMES:
        low, high = TRAVEL[name[2]]
        count = n.get(name[2], 5) if isinstance(n, dict) else n
        positions = np.linspace(low, high, count)
        scale = 1e-3 if name[1] in "XYZ" else 1e-6
        v = np.asarray(values.get(name, np.zeros(count)), dtype=float) * scale
        result.tables[name] = Table(positions, v, np.zeros(count))
    result.squareness = {s: (squareness.get(s, 0.0) * 1e-6, 0.0) for s in SQUARENESS_NAMES}
    return result


def with_reversal(tables: ErrorTableSet, name: str, half_um: float) -> ErrorTableSet:
    """Directional tables ``name+`` / ``name-`` at -half / +half around the mean."""
    mean = tables.tables[name]
    tables.tables[name + "+"] = Table(mean.positions_mm, mean.values - half_um * 1e-3, mean.u95)
    tables.tables[name + "-"] = Table(mean.positions_mm, mean.values + half_um * 1e-3, mean.u95)
    return tables


@pytest.fixture
def machine() -> Machine:
    return make_machine()
