"""Benchmark: machine time of the measurement, one and two launch-unit stations (issue 13).

For each seed: the G-code's own estimate (:func:`trajectories.gcode.program.
estimate_machine_time`: programmed feeds, the machine file's
``cnc.acceleration_mm_s2``, dwells) of each station's program, and the
simulated on-machine time of the two-station dry run
(:func:`sim.two_stations.simulate_two_stations`: identification, alignment and
the program executed by the simulated CNC with the machine file's feeds and
acceleration, capturing at every dwell), with the volumetric residual.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_machine_time.py [--seeds 3]``.
Targets: G-code time <= 12 min for station 1, <= 25 min for both stations.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from sim.dry_run import DryRunOptions
from sim.two_stations import simulate_two_stations
from trajectories.gcode.program import estimate_machine_time
from xmalign.formats.plan import read_plan
from xmalign.machine import default_machine_path, load_machine


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    machine = load_machine(default_machine_path())
    print(
        f"{'seed':>4} {'G-code 1 min':>12} {'G-code 2 min':>12} {'G-code 1+2':>10}"
        f" {'sim 1 min':>9} {'sim 2 min':>9} {'sim 1+2':>8} {'strokes um':>10} {'travel um':>9}"
    )
    worst_one = worst_two = 0.0
    for seed in range(1, args.seeds + 1):
        with tempfile.TemporaryDirectory() as workdir:
            report = simulate_two_stations(machine, Path(workdir), DryRunOptions(seed=seed))
            gcode = [
                estimate_machine_time(read_plan(Path(workdir) / f"station{n}-plan.json"), machine)
                for n in (1, 2)
            ]
        g1, g2 = (t.total_s / 60 for t in gcode)
        s1, s2 = (station.on_machine_s / 60 for station in report.stations)
        worst_one, worst_two = max(worst_one, g1), max(worst_two, g1 + g2)
        print(
            f"{seed:>4} {g1:>12.1f} {g2:>12.1f} {g1 + g2:>10.1f} {s1:>9.1f} {s2:>9.1f}"
            f" {s1 + s2:>8.1f} {report.strokes_um:>10.2f} {report.travel_um:>9.2f}"
        )
    print(
        f"{'PASS' if worst_one <= 12 else 'FAIL'}  G-code, one station <= 12 min ({worst_one:.1f})"
    )
    print(
        f"{'PASS' if worst_two <= 25 else 'FAIL'}  G-code, two stations <= 25 min ({worst_two:.1f})"
    )


if __name__ == "__main__":
    main()
