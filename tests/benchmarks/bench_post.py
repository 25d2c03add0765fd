"""Benchmark: ``post`` on six lines x 2 bidirectional runs x 50 targets in <= 3 s.

Run explicitly: ``python tests/benchmarks/bench_post.py`` (or with pytest).
Also reports the volumetric reproduction of the virtual machine (target <= 1 um
RMS after removing a rigid motion).
"""

from __future__ import annotations

import time

import numpy as np

from sim.machine import VirtualMachine
from sim.synthetic import measure, six_line_plan
from xmalign.machine import default_machine_path, load_machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import post_process
from xmalign.rigid_body import Chain, ErrorTables

TARGET_S = 3.0


def run() -> tuple[float, float, float]:
    machine = load_machine(default_machine_path())
    chain = Chain.parse(machine.chain)
    truth = VirtualMachine(machine, seed=2024)
    plan = six_line_plan(machine, 50, runs=2, bidirectional=True)
    rows = measure(plan, chain, truth, np.random.default_rng(1), backlash_mm=[0.004, 0.003, 0.002])
    start = time.perf_counter()
    result = post_process(machine, plan, rows, "benchmark")
    elapsed = time.perf_counter() - start
    points = grid_points(machine.travel_min_mm, machine.travel_max_mm, 8)
    before = volumetric_rms_um(chain, points, ErrorTables(), truth)
    after = volumetric_rms_um(chain, points, result.fit.tables.model(""), truth)
    print(
        f"post: {len(rows)} points, {result.fit.n_parameters} parameters in {elapsed:.2f} s"
        f" (target {TARGET_S} s); volumetric RMS of the machine {before:.1f} um,"
        f" tables vs truth {after:.2f} um (target 1 um)"
    )
    return elapsed, before, after


def test_post_benchmark() -> None:
    elapsed, before, after = run()
    assert elapsed <= TARGET_S
    assert before > 10.0 and after <= 1.0


if __name__ == "__main__":
    run()
