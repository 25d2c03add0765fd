"""Benchmark: four laser tracers one place at a time against all at once (issue 31.5).

The whole instrument dry run (:func:`sim.instrument_dry_run.simulate_instruments`:
``xmalign program --instrument tracer``'s plan with its three proposed SMR
positions, the virtual tracers with a 0.5 ppm scale per run, the machine's scales
at 20.6 to 21.4 degC through each run, then ``post``), on the reference machine
(``examples/fyxz.yaml``) with seeds 1..N, both ways:

- **one place at a time**: one tracer moved through the four places, the program
  run once at each;
- **all at once** (``--simultaneous``): a tracer at every place, all following the
  SMR through one run of the program (one draw of the machine's repeatability
  and temperature per point, seen by every tracer).

Figures: machine time of the programs (the G-code's own estimate, SMR changes
included) and the RMS volumetric difference from the truth at the tool point
after removing a rigid motion, 8 x 8 x 8 grid over the whole travel.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_tracers_at_once.py [--seeds 3]``.
Targets: all at once a quarter of the machine time (within 5 %), the residual
at most 0.1 um worse than one place at a time, both <= 1.0 um.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from sim.instrument_dry_run import simulate_instruments
from xmalign.machine import default_machine_path, load_machine

TIME_RATIO = 0.25
TIME_TOLERANCE = 0.05
RESIDUAL_MARGIN_UM = 0.1
RESIDUAL_TARGET_UM = 1.0


def both_ways(seed: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """(minutes, residual um) one place at a time, then all at once."""
    machine = load_machine(default_machine_path())
    figures = []
    with tempfile.TemporaryDirectory() as folder:
        for simultaneous in (False, True):
            out = Path(folder) / f"at-once-{simultaneous}"
            run = simulate_instruments(machine, out, "tracer", seed, None, simultaneous)
            figures.append((run.instrument_min, run.volumetric_after_um))
    return figures[0], figures[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    seeds = range(1, parser.parse_args().seeds + 1)
    failed = []
    print("seed  one at a time: min  um   all at once: min  um")
    for seed in seeds:
        (apart_min, apart_um), (together_min, together_um) = both_ways(seed)
        print(
            f"{seed:4d}  {apart_min:22.0f} {apart_um:5.2f}  {together_min:16.0f} {together_um:5.2f}"
        )
        if abs(together_min / apart_min - TIME_RATIO) > TIME_TOLERANCE:
            failed.append(f"seed {seed}: time ratio {together_min / apart_min:.2f}")
        if (
            together_um > apart_um + RESIDUAL_MARGIN_UM
            or max(apart_um, together_um) > RESIDUAL_TARGET_UM
        ):
            failed.append(f"seed {seed}: {apart_um:.2f} -> {together_um:.2f} um")
    for line in failed:
        print(f"FAILED {line}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
