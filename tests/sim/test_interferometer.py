import numpy as np
import pytest

from sim.clock import SimClock
from sim.interferometer import InterferometerNoise, SimInterferometer
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.units import SimPositioningUnit, SimUnit
from tests.sim.conftest import StandingCnc
from xmalign.geometry import line_frame, rot_z
from xmalign.kinematics import aligned_angles, receiver_cp
from xmalign.roles import Interferometer

SILENT = InterferometerNoise(0.0, 0.0, 0.0, 0.0)
LAUNCH_MM = np.array([100.0, 100.0, -680.0])
GAMMA = 0.3


def setup(machine, amplitudes=None, noise=SILENT, cnc_mm=(1000.0, 100.0, -100.0)):
    clock = SimClock()
    vm = VirtualMachine(machine, amplitudes or ErrorAmplitudes(scale=0.0, repeatability_um=0.0))
    launch, receiver = SimUnit("launch", clock), SimUnit("receiver", clock)
    cnc = StandingCnc(cnc_mm)
    xm = SimInterferometer(launch, receiver, vm, cnc, LAUNCH_MM, GAMMA, noise=noise, seed=1)
    cp = receiver_cp(cnc.position, machine.receiver_offset, machine.spindle_angle_rad)
    aligned = aligned_angles(LAUNCH_MM, GAMMA, cp, machine.spindle_angle_rad)
    SimPositioningUnit(launch).move_to(aligned.launch_rad, 60.0)
    SimPositioningUnit(receiver).move_to(aligned.receiver_rad, 60.0)
    return xm, cnc, aligned


def test_aligned_units_read_zero_and_linear_follows_the_beam(machine):
    xm, cnc, aligned = setup(machine)
    assert isinstance(xm, Interferometer)
    first = xm.read()
    assert first.beam_ok
    assert first.channels[0] == pytest.approx(aligned.distance_mm * 1e3)
    np.testing.assert_allclose(first.channels[1:], 0.0, atol=1e-6)
    xm.zero()
    beam = line_frame(cnc.position + machine.receiver_offset - LAUNCH_MM)
    cnc.position = cnc.position + 0.050 * beam[0] + 0.020 * beam[1] - 0.010 * beam[2]
    moved = xm.read().channels
    np.testing.assert_allclose(moved[:3], [50.0, 20.0, -10.0], atol=1e-3)


def test_tool_rotation_shows_in_the_angle_channels(machine):
    motions = {name: (0, 0, 0.5, 0, 0, 1, 0, 0) for name in ErrorAmplitudes().motions}
    motions["EBX"] = (30, 0, 0.5, 0, 0, 1, 0, 0)
    xm, _, _ = setup(
        machine, ErrorAmplitudes(motions=motions, repeatability_um=0.0, squareness_urad=0.0)
    )
    eps = xm.machine.motions("X", np.array([1000.0]))[1][0]
    frame = line_frame(xm.launch.head_rotation(rot_z(GAMMA))[:, 0])
    reading_rad = xm.read().channels[3:] * 1e-6
    np.testing.assert_allclose(frame.T @ reading_rad, eps, atol=1e-9)


def test_beam_lost_outside_the_ranges(machine):
    xm, cnc, _ = setup(machine)
    cnc.position = cnc.position + np.array([0.0, 0.0, -0.5])  # 500 um across the beam
    assert not xm.read().beam_ok
    assert not xm.average(0.1).beam_ok


def test_average_reduces_noise_and_advances_the_clock(machine):
    xm, _, _ = setup(machine, noise=InterferometerNoise())
    start = xm.clock.now()
    singles = np.array([xm.read().channels for _ in range(200)])
    averages = np.array([xm.average(2.0).channels for _ in range(50)])
    assert xm.clock.now() - start == pytest.approx(100.0)
    assert singles[:, 1].std() == pytest.approx(0.2, rel=0.2)
    assert averages[:, 1].std() < singles[:, 1].std() / 5
