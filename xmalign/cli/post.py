"""``xmalign post`` (measurement -> error tables, report) and ``xmalign comp`` (tables -> CNC)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table as RichTable

from xmalign.cli.common import console, error_console, machine_or_default
from xmalign.comp import WRITERS, Compensation, compensate, linuxcnc
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text
from xmalign.formats.error_tables import read_error_tables, write_error_tables
from xmalign.formats.measurements import read_measurements
from xmalign.formats.plan import read_plan
from xmalign.machine import Machine
from xmalign.post.evaluate import PostResult, post_process

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
        Path | None,
        typer.Option(
            help="LinuxCNC: the machine's INI; writes a merged copy (linuxcnc-volumetric: needed)."
        ),
    ] = None,
) -> None:
    """Fit the controller's compensation model over the whole travel and write its tables."""
    machine_ = machine_or_default(machine)
    name = controller or machine_.controller
    if name == "linuxcnc-volumetric":
        from xmalign.cli.linuxcnc_volumetric import write_volumetric

        write_volumetric(read_error_tables(errors), machine_, ini, out)
        return
    result = compensate(machine_, read_error_tables(errors), name)
    files = dict(result.files)
    if ini is not None:
        files.update(_linuxcnc_ini(name, machine_, result, ini, out))
    for file_name, text in files.items():
        atomic_write_text(out / file_name, text)
    fit = result.fit
    console.print(
        f"{name}: wrote {', '.join(sorted(files))} in {out}\n"
        f"predicted volumetric error over the travel (RMS, both directions): before"
        f" {fit.before_um:.2f} um, after these tables {fit.after_um:.2f} um"
        f" ({100 * fit.removed_share:.0f} % removed; {fit.grid_points} grid points)"
    )
    if not fit.removes_enough:
        error_console.print(
            f"[yellow]warning:[/] {name}'s tables remove less than half of the predicted error"
            f" ({fit.after_um:.2f} of {fit.before_um:.2f} um left)",
            highlight=False,
        )


def _linuxcnc_ini(name: str, machine: Machine, result: Compensation, ini: Path, out: Path) -> dict:
    """The LinuxCNC comp files for the INI's joints and the merged INI (file name -> text)."""
    if name != linuxcnc.NAME:
        raise InputError(f"--ini is for the linuxcnc controller, not '{name}'")
    try:
        text = ini.read_text(encoding="utf-8")
    except OSError as error:
        raise InputError(f"{ini}: cannot read ({error.strerror})") from error
    joints = linuxcnc.resolve_joints(machine, text.splitlines(), str(ini))
    files = linuxcnc.render(result.fit, machine, joints)
    merged = f"{ini.stem}-xmalign{ini.suffix}"
    files[merged] = linuxcnc.merge_ini(text, joints, out, str(ini))
    for joint in linuxcnc.backlash_joints(text, joints):
        error_console.print(
            f"[yellow]warning:[/] {ini}: [JOINT_{joint}] BACKLASH is set; the COMP_FILE's"
            " reverse column already carries the reversal",
            highlight=False,
        )
    console.print(f"joints {' '.join(joints)}; start LinuxCNC with {out / merged}")
    return files


def register(app: typer.Typer) -> None:
    app.command()(post)
    app.command()(comp)
