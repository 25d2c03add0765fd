"""Benchmark: residual over the whole travel after LinuxCNC's volumetric component.

Run explicitly: ``PYTHONPATH=. python tests/benchmarks/bench_linuxcnc_volumetric.py``.

Held-out machines (virtual machines of seeds used nowhere else, FYXZ and XFYZ)
are measured on six lines (2 bidirectional runs, setup disturbances and
channel noise), ``post`` fits the tables, and the residual volumetric error at
the machine file's tool offset is evaluated on an 8 x 8 x 8 grid over the whole
travel, after removing a rigid motion (which no table can see), for:

- no compensation;
- pitch-only ``COMP_FILE`` (the files ``xmalign comp --controller linuxcnc``
  writes, pitch tables fitted to the predicted field over the travel, applied
  as LinuxCNC does: correction = nominal - actual at the commanded position,
  mean of both directions);
- the full fitted model, applied ideally (joints at ``k + c``, ``c = -dp(k + c)``);
- the component: the same model read back from the table file it loads.

Where LinuxCNC and halcompile are installed (and we are root), the first
machine is also run in a real headless LinuxCNC: the corrections read at the
component's pins on a 4 x 4 x 4 grid replace the computed ones.
Target: the component within 0.2 um RMS of the full model.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from sim.machine import VirtualMachine
from sim.synthetic import measure, six_line_plan
from xmalign.comp import compensate, linuxcnc
from xmalign.comp.linuxcnc_volumetric import (
    INSTANCE,
    correction_mm,
    merge_config,
    parse_table,
    render_table,
)
from xmalign.formats.common import atomic_write_text
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.machine import Machine, default_machine_path, load_machine
from xmalign.post.compare import grid_points, remove_rigid_motion
from xmalign.post.evaluate import post_process
from xmalign.rigid_body import AXES, AXIS_INDEX, Chain, deviation

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "linuxcnc"))
TARGET_UM = 0.2
#: (chain, seed) of the held-out machines
MACHINES = (("FYXZ", 9101), ("FYXZ", 9202), ("XFYZ", 9303))
TOOL_OFFSET_MM = [0.0, 0.0, -100.0]


def held_out_machine(chain: str) -> Machine:
    base = load_machine(default_machine_path()).model_dump()
    base.update(
        chain=chain,
        controller="linuxcnc",
        cnc={"tool_offset_mm": TOOL_OFFSET_MM, "max_correction_um": 200.0},
    )
    return Machine.model_validate(base)


def fitted_tables(machine: Machine, truth: VirtualMachine, seed: int) -> ErrorTableSet:
    plan = six_line_plan(machine, 21, runs=2, bidirectional=True)
    rows = measure(plan, Chain.parse(machine.chain), truth, np.random.default_rng(seed))
    return post_process(machine, plan, rows, "benchmark").fit.tables


def residual_um(
    chain: Chain, truth: VirtualMachine, points_mm: np.ndarray, correction: np.ndarray
) -> tuple[float, float]:
    """RMS and largest length of the tool point's error after ``correction``, um."""
    dp, _ = deviation(chain, points_mm + correction, TOOL_OFFSET_MM, truth)
    left = remove_rigid_motion(points_mm, correction + dp)
    lengths = np.linalg.norm(left, axis=1) * 1e3
    return float(np.sqrt(np.mean(lengths**2))), float(lengths.max())


def pitch_correction(machine: Machine, tables: ErrorTableSet, points_mm: np.ndarray) -> np.ndarray:
    """What LinuxCNC's COMP_FILE type 0 applies: nominal - actual (mean of both columns)."""
    files = compensate(machine, tables, linuxcnc.NAME).files
    correction = np.zeros_like(points_mm)
    for axis in AXES:
        i = AXIS_INDEX[axis]
        rows = np.array([line.split() for line in files[linuxcnc.comp_file(axis)].splitlines()])
        nominal, forward, reverse = rows.astype(float).T
        correction[:, i] = np.interp(points_mm[:, i], nominal, nominal - 0.5 * (forward + reverse))
    return correction


def live_corrections(
    machine: Machine, tables: ErrorTableSet, points_mm: np.ndarray
) -> np.ndarray | None:
    """The component's corrections at the pins of a headless LinuxCNC, or None."""
    from harness import (
        SimMachine,
        halcompile_available,
        host_lock,
        linuxcnc_available,
        run_linuxcnc,
        standard_start,
        write_sim_config,
    )

    if not (linuxcnc_available() and halcompile_available() and os.geteuid() == 0):
        return None
    folder = Path(tempfile.mkdtemp(prefix="xmalign-bench-"))
    try:
        with host_lock():
            shutil.copy(ROOT / "linuxcnc" / "xmalign_volcomp.comp", folder)
            subprocess.run(
                ["halcompile", "--install", "xmalign_volcomp.comp"],
                cwd=folder,
                check=True,
                capture_output=True,
            )
        travel = {a: tuple(machine.travel_mm[a]) for a in AXES}
        ini = write_sim_config(folder, SimMachine(coordinates="XYZ", travel_mm=travel))
        merged = merge_config(ini, tables, machine, folder)
        for name, text in merged.files.items():
            atomic_write_text(folder / name, text)
        names = [f"{INSTANCE}.motor-pos-out-{j}" for j in range(3)]
        names += [f"joint.{j}.motor-pos-cmd" for j in range(3)]
        actions = standard_start()
        for i, (x, y, z) in enumerate(points_mm):
            actions += [
                {"op": "mdi", "gcode": f"G53 G0 X{x:.4f} Y{y:.4f} Z{z:.4f}"},
                {"op": "pins", "names": names, "label": f"p{i}"},
            ]
        run = run_linuxcnc(folder / merged.ini_name, actions, timeout_s=300)
        pins = [run.value(f"p{i}") for i in range(len(points_mm))]
        return np.array(
            [
                [
                    p[f"{INSTANCE}.motor-pos-out-{j}"] - p[f"joint.{j}.motor-pos-cmd"]
                    for j in range(3)
                ]
                for p in pins
            ]
        )
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def run() -> float:
    worst_gap = 0.0
    print("residual over the whole travel, um RMS (max), rigid motion removed, t = [0, 0, -100]")
    for number, (chain_name, seed) in enumerate(MACHINES):
        machine = held_out_machine(chain_name)
        chain = Chain.parse(chain_name)
        truth = VirtualMachine(machine, seed=seed)
        tables = fitted_tables(machine, truth, seed + 1)
        points = grid_points(machine.travel_min_mm, machine.travel_max_mm, 8)
        fitted = tables.model("")
        component = parse_table(render_table(tables, chain, "XYZ", TOOL_OFFSET_MM, 200.0))
        figures = {
            "none": residual_um(chain, truth, points, np.zeros_like(points)),
            "pitch COMP_FILE": residual_um(
                chain, truth, points, pitch_correction(machine, tables, points)
            ),
            "full model": residual_um(
                chain, truth, points, correction_mm(chain, fitted, TOOL_OFFSET_MM, points)
            ),
            "component": residual_um(
                chain,
                truth,
                points,
                correction_mm(component.chain, component.model, TOOL_OFFSET_MM, points),
            ),
        }
        gap = abs(figures["component"][0] - figures["full model"][0])
        if number == 0:
            live_points = grid_points(machine.travel_min_mm, machine.travel_max_mm, 4)
            live = live_corrections(machine, tables, live_points)
            if live is not None:
                on_pins = residual_um(chain, truth, live_points, live)
                ideal = residual_um(
                    chain,
                    truth,
                    live_points,
                    correction_mm(chain, fitted, TOOL_OFFSET_MM, live_points),
                )
                figures["component, LinuxCNC pins (4^3)"] = on_pins
                figures["full model (same 4^3)"] = ideal
                gap = max(gap, abs(on_pins[0] - ideal[0]))
        worst_gap = max(worst_gap, gap)
        print(f"{machine.chain} seed {seed}:")
        for name, (rms, largest) in figures.items():
            print(f"  {name:32s} {rms:7.3f} ({largest:7.3f})")
    print(f"component vs full model: largest RMS gap {worst_gap:.1e} um (target {TARGET_UM} um)")
    return worst_gap


def test_linuxcnc_volumetric_benchmark() -> None:
    assert run() <= TARGET_UM


if __name__ == "__main__":
    run()
