import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from xmalign.calibration import capture_sequence, head_frame, line_channels
from xmalign.formats.plan import PlanLine
from xmalign.geometry import direction, line_frame
from xmalign.kinematics import aligned_angles
from xmalign.roles import InterferometerReading


def _line(u, runs=2, bidirectional=True, targets=(0.0, 100.0, 200.0)):
    u = np.asarray(u, dtype=float)
    start = np.array([500.0, 400.0, -300.0])
    angles = aligned_angles([0.0, 0.0, -700.0], 0.3, start + 1000 * u, 0.0)
    return PlanLine(
        id="L",
        start_mm=start,
        end_mm=start + targets[-1] * u,
        frame=line_frame(u),
        launch_rad=angles.launch_rad,
        receiver_rad=angles.receiver_rad,
        targets_mm=np.array(targets),
        runs=runs,
        bidirectional=bidirectional,
        dwell_s=1.0,
    )


def test_capture_sequence_is_the_program_order():
    keys = [(p.run, p.direction, p.index) for p in capture_sequence(_line([1.0, 0, 0]))]
    assert keys[:6] == [
        (1, "+", 0),
        (1, "+", 1),
        (1, "+", 2),
        (1, "-", 2),
        (1, "-", 1),
        (1, "-", 0),
    ]
    assert len(keys) == 13 and keys[6] == (2, "+", 0)
    assert keys[-1] == (0, "+", 0)  # the drift check: target 1 again, after the last run
    one_way = [p.direction for p in capture_sequence(_line([1.0, 0, 0], 1, False))]
    assert one_way == ["+", "+", "+", "+"]  # with the drift check


@given(az=st.floats(-math.pi, math.pi), el=st.floats(-1.3, 1.3), spindle=st.floats(-3.0, 3.0))
def test_head_frame_is_the_beam_line_frame_for_non_vertical_beams(az, el, spindle):
    beam = direction(az, el)
    angles = aligned_angles([0.0, 0.0, 0.0], 0.0, 1000 * beam, spindle)
    line = PlanLine(
        "L",
        np.zeros(3),
        beam,
        line_frame(beam),
        angles.launch_rad,
        angles.receiver_rad,
        np.array([0.0, 1.0]),
    )
    np.testing.assert_allclose(head_frame(line, spindle), line_frame(beam), atol=1e-9)


def test_line_channels_reverse_v_with_the_line_and_subtract_the_commanded_move():
    reading = InterferometerReading(0.0, np.array([-100_010.0, 5.0, 7.0, 1.0, 2.0, 3.0]))
    flip = np.diag([-1.0, -1.0, 1.0])  # line u opposite the beam: v reverses, w stays
    channels = line_channels(reading, flip, commanded_mm=100.0)
    np.testing.assert_allclose(channels, [10.0, -5.0, 7.0, -1.0, -2.0, 3.0])


def test_line_channels_turn_a_vertical_head_frame_into_the_line_frame():
    quarter = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # 90° about u
    reading = InterferometerReading(0.0, np.array([0.0, 4.0, 0.0, 0.0, 6.0, 0.0]))
    channels = line_channels(reading, quarter, commanded_mm=0.0)
    np.testing.assert_allclose(channels, [0.0, 0.0, 4.0, 0.0, 0.0, 6.0], atol=1e-12)
