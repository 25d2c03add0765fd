"""``xmalign post`` (measurement -> error tables, report) and ``xmalign comp`` (tables -> CNC)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import (
    BarColumn,
    Progress,
    SpinnerColumn,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table as RichTable

from xmalign.cli.common import (
    ForceOption,
    console,
    error_console,
    machine_or_default,
    named_by_options,
    warn,
)
from xmalign.cli.instruments import check_inputs, count_readings, read_instruments
from xmalign.comp import WRITERS, fit_for
from xmalign.errors import InputError, MachineKeyError
from xmalign.formats.error_tables import read_error_tables
from xmalign.formats.plan import Plan, read_plan
from xmalign.formats.provenance import FileSource
from xmalign.instrument_text import instrument_lines, instrument_notes
from xmalign.machine import Machine, default_machine_path
from xmalign.post.evaluate import PostResult, Station
from xmalign.post.instruments import MAX_KNOT_SPACING_MM, MIN_KNOT_SPACING_MM
from xmalign.rigid_body import ErrorTables
from xmalign.steps import as_left_step, comp_step, post_step

MachineOption = Annotated[
    Path | None, typer.Option("--machine", help="Machine YAML (default: the reference machine).")
]


def _progress() -> Progress:
    return Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        BarColumn(),
        TaskProgressColumn(),
        TimeElapsedColumn(),
        console=console,
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


def _stations(plans: list[Path], data: list[Path]) -> list[tuple[Plan, Path]]:
    """One plan/data pair per station, in the order given (the step checks each plan
    against the machine and each data file against its plan)."""
    if len(plans) != len(data):
        raise InputError(
            f"post: {len(plans)} --plan but {len(data)} --data; give one --plan/--data pair per"
            " launch-unit station, in the same order"
        )
    return [(read_plan(plan_path), path) for plan_path, path in zip(plans, data, strict=True)]


#: What ``xmalign post`` calls :func:`~xmalign.steps.post_step`'s files.
POST_OPTIONS = {
    "errors_path": "--out",
    "measurements": "--data",
    "plan": "--plan",
    "machine": "--machine",
    "tracker": "--tracker",
    "tracer": "--tracer",
    "more_files": "--report",
}


def post(
    out: Annotated[Path, typer.Option(help="Error-table CSV to write.")],
    plan: Annotated[
        list[Path] | None,
        typer.Option(help="Measurement plan (xmalign.plan/1 JSON); once per station, in order."),
    ] = None,
    data: Annotated[
        list[Path] | None,
        typer.Option(help="Measurement CSV written by xmalign run; once per station, in order."),
    ] = None,
    tracker: Annotated[
        list[Path] | None,
        typer.Option(help="Laser-tracker points (tracker-points/1 CSV); repeatable."),
    ] = None,
    tracer: Annotated[
        list[Path] | None,
        typer.Option(help="Laser-tracer lengths (tracer-lengths/1 CSV); repeatable."),
    ] = None,
    machine: MachineOption = None,
    report: Annotated[
        Path | None, typer.Option(help="Also write the calibration record here (.html or .pdf).")
    ] = None,
    operator: Annotated[str, typer.Option(help="Who calibrated, for the record.")] = "",
    units: Annotated[
        Path | None,
        typer.Option(help="units.yaml of the run: instrument and sensor serials for the record."),
    ] = None,
    vdi3441: Annotated[
        bool, typer.Option("--vdi3441", help="Also give the VDI/DGQ 3441 figures in the record.")
    ] = False,
    verify_data: Annotated[
        Path | None,
        typer.Option(
            help="Measurement CSV of a verification run after compensation (as left), "
            "compared with the calibration (as found)."
        ),
    ] = None,
    verify_plan: Annotated[
        Path | None,
        typer.Option(help="Plan of the verification run (default: the first --plan)."),
    ] = None,
    verify_controller: Annotated[
        str | None,
        typer.Option(
            help="Whose tables were loaded for the verification run, fitted by xmalign comp"
            " to these errors (default: the machine file's controller)."
        ),
    ] = None,
    knot_spacing_mm: Annotated[
        float | None,
        typer.Option(
            min=MIN_KNOT_SPACING_MM,
            max=MAX_KNOT_SPACING_MM,
            help="Compensation-point spacing where only --tracker/--tracer measured, mm"
            " (default: chosen by cross-validation); with lines, of the points beyond them"
            " (default 400).",
        ),
    ] = None,
    force: ForceOption = False,
) -> None:
    """Solve the 21 geometric errors (with U95) and the ISO 230-2 figures from the lines.

    Where the measurement has environment columns, the linear readings are first
    compensated for the air's refractive index, the dead path and the material
    temperature (normalised to 20 °C).

    Repeat --plan and --data for a second launch-unit station: one set of error
    tables is fitted to all lines, each line with its own setup terms.

    With --verify-data, the measurement made after loading the compensation is
    posted on its own and compared with the calibration (as found / as left).

    --tracker and --tracer files (each repeatable) join the same fit, with or
    without lines: every tracker station brings its pose, every tracer place its
    pivot and constants, each reading weighted with its instrument's uncertainty.
    """
    plan, data, tracker, tracer = plan or [], data or [], tracker or [], tracer or []
    check_inputs(plan, tracker, tracer, verify_data is not None and verify_plan is None)
    if knot_spacing_mm is not None and not tracker and not tracer:
        raise InputError(
            "--knot-spacing-mm is for --tracker/--tracer readings; lines set their own"
            " compensation points (measurement.target_spacing_mm)"
        )
    if verify_data is None and (verify_plan or verify_controller):
        option = "--verify-plan" if verify_plan else "--verify-controller"
        raise InputError(f"{option} needs --verify-data (the verification measurement)")
    caller = named_by_options(
        POST_OPTIONS,
        read={"--units": units, "--verify-plan": verify_plan, "--verify-data": verify_data},
        written={"--report": report},
    )
    instruments = _instrument_serials(units) if units is not None else {}
    with _progress() as progress:
        task = progress.add_task("reading plans and measurements", total=None)
        machine_, stations = machine_or_default(machine), _stations(plan, data)
        readings = read_instruments(tracker, tracer, knot_spacing_mm)
        verification: list[PostResult] = []

        def on_fit(read: list[Station]) -> None:
            if report is not None:  # after the step's checks of --out and --report
                from xmalign.report import check_report_name

                check_report_name(report)
            points = sum(len(station.rows) for station in read)
            extra = count_readings(readings)
            fitting = ([f"{points} points"] if read else []) + ([extra] if extra else [])
            progress.update(task, description=f"fitting {', '.join(fitting)}")

        def more_files(result: PostResult) -> dict[Path, bytes]:
            if verify_data is not None:
                progress.update(task, description="fitting the verification run")
                controller = verify_controller or machine_.controller
                applied = fit_for(machine_, result.fit.tables, controller)
                verification.append(
                    _post_verification(verify_plan or plan[0], verify_data, machine_, applied.mean)
                )
            if report is None:
                return {}
            progress.update(task, description="drawing the report")
            # imported here: matplotlib is only loaded when a report is asked for
            from xmalign.report import RecordInfo, report_bytes

            info = RecordInfo.of_compensation(
                result.compensation,
                operator=operator,
                instruments=instruments,
                vdi3441=vdi3441,
                verification=verification[0] if verification else None,
            )
            return {report: report_bytes(report, machine_, result, machine_.controller, info)}

        def fitting(done: int, total: int, what: str) -> None:
            progress.update(
                task,
                description=f"fitting the instruments' rows, {what}",
                completed=done,
                total=total,
            )

        # the tables and the report together, or neither (a failed report leaves no tables)
        posted = post_step(
            machine_,
            stations,
            out,
            readings,
            _instrument_inputs(tracker, tracer),
            on_fit=on_fit,
            more_files=more_files,
            replace=force,
            caller=caller,
            progress=fitting,
        )
        result = posted.post
    console.print(_summary(result))
    if result.instruments is not None:
        for note in instrument_lines(result.instruments) + instrument_notes(result.instruments):
            console.print(note, markup=False, soft_wrap=True)
    if verification:
        console.print(_as_left(machine_, result, verification[0]))
    for note in dict.fromkeys(result.notes):
        console.print(note, markup=False, soft_wrap=True)
    drift = [check for c in result.compensation for check in c.drift]
    if drift:
        console.print(
            "drift at the first target: "
            + ", ".join(f"{check.line_id} {check.drift_um:+.2f} um" for check in drift),
            markup=False,
            soft_wrap=True,
        )
    for warning in posted.warnings + result.warnings:
        console.print(f"[yellow]warning:[/yellow] {warning}", soft_wrap=True)
    console.print(
        f"sigma0 {result.fit.sigma0:.2f}; wrote {out}" + (f" and {report}" if report else "")
    )


def _instrument_inputs(tracker: list[Path], tracer: list[Path]) -> list[FileSource]:
    """The tracker and tracer files the tables were made from."""
    return [FileSource.of("tracker", p) for p in tracker] + [
        FileSource.of("tracer", p) for p in tracer
    ]


def _post_verification(
    plan: Path, data: Path, machine: Machine, applied: ErrorTables
) -> PostResult:
    """The verification run posted on its own, with the tables ``applied`` during it."""
    return as_left_step(machine, read_plan(plan), data, applied)


def _as_left(machine: Machine, result: PostResult, verification: PostResult) -> RichTable:
    from xmalign.report import as_left_table

    table = as_left_table(machine, result, verification)
    shown = RichTable(title=table.title)
    for number, name in enumerate(table.header):
        shown.add_column(name, justify="right" if number > 1 else "left")
    for row in table.rows:
        shown.add_row(*row)
    return shown


def _instrument_serials(units: Path) -> dict[str, str]:
    """Instrument and sensor serial numbers of a units.yaml."""
    from firmware_iface.config import load_units_config
    from firmware_iface.weather_station import record_serials

    config = load_units_config(units)
    return record_serials(config.instruments, config.environment)


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
    force: ForceOption = False,
) -> None:
    """Fit the controller's compensation model over the whole travel and write its tables."""
    machine_ = machine_or_default(machine)
    name = controller or machine_.controller
    tables = read_error_tables(errors)
    caller = named_by_options(COMP_OPTIONS)
    if name == "linuxcnc-volumetric":
        from xmalign.cli.linuxcnc_volumetric import volumetric_comp

        volumetric_comp(tables, machine_, ini, out, force, caller)
        return
    try:
        result = comp_step(machine_, tables, out, name, ini, force, caller, warn)
    except MachineKeyError as error:
        raise error.in_file(str(machine or default_machine_path())) from error
    if result.merged_ini is not None:
        console.print(
            f"joints {' '.join(result.joints)}; start LinuxCNC with {result.merged_ini}",
            highlight=False,
        )
    fit = result.fit
    console.print(
        f"{name}: wrote {', '.join(sorted(result.files))} in {out}\n"
        f"predicted volumetric error over the travel (RMS, both directions): before"
        f" {fit.before_um:.2f} um, after these tables {fit.after_um:.2f} um"
        f" ({100 * fit.removed_share:.0f} % removed; {fit.grid_points} grid points)",
        highlight=False,
    )
    if fit.after_optional_um is not None:
        console.print(
            f"with the optional tables too: {fit.after_optional_um:.2f} um"
            f" ({100 * (1 - fit.after_optional_um / fit.before_um):.0f} % removed)",
            highlight=False,
        )
    for line in result.loading.lines():
        console.print(line, highlight=False)
    if not fit.converged:
        error_console.print(
            f"[yellow]warning:[/] {name}: some table values were left undetermined by the fit"
            " grid; check the tables before loading them",
            highlight=False,
        )
    if not fit.removes_enough:
        error_console.print(
            f"[yellow]warning:[/] {name}\x27s tables remove less than half of the predicted error"
            f" ({fit.after_um:.2f} of {fit.before_um:.2f} um left)",
            highlight=False,
        )


#: What ``xmalign comp`` calls :func:`~xmalign.steps.comp_step`'s files.
COMP_OPTIONS = {"out_dir": "--out", "tables": "--errors", "machine": "--machine", "ini": "--ini"}


def register(app: typer.Typer) -> None:
    app.command()(post)
    app.command()(comp)
