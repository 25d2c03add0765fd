"""One contract, every implementation of ``Interferometer``: the serial driver (over a pty to the
simulated instrument), the replay of a recorded stream, and the simulated instrument itself.

All three look at the same aligned virtual setup and must answer the same assertions.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from firmware_iface.interferometer import (
    RecordingInterferometer,
    ReplayInterferometer,
    SerialInterferometer,
    open_serial,
)
from sim import motion
from sim.clock import SimClock
from sim.interferometer import SimInterferometer
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.servers.serial_pty import PtyInterferometerServer
from sim.units import SimUnit
from tests.sim.conftest import StandingCnc
from xmalign.kinematics import aligned_angles, receiver_cp
from xmalign.machine import Machine
from xmalign.roles import Interferometer

LAUNCH_MM = np.array([100.0, 100.0, -680.0])
GAMMA_RAD = 0.3
RATE_HZ = 100.0


def aligned_instrument(machine: Machine, clock: SimClock) -> SimInterferometer:
    """The simulated instrument with both units standing aligned on the beam."""
    vm = VirtualMachine(machine, ErrorAmplitudes(scale=0.0, repeatability_um=0.0))
    launch, receiver = SimUnit("launch", clock), SimUnit("receiver", clock)
    cnc = StandingCnc((1000.0, 100.0, -100.0))
    cp = receiver_cp(cnc.position, machine.receiver_offset, machine.spindle_angle_rad)
    aligned = aligned_angles(LAUNCH_MM, GAMMA_RAD, cp, machine.spindle_angle_rad)
    for unit, angles in ((launch, aligned.launch_rad), (receiver, aligned.receiver_rad)):
        for axis, angle in zip(unit.axes, angles, strict=True):
            axis.profile = motion.rest(float(angle), clock.now())
    return SimInterferometer(
        launch, receiver, vm, cnc, LAUNCH_MM, GAMMA_RAD, rate_hz=RATE_HZ, seed=3
    )


def serial(machine: Machine, tmp_path: Path) -> Iterator[Interferometer]:
    server = PtyInterferometerServer(aligned_instrument(machine, SimClock(real_time=True)), RATE_HZ)
    server.start()
    connection = open_serial(server.port, timeout_s=2.0)
    yield SerialInterferometer(connection, f"interferometer on {server.port}")
    connection.close()
    server.stop()


def replay(machine: Machine, tmp_path: Path) -> Iterator[Interferometer]:
    clock = SimClock()
    recorder = RecordingInterferometer(aligned_instrument(machine, clock), tmp_path / "xm.csv")
    for _ in range(200):
        recorder.read()
        clock.sleep(1.0 / RATE_HZ)
    recorder.close()
    yield ReplayInterferometer(tmp_path / "xm.csv")


def simulated(machine: Machine, tmp_path: Path) -> Iterator[Interferometer]:
    yield aligned_instrument(machine, SimClock())


@pytest.fixture(params=[serial, replay, simulated])
def instrument(request, reference_machine, tmp_path) -> Iterator[Interferometer]:
    yield from request.param(reference_machine, tmp_path)


def test_reads_six_channels_in_time_order(instrument: Interferometer) -> None:
    assert isinstance(instrument, Interferometer)
    first, second = instrument.read(), instrument.read()
    assert first.channels.shape == second.channels.shape == (6,)
    assert first.beam_ok and second.beam_ok
    assert second.time_s >= first.time_s
    np.testing.assert_allclose(first.channels[1:], 0.0, atol=5.0)  # aligned: noise only


def test_zero_sets_the_linear_datum(instrument: Interferometer) -> None:
    instrument.zero()
    assert abs(instrument.read().channel("linear_um")) < 1.0


def test_average_spans_the_duration_and_beats_the_noise(instrument: Interferometer) -> None:
    instrument.zero()
    before = instrument.read()
    mean = instrument.average(0.2)
    assert mean.beam_ok and mean.channels.shape == (6,)
    assert mean.time_s - before.time_s >= 0.2 - 1.5 / RATE_HZ
    np.testing.assert_allclose(mean.channels, 0.0, atol=1.0)
