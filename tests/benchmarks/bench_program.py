"""Benchmark: ``xmalign program`` on the reference machine must take <= 1 s wall time.

Run explicitly: ``python tests/benchmarks/bench_program.py``. Prints the wall
time of the whole command (process start, imports, planning, G-code, plan file)
for every dialect, and of the planning + G-code work alone.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from trajectories.gcode import DIALECTS
from trajectories.gcode.program import write_program
from trajectories.planner import plan_measurement
from xmalign.formats.pose import LaunchPose, write_pose
from xmalign.machine import default_machine_path, load_machine

BUDGET_S = 1.0


def main() -> int:
    machine = load_machine(default_machine_path())
    pose = LaunchPose(
        position_mm=np.array([100.0, 100.0, -680.0]),
        gamma_rad=np.radians(30.0),
        covariance=np.diag([0.05**2] * 3 + [20e-6**2]),
        encoder_offsets_rad={"c2": 0.0, "c3": 0.0, "c4": 0.0},
    )
    start = time.perf_counter()
    measurement = plan_measurement(machine, pose)
    for dialect in DIALECTS.values():
        write_program(measurement.plan, machine, dialect())
    in_process_s = time.perf_counter() - start
    print(f"planning + G-code in all {len(DIALECTS)} dialects, in process: {in_process_s:.3f} s")
    worst = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        pose_path = Path(tmp) / "pose.json"
        write_pose(pose_path, pose)
        for dialect in DIALECTS:
            command = [
                sys.executable,
                "-m",
                "xmalign",
                "program",
                "--pose",
                str(pose_path),
                "--plan-out",
                str(Path(tmp) / "plan.json"),
                "--dialect",
                dialect,
                "--out",
                str(Path(tmp) / "run.nc"),
            ]
            start = time.perf_counter()
            subprocess.run(command, check=True, capture_output=True)
            wall_s = time.perf_counter() - start
            worst = max(worst, wall_s)
            print(f"xmalign program --dialect {dialect}: {wall_s:.3f} s wall")
    verdict = "within" if worst <= BUDGET_S else "OVER"
    print(f"worst {worst:.3f} s, {verdict} the {BUDGET_S:.1f} s budget")
    return 0 if worst <= BUDGET_S else 1


if __name__ == "__main__":
    sys.exit(main())
