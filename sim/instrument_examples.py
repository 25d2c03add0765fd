"""Writes examples/tracker.csv, examples/tracer.csv and examples/spatial-analyzer.txt.

The simulator measures the reference machine (seed 7) as
``xmalign program --instrument tracker`` and ``--instrument tracer`` plan it:
the tracker's 250 points twice, the tracers' points (here 200 per place, to
keep the example small) from the four proposed places. The SpatialAnalyzer
export holds the same tracker readings as ``tracker.csv``, so ``xmalign import``
of it with the program's point list gives the same points.

Run: ``PYTHONPATH=$PWD python -m sim.instrument_examples [FOLDER]`` (default examples/).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from sim.machine import VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker, measure_tracker
from trajectories.instruments import (
    grid_and_random_points,
    program_start_mm,
    propose_tracer_places,
    tracker_place,
    tracker_points,
    visiting_order,
)
from xmalign.formats.common import atomic_write_text
from xmalign.formats.instruments import (
    TrackerPoint,
    write_tracer_lengths,
    write_tracker_points,
)
from xmalign.machine import Machine, default_machine_path, load_machine

SEED = 7
TRACER_POINTS_PER_PLACE = (4, 4, 3), 152


def spatial_analyzer_text(points: list[TrackerPoint]) -> str:
    """The readings as SpatialAnalyzer exports them: ``Collection Group Target X Y Z``."""
    lines = ["// SpatialAnalyzer ASCII export (simulated, xmalign sim.instrument_examples)"]
    lines += ["// Collection Group Target X Y Z (mm)"]
    lines += [
        f"A run{p.run} {p.index} " + " ".join(f"{v:.4f}" for v in p.tracker_mm) for p in points
    ]
    return "\n".join(lines) + "\n"


def write_examples(folder: Path, machine: Machine) -> None:
    truth = VirtualMachine(machine, seed=SEED)
    tracker = VirtualTracker(tracker_place(machine), np.array([0.5, -1.0, 30.0]), seed=SEED)
    rows = measure_tracker(truth, tracker, tracker_points(machine), 2, machine.smr_offset)
    rows = [
        TrackerPoint(r.station, r.run, r.index, r.machine_mm, np.round(r.tracker_mm, 4))
        for r in rows
    ]
    write_tracker_points(folder / "tracker.csv", rows)
    atomic_write_text(folder / "spatial-analyzer.txt", spatial_analyzer_text(rows))
    lengths = []
    guesses = {}
    grid, n_random = TRACER_POINTS_PER_PLACE
    low, high = machine.travel_min_mm, machine.travel_max_mm
    for i, pivot in enumerate(propose_tracer_places(machine, 4)):
        points = visiting_order(
            grid_and_random_points(low, high, grid, n_random, SEED * 10 + i),
            program_start_mm(machine),
        )
        tracer = VirtualTracer(pivot, seed=SEED * 10 + i)
        lengths += measure_tracer(truth, tracer, points, 1, machine.smr_offset, f"P{i + 1}")
        guesses[f"P{i + 1}"] = np.round(pivot + [30.0, -20.0, 10.0], -1)
    write_tracer_lengths(folder / "tracer.csv", lengths, guesses)


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("examples")
    write_examples(target, load_machine(default_machine_path()))
