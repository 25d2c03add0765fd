from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.trajectories.conftest import make_pose
from trajectories.lines import (
    LINE_IDS,
    grid_step,
    plan_line,
    receiver_offset_mcs,
    target_distances,
)
from trajectories.lines import (
    PROGRAM_RESOLUTION_MM as GRID_MM,
)
from trajectories.planner import plan_measurement
from xmalign.errors import GeometryError
from xmalign.machine import default_machine_path, load_machine


def test_reference_machine_gives_six_lines_through_the_launch_cp(machine, pose):
    measurement = plan_measurement(machine, pose)
    assert [line.id for line in measurement.plan.lines] == list(LINE_IDS)
    for planned in measurement.lines:
        layout = planned.layout
        receiver = layout.target_points_mm() + receiver_offset_mcs(machine)
        beam = receiver - pose.position_mm
        lateral = beam - np.outer(beam @ layout.u, layout.u)
        # the start is snapped to the program's grid (half a grid cell's diagonal)
        assert np.max(np.linalg.norm(lateral, axis=1)) < np.sqrt(3) / 2 * GRID_MM
        assert np.all(machine.within_travel(layout.target_points_mm()))
        distances = np.linalg.norm(beam, axis=1)
        m = machine.measurement
        assert distances.min() >= m.standoff_mm + m.overrun_mm - GRID_MM
        assert distances.max() <= machine.interferometer.max_range_mm
        step = np.linalg.norm(grid_step(layout.u))
        assert np.max(np.diff(layout.targets_mm)) <= machine.measurement.target_spacing_mm + step
        assert planned.envelope.within


def test_x_line_runs_at_the_bottom_of_z_and_covers_the_stroke_left_by_the_standoff(machine, pose):
    layout = plan_line("X", pose.position_mm, machine)
    m = machine.measurement
    np.testing.assert_allclose(layout.start_mm, [100 + m.standoff_mm + m.overrun_mm, 100, -500])
    np.testing.assert_allclose(layout.end_mm, [2000 - m.overrun_mm, 100, -500])
    np.testing.assert_allclose(layout.u, [1, 0, 0])
    assert layout.coverage == pytest.approx((2000 - 100 - m.standoff_mm - 2 * m.overrun_mm) / 2000)


def test_face_diagonal_follows_the_travel_rectangle(machine, pose):
    layout = plan_line("XY", pose.position_mm, machine)
    np.testing.assert_allclose(layout.u, np.array([2000, 1500, 0]) / 2500)


def test_irregular_targets_stay_ordered_and_cover_the_line():
    regular = target_distances(1000.0, 100.0, irregular=False)
    irregular = target_distances(1000.0, 100.0, irregular=True)
    assert len(regular) == len(irregular) == 11
    assert irregular[0] == 0.0 and irregular[-1] == 1000.0
    assert np.all(np.diff(irregular) > 0)
    assert not np.allclose(np.diff(irregular), 100.0)
    np.testing.assert_allclose(target_distances(1000.0, 100.0, irregular=True), irregular)


def test_cp_slightly_below_reach_gives_the_closest_parallel_line_and_says_so(machine):
    pose = make_pose(position_mm=(100.0, 100.0, -680.03))
    measurement = plan_measurement(machine, pose)
    x_line = measurement.plan.line("X")
    assert x_line.start_mm[2] == pytest.approx(-500.0)
    assert "below the lowest receiver cp" in x_line.extra["note"]
    assert x_line.extra["shift_mm"][2] == pytest.approx(0.03)
    assert np.max(measurement.lines[0].envelope.lateral_nominal_um) > 0


def test_cp_far_below_the_lowest_receiver_position_is_refused_with_the_fix(machine):
    with pytest.raises(GeometryError, match=r"line X .*20\.0 mm below.*raise the launch unit"):
        plan_measurement(machine, make_pose(position_mm=(100.0, 100.0, -700.0)))


def test_too_short_line_is_refused(machine, pose):
    data = machine.model_dump()
    data["measurement"]["standoff_mm"] = 450.0
    short = type(machine).model_validate(data)
    with pytest.raises(GeometryError, match=r"line Z: only .* usable.*Fix"):
        plan_line("Z", pose.position_mm, short)


_MACHINE = load_machine(default_machine_path())


@settings(max_examples=40, deadline=None)
@given(
    x=st.floats(0, 2000),
    y=st.floats(0, 1500),
    z=st.floats(-680, -180),
    line_id=st.sampled_from(LINE_IDS),
)
def test_any_reachable_launch_position_gives_lines_inside_travel_and_range(x, y, z, line_id):
    try:
        layout = plan_line(line_id, np.array([x, y, z]), _MACHINE)
    except GeometryError:
        return
    m = _MACHINE.measurement
    points = layout.target_points_mm()
    ends = np.vstack([points[0] - m.overrun_mm * layout.u, points[-1] + m.overrun_mm * layout.u])
    assert np.all(_MACHINE.within_travel(np.vstack([points, ends])))
    assert layout.length_mm >= m.min_line_mm
    near, far = layout.beam_distance_mm
    assert near >= m.standoff_mm and far <= _MACHINE.interferometer.max_range_mm + 1e-9


@pytest.mark.parametrize("irregular", [False, True])
def test_targets_lie_on_the_programs_grid(machine, pose, irregular):
    """Plan, G-code and measurement file name the same coordinates (1 um grid)."""
    measurement = machine.measurement.model_copy(update={"irregular_spacing": irregular})
    planned = plan_measurement(machine.model_copy(update={"measurement": measurement}), pose)
    for line in planned.plan.lines:
        points_um = line.target_points_mm() / GRID_MM
        np.testing.assert_allclose(points_um, np.round(points_um), atol=1e-6)


@given(st.floats(0.05, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))
def test_a_grid_step_is_on_the_grid_and_along_the_direction(a, b, c):
    u = np.array([a, b, c]) / np.linalg.norm([a, b, c])
    step_um = grid_step(u) / GRID_MM
    np.testing.assert_allclose(step_um, np.round(step_um), atol=1e-9)
    assert np.linalg.norm(step_um / np.linalg.norm(step_um) - u) < 1e-4
