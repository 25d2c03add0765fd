import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim import motion


@given(
    st.floats(-3, 3),
    st.floats(-3, 3),
    st.floats(0.05, 2),
    st.floats(0.1, 5),
)
def test_move_reaches_target_within_limits(start, target, v_max, accel):
    profile = motion.move(motion.rest(start, 0.0), 0.0, target, v_max, accel)
    times = np.linspace(0.0, profile.end_s + 1.0, 400)
    states = np.array([profile.state(t) for t in times])
    assert profile.state(profile.end_s + 1.0) == pytest.approx((target, 0.0), abs=1e-9)
    assert np.all(np.abs(states[:, 1]) <= v_max + 1e-9)
    assert np.all(np.abs(np.diff(states[:, 1])) <= accel * np.diff(times).max() + 1e-9)
    assert not profile.is_moving(profile.end_s)


def test_move_while_moving_brakes_first_then_goes():
    first = motion.move(motion.rest(0.0, 0.0), 0.0, 10.0, 1.0, 1.0)
    second = motion.move(first, 2.0, 0.0, 1.0, 1.0)
    position, velocity = second.state(2.0)
    assert position == pytest.approx(first.state(2.0)[0])
    assert velocity == pytest.approx(1.0)
    assert second.state(1e3) == pytest.approx((0.0, 0.0))


def test_stop_and_cruise():
    running = motion.cruise(motion.rest(0.0, 0.0), 0.0, 2.0, 4.0)
    assert running.is_moving(100.0)
    assert running.state(10.0) == pytest.approx((0.5 * 2.0 * 0.5 + 2.0 * 9.5, 2.0))
    stopped = motion.stop(running, 10.0, 4.0)
    assert stopped.end_s == pytest.approx(10.5)
    assert stopped.state(20.0)[1] == 0.0
