"""``xmalign post`` (measurement -> error tables, report) and ``xmalign comp`` (tables -> CNC)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table as RichTable

from xmalign.cli.common import console, machine_or_default
from xmalign.comp import WRITERS, writer
from xmalign.formats.common import atomic_write_text
from xmalign.formats.error_tables import read_error_tables, write_error_tables
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan
from xmalign.post.evaluate import PostResult, post_process
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


def post(
    plan: Annotated[Path, typer.Option(help="Measurement plan (xmalign.plan/1 JSON).")],
    data: Annotated[Path, typer.Option(help="Measurement CSV written by xmalign run.")],
    out: Annotated[Path, typer.Option(help="Error-table CSV to write.")],
    machine: MachineOption = None,
    report: Annotated[Path | None, typer.Option(help="Also write an HTML report here.")] = None,
) -> None:
    """Solve the 21 geometric errors (with U95) and the ISO 230-2 figures from six lines."""
    machine_ = machine_or_default(machine)
    with _progress() as progress:
        task = progress.add_task("reading plan and measurements", total=None)
        plan_ = read_plan(plan)
        rows = read_measurements(data)
        progress.update(task, description=f"fitting {len(rows)} points")
        result = post_process(machine_, plan_, rows, str(data))
        write_error_tables(out, result.fit.tables)
        if report is not None:
            progress.update(task, description="drawing the report")
            # imported here: matplotlib is only loaded when a report is asked for
            from xmalign.report import write_report

            write_report(report, machine_, result, machine_.controller)
    console.print(_summary(result))
    console.print(
        f"sigma0 {result.fit.sigma0:.2f}; wrote {out}" + (f" and {report}" if report else "")
    )


def comp(
    errors: Annotated[Path, typer.Option(help="Error-table CSV written by xmalign post.")],
    out: Annotated[Path, typer.Option(help="Directory for the controller's files.")],
    machine: MachineOption = None,
    controller: Annotated[
        str | None,
        typer.Option(
            help=f"One of {', '.join(WRITERS)}, linuxcnc-volumetric (default: the machine file's)."
        ),
    ] = None,
    ini: Annotated[
        Path | None, typer.Option(help="linuxcnc-volumetric: the machine's LinuxCNC INI file.")
    ] = None,
) -> None:
    """Write compensation tables for a CNC controller from an error-table CSV."""
    machine_ = machine_or_default(machine)
    if controller == "linuxcnc-volumetric":
        from xmalign.cli.linuxcnc_volumetric import write_volumetric

        write_volumetric(read_error_tables(errors), machine_, ini, out)
        return
    module = writer(controller or machine_.controller)
    files = module.render(read_error_tables(errors), Chain.parse(machine_.chain))
    for name, text in files.items():
        atomic_write_text(out / name, text)
    console.print(f"{module.NAME}: wrote {', '.join(sorted(files))} in {out}")


def register(app: typer.Typer) -> None:
    app.command()(post)
    app.command()(comp)
