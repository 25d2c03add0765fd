"""Benchmark: a million instrument rows in stride (issue 31.4).

``xmalign post`` on 1e5 and 1e6 rows of each kind, run as a user runs it (a
fresh ``python -m xmalign``), its wall time and peak resident memory (the
process's own ``ru_maxrss``):

- **tracker on the fly**: the reference machine (``examples/fyxz.yaml``) runs
  the on-the-fly program (71 paths at 5000 mm/min); the virtual tracker logs a
  stream (:mod:`sim.tracker_stream`) at the rate that gives about N rows on the
  paths' cruise; ``xmalign import --tracker-stream`` turns it into the rows
  (timed too);
- **tracer lengths**: four places, N / 4 points each (a 5 x 4 x 3 grid and
  random points over the travel, :mod:`sim.tracer`).

Before issue 31 (a dense Jacobian of all rows, one object per row): 1e5 rows on
the fly 16 s and 0.77 GB; 1e6 rows 167 s and 6.6 GB; a million tracer lengths
119 s and 7.4 GB.

Run: ``PYTHONPATH=$PWD python tests/benchmarks/bench_instruments_scale.py
[--rows 100000 1000000] [--kinds fly tracer]``. Target: 1e6 rows fitted in
minutes in <= 2 GB, near-linear in the rows.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.tracer import VirtualTracer, measure_tracer
from sim.tracker import VirtualTracker
from sim.tracker_stream import StreamOptions, record_stream
from trajectories.instruments import (
    InstrumentProgram,
    fly_paths,
    grid_and_random_points,
    point_list_csv,
    propose_tracer_places,
    tracker_place,
)
from xmalign.formats.common import atomic_write_text
from xmalign.formats.instruments import write_tracer_lengths
from xmalign.formats.tracker_stream import write_tracker_stream
from xmalign.machine import default_machine_path, load_machine

ROOT = Path(__file__).resolve().parents[2]
#: Rows on the paths' cruise per stream sample at 100 Hz (measured: 113 385 of 159 283).
CRUISE_SHARE = 0.71


def run_xmalign(args: list[str], cwd: Path) -> tuple[float, float, float]:
    """``python -m xmalign ARGS``: wall time (s), CPU time (s) and peak RSS (GB).

    The CPU time is what the process itself used: on a machine shared with other
    jobs the wall time grows with their load, the CPU time much less.
    """
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "200"}
    log = cwd / "stderr.txt"
    start = time.perf_counter()
    with log.open("w") as stderr:  # a file, not a pipe: a full pipe would stall the process
        process = subprocess.Popen(
            [sys.executable, "-m", "xmalign", *args],
            cwd=cwd,
            env=env,
            stdout=stderr,
            stderr=stderr,
        )
        _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    if status != 0:
        raise SystemExit(f"xmalign {' '.join(args)} failed: {log.read_text()}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1e6


def fly_rows(folder: Path, rows: int) -> tuple[float, float, float]:
    """A stream with about ``rows`` rows on the paths, imported; the import's figures."""
    machine = load_machine(default_machine_path())
    truth = VirtualMachine(machine, ErrorAmplitudes(), seed=1)
    program = InstrumentProgram(paths_mm=fly_paths(machine))
    tracker = VirtualTracker(tracker_place(machine), np.array([0.5, -1.0, 30.0]), seed=1)
    rate = 100.0 * rows / (CRUISE_SHARE * 159_283)
    run = record_stream(machine, truth, tracker, program, StreamOptions(rate_hz=rate))
    write_tracker_stream(folder / "stream.csv", [run])
    atomic_write_text(folder / "points.csv", point_list_csv(program, machine.smr_offset))
    args = ["import", "--tracker-stream", "stream.csv", "--points", "points.csv"]
    return run_xmalign([*args, "--out", "tracker.csv"], folder)


def tracer_rows(folder: Path, rows: int) -> None:
    machine = load_machine(default_machine_path())
    truth = VirtualMachine(machine, ErrorAmplitudes(), seed=1)
    low, high = machine.travel_min_mm, machine.travel_max_mm
    points = grid_and_random_points(low, high, (5, 4, 3), rows // 4 - 60, seed=1)
    lengths = []
    for i, pivot in enumerate(propose_tracer_places(machine, 4)):
        tracer = VirtualTracer(pivot, seed=i)
        lengths += measure_tracer(truth, tracer, points, 1, machine.smr_offset, f"P{i + 1}")
    write_tracer_lengths(folder / "tracer.csv", lengths)


def _rows(path: Path) -> int:
    """Data rows of an instrument CSV (neither comments nor the header)."""
    with path.open() as lines:
        return sum(1 for line in lines if not line.startswith("#")) - 1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--kinds", nargs="+", default=["fly", "tracer"])
    options = parser.parse_args()
    print(
        f"{'kind':<8}{'rows':>10}{'import s':>10}{'cpu s':>8}{'GB':>6}"
        f"{'post s':>9}{'cpu s':>8}{'GB':>6}"
    )
    for kind in options.kinds:
        for rows in options.rows:
            with tempfile.TemporaryDirectory() as name:
                folder = Path(name)
                if kind == "fly":
                    imported = fly_rows(folder, rows)
                    given = ["--tracker", "tracker.csv"]
                    counted = _rows(folder / "tracker.csv")
                else:
                    tracer_rows(folder, rows)
                    imported = (float("nan"),) * 3
                    given = ["--tracer", "tracer.csv"]
                    counted = _rows(folder / "tracer.csv")
                wall, cpu, rss = run_xmalign(["post", *given, "--out", "errors.csv"], folder)
                print(
                    f"{kind:<8}{counted:>10}{imported[0]:>10.1f}{imported[1]:>8.1f}"
                    f"{imported[2]:>6.2f}{wall:>9.1f}{cpu:>8.1f}{rss:>6.2f}",
                    flush=True,
                )
                said = (folder / "stderr.txt").read_text().splitlines()
                chosen = [line.strip() for line in said if "mm apart" in line]
                print("\n".join(f"    {line}" for line in chosen), flush=True)


if __name__ == "__main__":
    main()
