"""The simulator's clock: virtual time, then the wall clock from where it stood."""

import time

from sim.clock import SimClock


def test_a_virtual_clock_goes_on_in_real_time_from_where_it_stood():
    clock = SimClock()
    clock.sleep(100.0)  # virtual: returns at once
    assert clock.now() == 100.0
    clock.follow_wall_clock()
    started = time.monotonic()
    clock.sleep(0.05)  # real: sleeps
    assert time.monotonic() - started >= 0.05
    assert 100.05 <= clock.now() < 101.0
