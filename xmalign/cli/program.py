"""``xmalign program`` and ``xmalign plan-identify``: plan the measurement, write G-code."""

from __future__ import annotations

import sys
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

from trajectories.gcode import DIALECTS
from trajectories.gcode.machine_time import MachineTime
from trajectories.gcode.program import estimate_machine_time
from trajectories.identification_design import IdentificationDesign
from trajectories.lines import LINE_IDS
from trajectories.planner import MeasurementPlan
from trajectories.stations import propose_second_station
from xmalign.cli.common import (
    ForceOption,
    check_positions,
    console,
    error_console,
    machine_or_default,
)
from xmalign.cli.instruments import (
    InstrumentRequest,
    check_instrument_options,
    program_instrument,
)
from xmalign.errors import GeometryError, InputError
from xmalign.formats.common import PathsOf, refuse_overwriting, refuse_replacing
from xmalign.formats.pose import read_pose
from xmalign.machine import Machine
from xmalign.steps import design_step, program_step

MachineOption = Annotated[
    Path | None, typer.Option("--machine", help="Machine YAML (default: the reference machine).")
]


def _plan_table(measurement: MeasurementPlan) -> Table:
    table = Table(title="Measuring lines, 95 % beam envelope / limit")
    for column in ("line", "mm", "%", "n", "launch deg", "receiver deg", "um", "urad", ""):
        table.add_column(column, justify="left" if column in ("line", "") else "right")
    for planned in measurement.lines:
        line, envelope = planned.line, planned.envelope
        table.add_row(
            line.id,
            f"{planned.layout.length_mm:.0f}",
            f"{100 * planned.layout.coverage:.0f}",
            str(len(line.targets_mm)),
            " ".join(f"{v:.2f}" for v in np.degrees(line.launch_rad)),
            " ".join(f"{v:.2f}" for v in np.degrees(line.receiver_rad[:2])),
            f"{np.max(envelope.lateral_95_um):.0f}/{envelope.straightness_limit_um:.0f}",
            f"{envelope.angle_95_urad:.0f}/{envelope.angle_limit_urad:.0f}",
            "ok" if envelope.within else "[yellow]warn[/]",
        )
    return table


#: Where ``xmalign identify --out`` is usually pointed, and ``program`` looks without --pose.
DEFAULT_POSE = Path("pose.json")


def program(
    pose: Annotated[
        Path,
        typer.Option(
            "--pose", help="Launch pose from xmalign identify (default: pose.json in this folder)."
        ),
    ] = DEFAULT_POSE,
    machine: MachineOption = None,
    plan_out: Annotated[
        Path | None, typer.Option("--plan-out", help="Write the measurement plan (JSON).")
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="Write the G-code here instead of stdout.")
    ] = None,
    dialect: Annotated[
        str | None,
        typer.Option(help=f"G-code dialect ({', '.join(DIALECTS)}); default from the controller."),
    ] = None,
    strict: Annotated[
        bool, typer.Option(help="Refuse, instead of warn, when an envelope leaves the range.")
    ] = False,
    lines: Annotated[
        str | None,
        typer.Option(help="Comma-separated lines to plan, e.g. Z,YZ,XZ (default: all six)."),
    ] = None,
    instrument: Annotated[
        str | None,
        typer.Option(help="Plan for a laser 'tracker' or 'tracer' instead (no --pose needed)."),
    ] = None,
    on_the_fly: Annotated[
        bool, typer.Option("--on-the-fly", help="Tracker: paths on the fly, not points.")
    ] = False,
    places: Annotated[int | None, typer.Option(help="Tracer: how many places (default 4).")] = None,
    simultaneous: Annotated[
        bool,
        typer.Option(
            "--simultaneous",
            help="Tracer: a tracer at every place, all following the SMR in the same run.",
        ),
    ] = False,
    points_out: Annotated[
        Path | None,
        typer.Option(help="With --instrument: the point list for the instrument's software."),
    ] = None,
    force: ForceOption = False,
) -> None:
    """Plan the 3 axis lines and 3 face diagonals through the launch unit; write G-code.

    With all six lines it also proposes a second launch-unit station whose lines
    complete the strokes (docs/post.md); plan that station with --lines.

    With --instrument tracker (--on-the-fly) or tracer (--places N, --simultaneous):
    the points or paths of a laser-tracker or laser-tracer calibration over the
    whole travel, with the SMR positions of the machine file (or three proposed).
    """
    check_instrument_options(instrument, on_the_fly, places, simultaneous)
    if instrument is not None:
        refuse_replacing({"--out": out, "--points-out": points_out}, force)
        request = InstrumentRequest(
            instrument, on_the_fly, places or 4, out, points_out, dialect, simultaneous
        )
        program_instrument(machine_or_default(machine), request)
        return
    if not pose.exists():
        raise InputError(
            f"{pose}: cannot read: no such file; identify the launch unit first"
            f" (xmalign identify ... --out {pose}) or give --pose POSE.json"
        )
    machine_model = machine_or_default(machine)
    line_ids = _line_ids(lines)
    launch_pose = read_pose(pose)
    programmed = program_step(
        machine_model,
        launch_pose,
        plan_out,
        out,
        dialect,
        pose_path=pose,
        line_ids=line_ids,
        machine_path=machine,
        write_program_file=out is not None,
        check_plan=partial(
            _show_plan, machine_model, launch_pose.position_mm, line_ids == LINE_IDS, strict=strict
        ),
        check_outputs=partial(
            _check_outputs, {"--pose": pose, "--machine": machine}, plan_out, force=force
        ),
    )
    error_console.print(
        _machine_time_text(estimate_machine_time(programmed.plan, machine_model)),
        highlight=False,
    )
    if out is None:
        sys.stdout.write(programmed.program)


def _show_plan(
    machine: Machine,
    launch_mm: np.ndarray,
    all_lines: bool,
    measurement: MeasurementPlan,
    strict: bool,
) -> None:
    """The planned lines, the second station (``all_lines``), the notes and the warnings
    (--strict: refused)."""
    error_console.print(_plan_table(measurement))
    if all_lines:
        error_console.print(_second_station(machine, launch_mm), highlight=False)
    for planned in measurement.lines:
        if "note" in planned.line.extra:
            error_console.print(f"note: line {planned.line.id}: {planned.line.extra['note']}")
    if measurement.warnings and strict:
        raise GeometryError(measurement.warnings[0])
    for warning in measurement.warnings:
        error_console.print(f"[yellow]warning:[/] {warning}", highlight=False)


def _check_outputs(
    inputs: Mapping[str, PathsOf], plan_out: Path | None, paths: list[Path], force: bool
) -> None:
    """The plan (--plan-out) and the program (--out) never replace an input, nor (without
    --force) a file."""
    outputs = {
        "--plan-out": [path for path in paths if path == plan_out],
        "--out": [path for path in paths if path != plan_out],
    }
    refuse_overwriting(inputs, outputs)
    refuse_replacing(outputs, force)


def _machine_time_text(time: MachineTime) -> str:
    acceleration = (
        "with the machine file's acceleration"
        if time.with_acceleration
        else "feeds reached at once (no cnc.acceleration_mm_s2 in the machine file)"
    )
    return (
        f"machine time of the program: {time.total_s / 60:.1f} min (moving"
        f" {time.moving_s / 60:.1f} min, {time.dwells} dwells {time.dwell_s / 60:.1f} min;"
        f" {acceleration}; setting the units at each line's stop not counted)"
    )


def _line_ids(text: str | None) -> tuple[str, ...]:
    if text is None:
        return LINE_IDS
    chosen = tuple(part.strip().upper() for part in text.split(",") if part.strip())
    unknown = [line for line in chosen if line not in LINE_IDS]
    if unknown or not chosen or len(set(chosen)) != len(chosen):
        raise InputError(
            f"--lines '{text}': give distinct lines out of {', '.join(LINE_IDS)}, comma-separated"
        )
    return chosen


def _second_station(machine: Machine, first_mm: np.ndarray) -> str:
    proposal = propose_second_station(machine, first_mm)
    where = ", ".join(f"{v:.0f}" for v in proposal.position_mm)
    covered = ", ".join(f"{axis} {100 * v:.0f} %" for axis, v in proposal.coverage.items())
    return (
        f"second station (optional, for tables over the whole travel): launch cp at [{where}] mm;"
        f" set launch_unit.position_mm to it, identify again and program"
        f" --lines {','.join(proposal.line_ids)}; both stations together cover {covered} of"
        " the strokes"
    )


def _design_table(design: IdentificationDesign) -> Table:
    table = Table(title="Identification positions (CNC tool point)")
    for column in ("#", "X mm", "Y mm", "Z mm"):
        table.add_column(column, justify="right")
    for index, point in enumerate(design.machine_mm, start=1):
        table.add_row(str(index), *(f"{v:.1f}" for v in point))
    return table


def plan_identify(
    machine: MachineOption = None,
    count: Annotated[int, typer.Option("--count", help="Number of alignments.")] = 6,
    out: Annotated[
        Path | None, typer.Option("--out", help="Write the positions and predictions (JSON).")
    ] = None,
) -> None:
    """Propose machine positions for identification that minimise the pose uncertainty."""
    check_positions(count, "--count")
    refuse_overwriting({"--machine": machine}, {"--out": out})
    machine_model = machine_or_default(machine)
    with error_console.status("optimising the identification positions"):
        design = design_step(machine_model, count, out, machine)
    std = design.std
    console.print(_design_table(design))
    for warning in design.warnings:
        error_console.print(f"warning: {warning}")
    console.print(
        f"predicted standard uncertainty: x {1e3 * std[0]:.1f} um, y {1e3 * std[1]:.1f} um,"
        f" z {1e3 * std[2]:.1f} um, gamma {1e6 * std[3]:.1f} urad"
    )


def register(app: typer.Typer) -> None:
    app.command("program")(program)
    app.command("plan-identify")(plan_identify)
