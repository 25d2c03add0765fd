"""``xmalign run`` and ``xmalign dry-run``: the measurement, and the whole calibration simulated."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from xmalign.cli.common import console, machine_or_default
from xmalign.errors import InputError
from xmalign.formats.measurements import MeasurementRow, MeasurementWriter, read_measurements
from xmalign.formats.plan import Plan, read_plan
from xmalign.machine import Machine

MachineOption = Annotated[
    Path | None, typer.Option("--machine", help="Machine YAML (default: the reference machine).")
]


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    )


def _point_count(plan: Plan) -> int:
    return sum(
        line.runs * len(line.targets_mm) * (2 if line.bidirectional else 1) for line in plan.lines
    )


def _recorder(
    writer: MeasurementWriter, advance: Callable[[], None]
) -> Callable[[MeasurementRow], None]:
    def record(row: MeasurementRow) -> None:
        writer.append(row)
        advance()

    return record


def _run_sim(
    machine: Machine,
    plan: Plan,
    out: Path,
    resume: bool,
    seed: int,
    program: Path | None,
    dialect: str | None,
) -> None:
    from sim.dry_run import measure_virtually, virtual_setup
    from trajectories.gcode import make_dialect, resolve_dialect
    from trajectories.gcode.program import write_program

    dialect_name = resolve_dialect(machine, dialect)
    text = (
        program.read_text(encoding="utf-8")
        if program is not None
        else write_program(plan, machine, make_dialect(dialect_name, machine))
    )
    setup = virtual_setup(machine, seed)
    done = len(read_measurements(out)) if resume and out.exists() else 0
    with _progress() as progress:
        task = progress.add_task("measuring (simulated)", total=_point_count(plan), completed=done)
        run = measure_virtually(setup, plan, text, dialect_name, out, resume)
        progress.update(task, completed=done + run.statistics.points)
    console.print(
        f"{run.statistics.points} points captured to {out} in {setup.world.clock.now() / 60:.1f}"
        " min of simulated machine time",
        markup=False,
    )


def _run_live(machine: Machine, plan: Plan, out: Path, resume: bool, config_path: Path) -> None:
    from firmware_iface.config import load_units_config, open_devices
    from xmalign.calibration import CalibrationRun, follow_machine, step_through
    from xmalign.roles import WallClock
    from xmalign.safety import units_locked_on_exit

    config = load_units_config(config_path)
    done = {row.key() for row in read_measurements(out)} if resume and out.exists() else set()
    if not resume:
        out.unlink(missing_ok=True)
    devices = open_devices(config, machine)
    try:
        with (
            MeasurementWriter(out) as writer,
            units_locked_on_exit(devices.launch, devices.receiver),
            _progress() as progress,
        ):
            task = progress.add_task("measuring", total=_point_count(plan), completed=len(done))
            run = CalibrationRun(
                plan,
                devices.launch,
                devices.receiver,
                devices.interferometer,
                WallClock(),
                _recorder(writer, lambda: progress.advance(task)),
                done=done,
            )
            if config.machine_position.source == "file":
                follow_machine(run, devices.mover, plan.lines, _tell_cycle_start)
            else:
                step_through(
                    run,
                    devices.mover,
                    plan.lines,
                    machine.feed_mm_min.measure,
                    machine.measurement.overrun_mm,
                )
    finally:
        devices.close()
    console.print(f"{run.statistics.points} points captured to {out}", markup=False)


def _tell_cycle_start(line: object) -> None:
    console.print(
        f"line {getattr(line, 'id', '?')}: units aligned and locked; press cycle start",
        markup=False,
    )


def run_command(
    plan: Annotated[Path, typer.Option(help="Measurement plan JSON (xmalign program --plan-out).")],
    out: Annotated[Path, typer.Option(help="Measurement CSV, appended point by point.")],
    machine: MachineOption = None,
    sim: Annotated[bool, typer.Option("--sim", help="Run on the virtual machine.")] = False,
    config: Annotated[
        Path | None, typer.Option(help="Hardware configuration units.yaml (live run).")
    ] = None,
    resume: Annotated[bool, typer.Option(help="Keep the points already in --out.")] = False,
    seed: Annotated[int, typer.Option(help="With --sim: the virtual machine's seed.")] = 1,
    program: Annotated[
        Path | None, typer.Option(help="With --sim: execute this G-code (default: from the plan).")
    ] = None,
    dialect: Annotated[str | None, typer.Option(help="G-code dialect of --program.")] = None,
) -> None:
    """Drive the units, lock them, step the machine through the plan and capture every point."""
    if sim == (config is not None):
        raise InputError("give either --sim or --config UNITS.yaml")
    machine_model = machine_or_default(machine)
    plan_model = read_plan(plan)
    if resume and not out.exists():
        raise InputError(f"--resume: {out} does not exist yet; run without --resume")
    if sim:
        _run_sim(machine_model, plan_model, out, resume, seed, program, dialect)
    else:
        _run_live(machine_model, plan_model, out, resume, config)


def _results_table(report: object) -> Table:
    from sim.dry_run import DryRunReport

    assert isinstance(report, DryRunReport)
    result = report.identification
    sigma = np.sqrt(np.diag(result.covariance))
    table = Table(title="Dry run against the simulator's truth", title_justify="left")
    for header in ("quantity", "result", "truth / target", "error / margin"):
        table.add_column(header, justify="right")
    for k, axis in enumerate("xyz"):
        table.add_row(
            f"launch {axis} mm",
            f"{result.position_mm[k]:.4f} ± {2 * sigma[k] * 1e3:.0f} µm",
            f"{report.truth_launch2mcs_mm[k]:.4f}",
            f"{report.position_error_um[k]:+.1f} µm",
        )
    table.add_row(
        "launch gamma °",
        f"{math.degrees(result.gamma_rad):.5f} ± {2 * sigma[3] * 1e6:.0f} µrad",
        f"{math.degrees(report.truth_gamma_rad):.5f}",
        f"{report.gamma_error_urad:+.1f} µrad",
    )
    for margin in report.margins:
        table.add_row(
            f"line {margin.line} beam margin",
            f"{margin.measured_straightness_um:.0f} µm, {margin.measured_angle_urad:.0f} µrad",
            "predicted (95 %)",
            f"{margin.predicted_straightness_um:.0f} µm, {margin.predicted_angle_urad:.0f} µrad",
        )
    table.add_row(
        "volumetric error (RMS)",
        f"{report.volumetric_after_um:.2f} µm after",
        f"{report.volumetric_before_um:.1f} µm before",
        "over the measured strokes, rigid motion removed",
    )
    table.add_row(
        "on-machine time",
        f"{report.on_machine_s / 60:.1f} min",
        "≤ 30 min",
        f"identify {report.identification_s / 60:.1f}, align {report.alignment_s / 60:.1f}, "
        f"measure {report.measuring_s / 60:.1f} min",
    )
    return table


def dry_run_command(
    machine: MachineOption = None,
    seed: Annotated[int, typer.Option(help="Seed of the virtual machine and units.")] = 1,
    out: Annotated[Path, typer.Option(help="Folder for every file of the calibration.")] = Path(
        "xmalign-dry-run"
    ),
    dialect: Annotated[
        str | None, typer.Option(help="G-code dialect (default: controller's).")
    ] = None,
    identification_positions: Annotated[int, typer.Option(min=3, help="Alignments.")] = 6,
) -> None:
    """The whole calibration on the virtual machine: identify, program, run, post, comp."""
    from sim.dry_run import STAGES, DryRunOptions, simulate_calibration

    machine_model = machine_or_default(machine)
    options = DryRunOptions(
        seed=seed, identification_positions=identification_positions, dialect=dialect
    )
    with _progress() as progress:
        task = progress.add_task("dry run", total=len(STAGES))
        started: list[str] = []

        def on_stage(name: str) -> None:
            if started:
                progress.advance(task)
            started.append(name)
            progress.update(task, description=f"dry run: {name}")

        report = simulate_calibration(machine_model, out, options, on_stage)
        progress.update(task, completed=len(STAGES), description="dry run: done")
    console.print(_results_table(report))
    for warning in report.identification.warnings + report.plan.warnings:
        console.print(f"warning: {warning}", style="yellow", markup=False)
    console.print(
        f"files in {out}/: " + ", ".join(p.name for p in report.files.values()), markup=False
    )


def register(app: typer.Typer) -> None:
    app.command("run")(run_command)
    app.command("dry-run")(dry_run_command)
