"""Benchmark: how many runs the axis lines and the diagonals need (issue 13, docs/machine-time.md).

For each choice of ``measurement.runs`` / ``measurement.diagonal_runs`` the dry
run (identify, program, run, post) of the reference machine, both chains, the
same seeds for every choice (common random numbers): volumetric residual after
compensation over the measured strokes (mean and worst) and the measuring time.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_runs.py [--seeds 10]``.
Target: <= 0.6 um on every seed, G-code <= 12 min.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from sim.dry_run import DryRunOptions, simulate_calibration
from xmalign.machine import Machine, default_machine_path, load_machine

CHOICES = ((2, 2), (2, 1), (1, 2), (1, 1))
CHAINS = ("FYXZ", "XFYZ")


def with_runs(machine: Machine, chain: str, runs: int, diagonal_runs: int) -> Machine:
    measurement = machine.measurement.model_copy(
        update={"runs": runs, "diagonal_runs": diagonal_runs}
    )
    return machine.model_copy(update={"chain": chain, "measurement": measurement})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    arguments = parser.parse_args()
    reference = load_machine(default_machine_path())
    print("chain  runs axis/diagonal  residual mean um  worst um  measuring min")
    for chain in CHAINS:
        for runs, diagonal_runs in CHOICES:
            machine = with_runs(reference, chain, runs, diagonal_runs)
            residual, minutes = [], []
            for seed in range(1, arguments.seeds + 1):
                with tempfile.TemporaryDirectory() as folder:
                    report = simulate_calibration(machine, Path(folder), DryRunOptions(seed=seed))
                residual.append(report.volumetric_after_um)
                minutes.append(report.measuring_s / 60)
            print(
                f"{chain}  {runs} / {diagonal_runs}  {np.mean(residual):16.3f}"
                f"  {max(residual):8.3f}  {min(minutes):.1f}-{max(minutes):.1f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
