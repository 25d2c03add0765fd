"""Capture on settled readings: the wait ends when the readings settle, never after the dwell."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.clock import SimClock
from xmalign.calibration import AVERAGE_END_FRACTION, CalibrationRun
from xmalign.roles import InterferometerReading

RATE_HZ = 50.0


class _Settling:
    """Linear channel ``amplitude * exp(-t / tau) + drift * t``, um (the machine creeping in)."""

    def __init__(self, clock: SimClock, amplitude_um: float, tau_s: float, drift_um_s: float):
        self.clock, self.amplitude, self.tau, self.drift = clock, amplitude_um, tau_s, drift_um_s

    def _linear_um(self, t_s: float) -> float:
        return self.amplitude * math.exp(-t_s / self.tau) + self.drift * t_s

    def average(self, duration_s: float) -> InterferometerReading:
        samples = []
        for _ in range(max(1, round(duration_s * RATE_HZ))):
            self.clock.sleep(1 / RATE_HZ)
            samples.append(self._linear_um(self.clock.now()))
        return InterferometerReading(self.clock.now(), np.array([np.mean(samples), 0, 0, 0, 0, 0]))


def _run(interferometer, clock) -> CalibrationRun:
    return CalibrationRun(None, None, None, interferometer, clock, lambda row: None)


def test_creep_after_the_stop_is_left_out_of_the_average():
    clock = SimClock()
    settling = _Settling(clock, amplitude_um=50.0, tau_s=0.15, drift_um_s=0.0)
    reading = _run(settling, clock)._settled_average(clock.now(), dwell_s=2.0)
    assert abs(reading.channels[0]) < 0.1
    # a fixed wait of a fifth of the dwell would have averaged in 0.4 um of creep
    fixed_clock = SimClock()
    fixed = _Settling(fixed_clock, amplitude_um=50.0, tau_s=0.15, drift_um_s=0.0)
    fixed_clock.sleep(0.4)
    assert fixed.average(1.2).channels[0] > 0.3
    assert clock.now() == pytest.approx(AVERAGE_END_FRACTION * 2.0, abs=1 / RATE_HZ)


def test_readings_that_never_settle_still_end_within_the_dwell():
    clock = SimClock()
    drifting = _Settling(clock, amplitude_um=0.0, tau_s=1.0, drift_um_s=20.0)
    _run(drifting, clock)._settled_average(clock.now(), dwell_s=0.5)
    assert clock.now() <= 0.5
