"""The D-optimal identification design: distinct positions, no steep beams, honest status."""

from __future__ import annotations

import numpy as np
import pytest

from trajectories.identification_design import (
    MAX_ELEVATION_DEG,
    IdentificationDesign,
    design_identification,
    design_violations,
    predicted_pose_covariance,
)
from trajectories.lines import receiver_offset_mcs
from xmalign.errors import GeometryError
from xmalign.machine import Machine, default_machine_path, load_machine


@pytest.fixture(scope="module")
def designs() -> dict[int, IdentificationDesign]:
    """Designs for 4, 6 and 10 alignments on the reference machine (computed once)."""
    machine = load_machine(default_machine_path())
    return {count: design_identification(machine, count) for count in (4, 6, 10)}


def _elevations_deg(machine: Machine, machine_mm: np.ndarray) -> np.ndarray:
    beams = machine_mm + receiver_offset_mcs(machine) - machine.launch_unit.position_mm
    return np.degrees(np.arctan2(np.abs(beams[:, 2]), np.hypot(beams[:, 0], beams[:, 1])))


@pytest.mark.parametrize("count", [4, 6, 10])
def test_design_has_distinct_points_and_no_steep_beams(machine, designs, count) -> None:  # noqa: ANN001
    design = designs[count]
    assert design.converged and not design.warnings
    points = design.machine_mm
    assert len(np.unique(np.round(points, 1), axis=0)) == count
    gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)[np.triu_indices(count, 1)]
    diagonal = np.linalg.norm(machine.travel_max_mm - machine.travel_min_mm)
    assert gaps.min() >= 0.1 * diagonal - 1e-3
    assert np.all(_elevations_deg(machine, points) <= MAX_ELEVATION_DEG + 1e-3)
    assert design_violations(machine, points, 1e-3) == []


def test_violations_name_repeats_and_steep_beams(machine) -> None:  # noqa: ANN001
    launch = np.array(machine.launch_unit.position_mm)
    above = launch - receiver_offset_mcs(machine) + [10.0, 0.0, 400.0]  # nearly vertical beam
    points = np.array([[2000.0, 0.0, 0.0], [2000.0, 0.0, 0.0], np.clip(above, -1e9, 0.0)])
    problems = " ".join(design_violations(machine, points))
    assert "closer than" in problems
    assert "steeper than" in problems


def test_more_alignments_predict_a_smaller_region(designs) -> None:  # noqa: ANN001
    small, large = designs[4], designs[10]
    assert np.linalg.det(large.pose_covariance) < np.linalg.det(small.pose_covariance)


def test_predicted_covariance_keeps_what_alignments_cannot_reduce(machine, designs) -> None:  # noqa: ANN001
    points = designs[10].machine_mm
    common_mm = machine.uncertainty.machine_common_um * 1e-3
    variances = np.diag(predicted_pose_covariance(machine, points))
    # a common shift of the machine moves the identified launch cp one to one
    assert np.all(variances[:3] >= common_mm**2)
    many = np.vstack([points] * 5)  # 5 times the same alignments
    variances_many = np.diag(predicted_pose_covariance(machine, many))
    assert np.all(variances_many[:3] >= common_mm**2)


def test_infeasible_design_says_why(machine) -> None:  # noqa: ANN001
    measurement = machine.measurement.model_copy(update={"standoff_mm": 5000.0})
    impossible = machine.model_copy(update={"measurement": measurement})
    with pytest.raises(GeometryError, match="no identification design.*solver:"):
        design_identification(impossible, 4)
