"""Benchmark: the first alignment by itself (xmalign.beam_search), the launch azimuth unknown.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_beam_search.py [--trials 20] [--alignments 6]``

Each trial is one seeded virtual setup of the reference machine as the dry run
places it (sim.dry_run.placement: the launch unit up to 25 mm from the machine
file's place along each axis, its azimuth anywhere on the circle), the CNC at
the first designed identification position, in-process on the virtual clock.
The search starts from the machine file's place alone; a trial succeeds when
fine alignment converges from where the search left the units. Reported: the
success rate, the search's simulated time (median, max) and sweeps, the wall
time per trial.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from sim.dry_run import placement
from sim.units import SimPositioningUnit
from sim.world import FixedPosition, build_world
from xmalign.alignment import fine_align
from xmalign.beam_search import search_first_beam
from xmalign.errors import BeamLostError, DeviceTimeoutError
from xmalign.kinematics import receiver_cp
from xmalign.machine import default_machine_path, load_machine
from xmalign.steps import design_step

TARGET_S = 300.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--alignments", type=int, default=6)
    args = parser.parse_args()
    trials = args.trials
    machine = load_machine(default_machine_path())
    assert machine.launch_unit is not None
    rough = np.asarray(machine.launch_unit.position_mm, dtype=float)
    position = design_step(machine, args.alignments).machine_mm[0]
    cp = receiver_cp(position, machine.receiver_offset, machine.spindle_angle_rad)
    print(f"searching at {position.tolist()} mm, {np.linalg.norm(cp - rough):.0f} mm away")
    found, times_s, sweeps, walls = 0, [], [], []
    for seed in range(trials):
        placed = placement(machine, seed)
        world = build_world(
            placed.machine, FixedPosition(position), seed=seed, gamma_rad=placed.gamma_rad
        )
        launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
        wall = time.perf_counter()
        try:
            result = search_first_beam(
                launch, receiver, world.interferometer, world.clock, rough, cp,
                machine.spindle_angle_rad, machine.interferometer,
            )  # fmt: skip
            fine_align(
                launch, receiver, world.interferometer, world.clock,
                float(np.linalg.norm(cp - rough)),
            )  # fmt: skip
        except (BeamLostError, DeviceTimeoutError) as error:
            print(f"seed {seed}: not found: {error}")
            continue
        walls.append(time.perf_counter() - wall)
        found += 1
        times_s.append(result.elapsed_s)
        sweeps.append(result.sweeps)
        print(f"seed {seed}: {result.elapsed_s:.1f} s simulated, {result.sweeps} sweep(s)")
    print(
        f"found and aligned {found} of {trials}; search median {np.median(times_s):.1f} s,"
        f" max {max(times_s):.1f} s simulated; sweeps {min(sweeps)}-{max(sweeps)};"
        f" wall {np.median(walls):.1f} s per trial (in-process); target <= {TARGET_S:.0f} s"
    )


if __name__ == "__main__":
    main()
