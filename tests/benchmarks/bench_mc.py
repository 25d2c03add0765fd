"""Benchmark of ``xmalign mc``: trials per minute/second on the local cores.

Run explicitly: ``python tests/benchmarks/bench_mc.py [--workers 2]``. Targets:
at least 1000 identification-only trials per minute on 2 cores; the
full-calibration rate is reported.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor

from sim.mc import Strategy, StudySettings, run_study
from xmalign.machine import default_machine_path, load_machine

IDENTIFICATION_TARGET_PER_MIN = 1000.0


def trials_per_second(mode: str, trials: int, workers: int) -> float:
    """Rate of one strategy's trials, pool start-up included, the study never stopping early."""
    machine = load_machine(default_machine_path())
    # digits=6: the stopping rule is never met, so exactly ``trials`` run
    settings = StudySettings(mode=mode, max_trials=trials, batch=trials, digits=6)
    started = time.perf_counter()
    with ProcessPoolExecutor(workers) as pool:
        (result,) = run_study(machine, [Strategy()], settings, pool)
    elapsed = time.perf_counter() - started
    return result.trials / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--identification-trials", type=int, default=2000)
    parser.add_argument("--calibration-trials", type=int, default=20)
    args = parser.parse_args()
    rate = trials_per_second("identification", args.identification_trials, args.workers)
    verdict = "meets" if rate * 60 >= IDENTIFICATION_TARGET_PER_MIN else "MISSES"
    print(
        f"identification-only: {rate * 60:.0f} trials/min on {args.workers} workers"
        f" ({verdict} the {IDENTIFICATION_TARGET_PER_MIN:.0f}/min target)"
    )
    rate = trials_per_second("calibration", args.calibration_trials, args.workers)
    print(f"full calibration: {rate:.2f} trials/s on {args.workers} workers")


if __name__ == "__main__":
    main()
