"""The second launch-unit station brings every stroke to 95 % coverage."""

from __future__ import annotations

import numpy as np
import pytest

from trajectories.lines import LINE_IDS
from trajectories.stations import (
    TARGET_COVERAGE,
    coverage,
    propose_second_station,
    station_lines,
)


def test_one_station_leaves_the_strokes_short(machine):
    first = np.asarray(machine.launch_unit.position_mm, dtype=float)
    layouts = station_lines(machine, first)
    assert tuple(layouts) == LINE_IDS
    assert min(coverage(machine, list(layouts.values())).values()) < 0.9


def test_the_proposed_second_station_covers_every_stroke(machine):
    first = np.asarray(machine.launch_unit.position_mm, dtype=float)
    proposal = propose_second_station(machine, first)
    assert proposal.covers
    assert all(value >= TARGET_COVERAGE for value in proposal.coverage.values())
    # the opposite corner of the travel, lower by the stand-off so that Z reaches down
    centre = 0.5 * (machine.travel_min_mm + machine.travel_max_mm)
    assert np.all(
        np.sign(proposal.position_mm[:2] - centre[:2]) == -np.sign(first[:2] - centre[:2])
    )
    assert proposal.position_mm[2] < first[2] - machine.measurement.standoff_mm
    assert "Z" in proposal.line_ids


def test_coverage_counts_overlapping_lines_once(machine):
    first = np.asarray(machine.launch_unit.position_mm, dtype=float)
    layouts = list(station_lines(machine, first).values())
    assert coverage(machine, layouts + layouts) == pytest.approx(coverage(machine, layouts))
