"""Benchmark: CPU time to simulate a six-line calibration of 600 captured points.

Target (issue 3): <= 10 s of CPU. Run: ``python tests/benchmarks/bench_sim.py``.
Six lines, radial from the launch unit so the beam stays on the receiver, 100
targets each, units aligned at every line start, 2 s dwell averaged at 50
samples/s per point (600 points = 60 000 simulated samples, 20 min simulated).
"""

from __future__ import annotations

import time

import numpy as np

from sim.units import SimPositioningUnit
from sim.world import FixedPosition, build_world
from xmalign.kinematics import aligned_angles, receiver_cp
from xmalign.machine import default_machine_path, load_machine
from xmalign.roles import CHANNELS

LINE_STARTS_MM = [
    (300.0, 300.0, -480.0),
    (400.0, 200.0, -470.0),
    (200.0, 500.0, -460.0),
    (600.0, 600.0, -400.0),
    (250.0, 250.0, -490.0),
    (500.0, 150.0, -450.0),
]
POINTS_PER_LINE = 100
LENGTH_MM = 900.0
DWELL_S = 2.0


def run() -> tuple[int, float, float]:
    machine = load_machine(default_machine_path())
    cnc = FixedPosition(LINE_STARTS_MM[0])
    world = build_world(machine, position=cnc, seed=7)
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    offset = machine.receiver_offset
    captured = 0
    lost = 0
    for start in LINE_STARTS_MM:
        start = np.array(start)
        cp = receiver_cp(start, offset, machine.spindle_angle_rad)
        u = (cp - world.launch2mcs_mm) / np.linalg.norm(cp - world.launch2mcs_mm)
        cnc.position = start
        angles = aligned_angles(world.launch2mcs_mm, world.gamma_rad, cp, machine.spindle_angle_rad)
        launch.move_to(angles.launch_rad, 120.0)
        receiver.move_to(angles.receiver_rad, 120.0)
        world.interferometer.zero()
        for distance in np.linspace(0.0, LENGTH_MM, POINTS_PER_LINE):
            cnc.position = start + distance * u
            world.clock.sleep(1.0)  # the CNC's move and settling
            reading = world.interferometer.average(DWELL_S)
            captured += 1
            lost += not reading.beam_ok
    return captured, lost, world.clock.now()


if __name__ == "__main__":
    cpu_start = time.process_time()
    points, lost, simulated_s = run()
    cpu_s = time.process_time() - cpu_start
    print(
        f"{points} points ({len(CHANNELS)} channels, {lost} with the beam lost), "
        f"{simulated_s / 60:.1f} min simulated, CPU {cpu_s:.2f} s (target <= 10 s)"
    )
