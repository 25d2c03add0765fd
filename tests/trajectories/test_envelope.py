from __future__ import annotations

import numpy as np
import pytest

from tests.trajectories.conftest import make_pose
from trajectories.envelope import K95, predict_envelope
from trajectories.lines import receiver_offset_mcs
from trajectories.planner import parameter_covariance, plan_one_line
from xmalign.kinematics import launch_direction


def test_exact_pose_without_uncertainty_has_a_zero_envelope(machine):
    pose = make_pose(sigma_mm=0.0, sigma_gamma_rad=0.0)
    planned = plan_one_line("XZ", pose, machine)
    frame = planned.line.frame
    envelope = predict_envelope(
        np.concatenate([pose.position_mm, [pose.gamma_rad], pose.offsets.as_array()]),
        np.zeros((7, 7)),
        planned.layout.target_points_mm() + receiver_offset_mcs(machine),
        planned.line.launch_rad,
        planned.line.receiver_rad,
        machine.spindle_angle_rad,
        frame,
        200.0,
        400.0,
    )
    assert np.max(envelope.lateral_95_um) < 1e-6
    assert envelope.angle_95_urad < 1e-6


def test_envelope_matches_monte_carlo_at_the_far_target(machine, pose):
    planned = plan_one_line("X", pose, machine)
    covariance = parameter_covariance(pose, machine)
    rng = np.random.default_rng(7)
    q0 = np.concatenate([pose.position_mm, [pose.gamma_rad], pose.offsets.as_array()])
    samples = rng.multivariate_normal(q0, covariance, size=20000)
    far = planned.layout.target_points_mm()[-1] + receiver_offset_mcs(machine)
    launch = planned.line.launch_rad
    d = launch_direction(samples[:, 3], launch[0], launch[1] + samples[:, 4])
    relative = far - samples[:, :3]
    lateral = relative - (np.sum(relative * d, axis=1))[:, None] * d
    radius_um = 1e3 * np.linalg.norm(lateral, axis=1)
    # The envelope bounds the radius by the largest axis of the 95 % ellipse, so it
    # lies between the Monte Carlo 95 % quantile and K95 times its largest sigma.
    predicted = planned.envelope.lateral_95_um[-1]
    assert np.quantile(radius_um, 0.95) <= predicted * 1.02
    assert predicted <= K95 * np.sqrt(2.0) * np.std(radius_um) * 3.0
    assert np.mean(radius_um <= predicted) == pytest.approx(0.97, abs=0.03)


def test_unestimated_offsets_widen_the_envelope_and_warn(machine):
    estimated = plan_one_line("XY", make_pose(), machine)
    unknown = plan_one_line("XY", make_pose(offsets_deg={}), machine)
    assert unknown.envelope.straightness_margin_um < estimated.envelope.straightness_margin_um
    assert unknown.warning is not None and "margin" in unknown.warning
    assert estimated.warning is None
