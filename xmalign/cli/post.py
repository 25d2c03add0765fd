"""``xmalign post`` (measurement -> error tables, report) and ``xmalign comp`` (tables -> CNC)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table as RichTable

from xmalign.cli.common import (
    console,
    machine_for_plan,
    machine_or_default,
    output_folder,
    refuse_overwriting,
)
from xmalign.comp import WRITERS, writer
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_files
from xmalign.formats.error_tables import read_error_tables, write_error_tables
from xmalign.formats.measurements import ChannelLimits, check_recorded_plan, load_measurements
from xmalign.formats.plan import read_plan
from xmalign.machine import Machine
from xmalign.post.evaluate import PostResult, Station, post_stations
from xmalign.rigid_body import Chain

MachineOption = Annotated[
    Path | None, typer.Option("--machine", help="Machine YAML (default: the reference machine).")
]


def _progress() -> Progress:
    return Progress(
        SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=console
    )


def _summary(result: PostResult) -> RichTable:
    summary = RichTable(title="Squareness and ISO 230-2 (um, urad)")
    summary.add_column("item")
    summary.add_column("value", justify="right")
    summary.add_column("U95 / detail", justify="right")
    for name, (value, u95) in result.fit.tables.squareness.items():
        summary.add_row(name, f"{value * 1e6:.2f} urad", f"{u95 * 1e6:.2f}")
    for figures in result.positioning:
        both = math.isfinite(figures.E)
        a, e, r = (
            (figures.A, figures.E, figures.R)
            if both
            else (figures.A_up, figures.E_up, figures.R_up)
        )
        summary.add_row(
            f"line {figures.line_id}", f"A {a:.2f} um", f"E {e:.2f}  R {r:.2f}  B {figures.B:.2f}"
        )
    return summary


def _stations(
    plans: list[Path], data: list[Path], machine: Path | None
) -> tuple[Machine, list[Station]]:
    """The machine and one station per ``--plan``/``--data`` pair, in the order given.

    Every plan must be for the machine given; every data file recorded for its plan.
    """
    if len(plans) != len(data):
        raise InputError(
            f"post: {len(plans)} --plan but {len(data)} --data; give one --plan/--data pair per"
            " launch-unit station, in the same order"
        )
    read = [(read_plan(plan_path), plan_path) for plan_path in plans]
    machine_ = [machine_for_plan(machine, plan_, plan_path) for plan_, plan_path in read][0]
    limits = ChannelLimits.of_ranges(**machine_.interferometer.model_dump())
    stations = []
    for (plan_, _), path in zip(read, data, strict=True):
        recorded = load_measurements(path, limits)
        check_recorded_plan(recorded, plan_, check_points=False)
        stations.append(Station(plan_, recorded.rows, str(path)))
    return machine_, stations


def post(
    plan: Annotated[
        list[Path],
        typer.Option(help="Measurement plan (xmalign.plan/1 JSON); once per station, in order."),
    ],
    data: Annotated[
        list[Path],
        typer.Option(help="Measurement CSV written by xmalign run; once per station, in order."),
    ],
    out: Annotated[Path, typer.Option(help="Error-table CSV to write.")],
    machine: MachineOption = None,
    report: Annotated[Path | None, typer.Option(help="Also write an HTML report here.")] = None,
) -> None:
    """Solve the 21 geometric errors (with U95) and the ISO 230-2 figures from the lines.

    Repeat --plan and --data for a second launch-unit station: one set of error
    tables is fitted to all lines, each line with its own setup terms.
    """
    refuse_overwriting(
        {"--plan": plan, "--data": data, "--machine": machine},
        {"--out": out, "--report": report},
    )
    with _progress() as progress:
        task = progress.add_task("reading plans and measurements", total=None)
        machine_, stations = _stations(plan, data, machine)
        points = sum(len(station.rows) for station in stations)
        progress.update(task, description=f"fitting {points} points")
        result = post_stations(machine_, stations)
        write_error_tables(out, result.fit.tables)
        if report is not None:
            progress.update(task, description="drawing the report")
            # imported here: matplotlib is only loaded when a report is asked for
            from xmalign.report import write_report

            write_report(report, machine_, result, machine_.controller)
    console.print(_summary(result))
    for warning in result.warnings:
        console.print(f"[yellow]warning:[/yellow] {warning}")
    console.print(
        f"sigma0 {result.fit.sigma0:.2f}; wrote {out}" + (f" and {report}" if report else "")
    )


def comp(
    errors: Annotated[Path, typer.Option(help="Error-table CSV written by xmalign post.")],
    out: Annotated[Path, typer.Option(help="Directory for the controller's files.")],
    machine: MachineOption = None,
    controller: Annotated[
        str | None,
        typer.Option(help=f"One of {', '.join(WRITERS)} (default: the machine file's)."),
    ] = None,
) -> None:
    """Write compensation tables for a CNC controller from an error-table CSV."""
    machine_ = machine_or_default(machine)
    module = writer(controller or machine_.controller)
    files = module.render(read_error_tables(errors), Chain.parse(machine_.chain))
    output_folder(out, "--out")
    refuse_overwriting(
        {"--errors": errors, "--machine": machine}, {"--out": [out / name for name in files]}
    )
    atomic_write_files({out / name: text.encode("utf-8") for name, text in files.items()})
    console.print(f"{module.NAME}: wrote {', '.join(sorted(files))} in {out}")


def register(app: typer.Typer) -> None:
    app.command()(post)
    app.command()(comp)
