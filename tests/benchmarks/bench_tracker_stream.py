"""Benchmark: the tracker on the fly from its own stream against the tracker at a standstill.

The instrument dry runs (:func:`sim.instrument_dry_run.simulate_instruments`) on the
same virtual machines (seeds 1..N of the reference machine ``examples/fyxz.yaml``,
seed 003's error amplitudes, 0.5 um repeatability):

- **standstill**: 250 points (seed 000's grid and random points) measured twice,
  3 s dwell each;
- **on the fly from the stream** (seed 001, issue 31): 71 paths at 5000 mm/min; the
  virtual tracker logs a stream at 100 Hz with its own clock (offset, 80 ppm rate
  error), the machine's moves between the paths, accelerations, stops and 10 ms
  servo lag, and noise correlated over 50 ms (:mod:`sim.tracker_stream`);
  ``import --tracker-stream`` assigns the samples to the paths and the fit
  widens its uncertainty for the correlation.

Both stand the tracker in the same place, turned by (0.5, -1, 30) degrees, with
the same noise model (half the published MPE). Figures: RMS volumetric difference
from the truth at the SMR over an 8 x 8 x 8 grid of the whole travel, rigid motion
removed; what the fit says of it (2 x the RMS standard uncertainty of the fitted
volumetric error, :meth:`xmalign.post.instruments.JointFit.volumetric_u_um`); the
G-code's machine time.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_tracker_stream.py [--seeds 5]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from sim.instrument_dry_run import simulate_instruments
from xmalign.machine import default_machine_path, load_machine
from xmalign.post.compare import grid_points
from xmalign.rigid_body import Chain


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    options = parser.parse_args()
    machine = load_machine(default_machine_path())
    chain = Chain.parse(machine.chain)
    grid = grid_points(machine.travel_min_mm, machine.travel_max_mm, 8)
    print(f"{'seed':<5}{'way':<12}{'after um':>9}{'fit U95 um':>11}{'min':>6}{'rows':>8}{'s':>7}")
    figures: dict[str, list[tuple[float, float, float]]] = {"standstill": [], "on the fly": []}
    for seed in range(1, options.seeds + 1):
        for way, fly in (("standstill", False), ("on the fly", True)):
            with tempfile.TemporaryDirectory() as name:
                start = time.perf_counter()
                report = simulate_instruments(machine, Path(name), "tracker", seed, None, fly)
                wall = time.perf_counter() - start
            joint = report.result.instruments
            assert joint is not None
            claimed = 2 * joint.volumetric_u_um(chain, grid)
            after = report.volumetric_after_um
            figures[way].append((after, claimed, report.instrument_min))
            print(
                f"{seed:<5}{way:<12}{after:>9.2f}{claimed:>11.2f}{report.instrument_min:>6.1f}"
                f"{joint.trackers[0].n_points:>8}{wall:>7.1f}",
                flush=True,
            )
    for way, rows in figures.items():
        a = np.array(rows)
        print(
            f"{way}: after {a[:, 0].min():.2f}-{a[:, 0].max():.2f} um (mean {a[:, 0].mean():.2f}),"
            f" fit U95 {a[:, 1].min():.2f}-{a[:, 1].max():.2f} um, machine time"
            f" {a[:, 2].mean():.1f} min"
        )


if __name__ == "__main__":
    main()
