"""The virtual tracker's stream (sim.tracker_stream): its clock, the machine's motion, its noise."""

from __future__ import annotations

import numpy as np
import pytest

from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracker import VirtualTracker
from sim.tracker_stream import StreamOptions, correlated_noise, program_timeline, record_stream
from trajectories.instruments import InstrumentProgram, axis_paths, tracker_place
from xmalign.machine import default_machine_path
from xmalign.machine import load_machine as load


def test_the_noise_has_unit_variance_and_the_asked_correlation():
    noise = correlated_noise(200_000, 100.0, 0.05, np.random.default_rng(1))
    assert np.var(noise, axis=0) == pytest.approx(np.ones(3), rel=0.05)
    lag1 = np.mean(noise[1:] * noise[:-1], axis=0) / np.var(noise, axis=0)
    assert lag1 == pytest.approx(np.full(3, np.exp(-0.2)), abs=0.01)


def test_the_stream_runs_on_the_trackers_clock_through_the_programs_moves():
    reference = load(default_machine_path())
    cnc = reference.cnc.model_copy(update={"acceleration_mm_s2": 600.0})
    machine = reference.model_copy(update={"cnc": cnc})
    low, high = machine.travel_min_mm, machine.travel_max_mm
    program = InstrumentProgram(paths_mm=axis_paths(low, high, (2, 2, 2)))
    truth = VirtualMachine(machine, ErrorAmplitudes(), seed=1)
    tracker = VirtualTracker(tracker_place(machine), seed=1)
    options = StreamOptions(rate_hz=50.0, clock_offset_s=100.0, clock_rate_ppm=200.0)
    run = record_stream(machine, truth, tracker, program, options)
    step = np.diff(run.time_s)
    np.testing.assert_allclose(step, (1 + 200e-6) / 50.0, rtol=1e-9)
    timeline = program_timeline(machine, program, None)
    assert timeline.accel_mm_s2 == 600.0
    assert run.time_s[-1] - run.time_s[0] == pytest.approx(
        timeline.end_s + 2 * options.rest_s, abs=0.05
    )
    # the commanded motion never accelerates harder than the machine file says
    t = np.arange(0.0, timeline.end_s, 0.002)
    position, _ = timeline.position_mm(t)
    acceleration = np.linalg.norm(np.diff(position, 2, axis=0), axis=1) / 0.002**2
    assert acceleration.max() <= 600.0 * 1.01
    # at rest before the program: only the tracker's noise moves the SMR (< 0.1 mm)
    rest = run.tracker_mm[: int(options.rest_s * options.rate_hz) - 5]
    assert np.ptp(rest, axis=0).max() < 0.1
