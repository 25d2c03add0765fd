"""Benchmark of the air and material compensation on a drifting shop.

Run: python tests/benchmarks/bench_environment.py [--seeds 2]

For each seed: identify the launch unit on the virtual reference machine,
plan, then run the measurement program while the shop drifts (air 22 -> 25 °C
with a ±0.2 K air-conditioning wave, pressure 975 -> 972 hPa, humidity
45 -> 55 %, the machine 22 -> 23 °C, the machine file's 11.5 ppm/K) and a simulated weather
station reports it on every captured point. The same seed is measured again in
a shop held at 20 °C. Prints the volumetric residual of the fitted tables
against the truth over the measured strokes (rigid motion removed) for the
20 °C shop (compensated) and the drifting shop with and without compensation,
and the drift seen at the first target of each line; checks that the
compensated drifting case is within 0.1 um of the 20 °C case.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from sim.dry_run import identify_virtually, measured_strokes, virtual_setup
from sim.environment import ShopClimate, attach_shop
from trajectories.gcode import DIALECTS, resolve_dialect
from trajectories.gcode.program import write_program
from trajectories.identification_design import design_identification
from trajectories.planner import plan_measurement
from xmalign.calibration import CalibrationRun, capture_program
from xmalign.environment import EnvironmentMonitor, EnvironmentSample, compensate_station
from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan
from xmalign.machine import Machine, default_machine_path, load_machine
from xmalign.post.compare import grid_points, volumetric_rms_um
from xmalign.post.evaluate import post_process
from xmalign.report import RecordInfo, write_report
from xmalign.rigid_body import Chain
from xmalign.safety import units_locked_on_exit

TARGET_UM = 0.1


@dataclass
class Measured:
    rows: list[MeasurementRow]
    samples: list[EnvironmentSample]


def compensated_rows(
    plan: Plan, measured: Measured, expansion: float, dead_path: bool = True
) -> list[MeasurementRow]:
    """The rows compensated as ``post`` does; without ``dead_path`` no beam distances."""
    if not dead_path:
        plan = replace(plan, lines=[replace(line, extra={}) for line in plan.lines])
    environments = [sample.values for sample in measured.samples]
    return compensate_station(plan, measured.rows, environments, expansion).rows


def calibrate(
    machine: Machine, seed: int, climate: ShopClimate, report: Path | None = None
) -> dict:
    setup = virtual_setup(machine, seed)
    with tempfile.TemporaryDirectory() as workdir:
        positions = design_identification(machine, 6).machine_mm
        pose = identify_virtually(setup, machine, positions, Path(workdir) / "s.json", seed=seed)
    measurement_plan = plan_measurement(machine, pose.to_pose())
    plan = measurement_plan.plan
    dialect = resolve_dialect(machine, None)
    program = write_program(plan, machine, DIALECTS[dialect]())
    world = setup.world
    monitor = EnvironmentMonitor(attach_shop(world, climate, seed))
    monitor.prime()
    measured = Measured([], [])

    def record(row: MeasurementRow) -> None:
        measured.rows.append(row)
        measured.samples.append(monitor.sample())

    started = world.clock.now()
    with units_locked_on_exit(setup.launch, setup.receiver):
        run = CalibrationRun(
            plan, setup.launch, setup.receiver, world.interferometer, world.clock, record
        )
        capture_program(run, setup.cnc.run_program(program, dialect))
    chain = Chain.parse(machine.chain)
    points = grid_points(*measured_strokes(measurement_plan))
    truth = world.machine
    expansion = machine.thermal.expansion_ppm_per_k
    figures: dict = {"minutes": (world.clock.now() - started) / 60}
    for name, rows in (
        ("raw", measured.rows),
        ("compensated", compensated_rows(plan, measured, expansion)),
        ("no dead path", compensated_rows(plan, measured, expansion, False)),
    ):
        tables = post_process(machine, plan, rows, "bench").fit.tables
        figures[name] = volumetric_rms_um(chain, points, truth, tables.model())
    air = np.array([s.values["air_temp_c"] for s in measured.samples])
    material = np.array([s.values["material_temp_c"] for s in measured.samples])
    figures["air"] = (air.min(), air.max())
    figures["material"] = (material.min(), material.max())
    if report is not None:
        write_record(report, machine, plan, measured)
    return figures


def write_record(directory: Path, machine: Machine, plan: Plan, measured: Measured) -> None:
    """The calibration record of a measurement (HTML and PDF), as ``post --report`` would."""
    environments = [sample.values for sample in measured.samples]
    compensation = compensate_station(
        plan, measured.rows, environments, machine.thermal.expansion_ppm_per_k
    )
    result = post_process(machine, plan, compensation.rows, "bench")
    info = RecordInfo.of_compensation(
        compensation,
        operator="bench_environment.py",
        instruments={"interferometer": "SIM-XM60", "weather station": "SIM-XC80"},
        vdi3441=True,
    )
    directory.mkdir(parents=True, exist_ok=True)
    for name in ("record.html", "record.pdf"):
        write_report(directory / name, machine, result, machine.controller, info)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--report", type=Path, help="Write seed 1's record (HTML, PDF) here.")
    args = parser.parse_args()
    machine = load_machine(default_machine_path())
    print(
        f"{'seed':>4} {'20C comp um':>11} {'drift comp um':>13} {'drift raw um':>12}"
        f" {'no dead path um':>15} {'|diff| um':>9} {'air C':>11} {'material C':>11}"
        f" {'run min':>7} {'wall s':>6}"
    )
    worst = 0.0
    for seed in range(1, args.seeds + 1):
        start = time.perf_counter()
        reference = calibrate(machine, seed, ShopClimate.reference())
        drifting = calibrate(
            machine, seed, ShopClimate.drifting(), args.report if seed == 1 else None
        )
        wall = time.perf_counter() - start
        diff = abs(drifting["compensated"] - reference["compensated"])
        worst = max(worst, diff)
        air, material = drifting["air"], drifting["material"]
        print(
            f"{seed:>4} {reference['compensated']:>11.3f} {drifting['compensated']:>13.3f}"
            f" {drifting['raw']:>12.1f} {drifting['no dead path']:>15.3f} {diff:>9.3f}"
            f" {air[0]:>5.2f}-{air[1]:<5.2f}"
            f" {material[0]:>5.2f}-{material[1]:<5.2f} {drifting['minutes']:>7.1f} {wall:>6.1f}"
        )
    verdict = "PASS" if worst <= TARGET_UM else "FAIL"
    print(
        f"{verdict}  compensated drifting shop within {TARGET_UM} um of 20 °C (worst {worst:.3f})"
    )
    raise SystemExit(0 if worst <= TARGET_UM else 1)


if __name__ == "__main__":
    main()
