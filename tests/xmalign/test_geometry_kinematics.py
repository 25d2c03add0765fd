import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from xmalign.errors import GeometryError
from xmalign.geometry import direction, line_frame, rot_y, rot_z, skew, unit, wrap_angle
from xmalign.kinematics import (
    EncoderOffsets,
    aligned_angles,
    launch_angles,
    launch_direction,
    receiver_angles,
    receiver_axis,
    receiver_cp,
)

angles = st.floats(-math.pi + 1e-6, math.pi - 1e-6)
elevations = st.floats(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3)


def test_launch_direction_matches_the_matrix_form_of_the_spec():
    gamma, phi1, phi2 = 0.3, -1.1, 0.4
    expected = rot_z(gamma + phi1) @ rot_y(-phi2) @ np.array([1.0, 0, 0])
    np.testing.assert_allclose(launch_direction(gamma, phi1, phi2), expected, atol=1e-15)
    assert launch_direction(0.0, 0.0, 0.5)[2] > 0  # positive elevation looks up


@given(gamma=angles, phi1=angles, phi2=elevations)
def test_launch_angles_invert_the_direction(gamma, phi1, phi2):
    d = launch_direction(gamma, phi1, phi2)
    back1, back2 = launch_angles(d, gamma)
    np.testing.assert_allclose(launch_direction(gamma, back1, back2), d, atol=1e-12)
    assert abs(back2 - phi2) < 1e-9
    assert abs(wrap_angle(back1 - phi1)) < 1e-9


@given(gamma_r=angles, phi3=angles, phi4=elevations)
def test_receiver_angles_invert_the_axis(gamma_r, phi3, phi4):
    u = receiver_axis(gamma_r, phi3, phi4)
    back3, back4 = receiver_angles(u, gamma_r)
    np.testing.assert_allclose(receiver_axis(gamma_r, back3, back4), u, atol=1e-12)


@given(
    launch=st.lists(st.floats(-1000, 1000), min_size=3, max_size=3),
    target=st.lists(st.floats(-1000, 1000), min_size=3, max_size=3),
    gamma=angles,
    spindle=angles,
)
def test_aligned_angles_point_the_units_at_each_other(launch, target, gamma, spindle):
    launch, target = np.array(launch), np.array(target)
    if np.linalg.norm(target - launch) < 1.0:
        return
    offsets = EncoderOffsets(c2=1e-4, c3=-2e-4, c4=5e-5)
    aligned = aligned_angles(launch, gamma, target, spindle, offsets)
    true_l = aligned.launch_rad + [0.0, offsets.c2]
    true_r = aligned.receiver_rad[:2] + [offsets.c3, offsets.c4]
    d = launch_direction(gamma, *true_l)
    u = receiver_axis(spindle, *true_r)
    beam = unit(target - launch)
    np.testing.assert_allclose(d, beam, atol=1e-9)
    np.testing.assert_allclose(u, -beam, atol=1e-9)
    assert aligned.distance_mm == pytest.approx(np.linalg.norm(target - launch))


def test_receiver_cp_turns_the_offset_with_the_spindle():
    cp = receiver_cp([10.0, 20.0, 30.0], [5.0, 0.0, -180.0], math.pi / 2)
    np.testing.assert_allclose(cp, [10.0, 25.0, -150.0], atol=1e-12)


@given(az=angles, el=elevations)
def test_line_frame_is_right_handed_with_w_towards_plus_z(az, el):
    frame = line_frame(direction(az, el))
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.cross(frame[0], frame[1]), frame[2], atol=1e-12)
    assert frame[2][2] >= 0


def test_line_frame_of_a_vertical_line():
    frame = line_frame([0.0, 0.0, -1.0])
    np.testing.assert_allclose(frame[1], [1.0, 0, 0])
    np.testing.assert_allclose(frame[2], np.cross(frame[0], frame[1]))
    horizontal = line_frame([1.0, 0, 0])
    np.testing.assert_allclose(horizontal[2], [0, 0, 1.0])
    np.testing.assert_allclose(horizontal[1], [0, 1.0, 0])


def test_skew_and_unit():
    a, b = np.array([1.0, 2, 3]), np.array([-2.0, 0.5, 4])
    np.testing.assert_allclose(skew(a) @ b, np.cross(a, b))
    with pytest.raises(GeometryError):
        unit([0.0, 0.0, 0.0])
