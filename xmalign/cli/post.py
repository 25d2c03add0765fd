"""``xmalign post`` (measurement -> error tables, report) and ``xmalign comp`` (tables -> CNC)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from functools import partial
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
    machine_for_plan,
    machine_or_default,
    output_folder,
)
from xmalign.cli.instruments import check_inputs, count_readings, read_instruments
from xmalign.comp import WRITERS, Compensation, fit_for, linuxcnc
from xmalign.errors import InputError, MachineKeyError
from xmalign.formats.common import (
    PathsOf,
    read_text,
    refuse_overwriting,
    refuse_replacing,
    same_file,
)
from xmalign.formats.error_tables import read_error_tables
from xmalign.formats.plan import Plan, read_plan
from xmalign.formats.provenance import FileSource
from xmalign.machine import Machine, default_machine_path
from xmalign.post.evaluate import PostResult, Station
from xmalign.post.instruments import instrument_lines, instrument_notes
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


def _stations(
    plans: list[Path], data: list[Path], machine: Path | None
) -> tuple[Machine, list[tuple[Plan, Path]]]:
    """The machine and one plan/data pair per station, in the order given.

    Every plan must be for the machine given (the step checks each data file
    against its plan).
    """
    if len(plans) != len(data):
        raise InputError(
            f"post: {len(plans)} --plan but {len(data)} --data; give one --plan/--data pair per"
            " launch-unit station, in the same order"
        )
    for later, path in enumerate(data[1:], start=1):
        first = next(k for k, other in enumerate(data) if same_file(path, other))
        if first < later:
            raise InputError(
                f"{path}: --data is given for station {first + 1} and again for station"
                f" {later + 1}; its points would count twice (give each station's data once)"
            )
    read = [(read_plan(plan_path), plan_path) for plan_path in plans]
    if not read:
        return machine_or_default(machine), []
    machine_ = [machine_for_plan(machine, plan_, plan_path) for plan_, plan_path in read][0]
    return machine_, [(plan_, path) for (plan_, _), path in zip(read, data, strict=True)]


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
    if verify_data is None and (verify_plan or verify_controller):
        option = "--verify-plan" if verify_plan else "--verify-controller"
        raise InputError(f"{option} needs --verify-data (the verification measurement)")
    refuse_overwriting(
        {
            "--plan": plan,
            "--data": data,
            "--machine": machine,
            "--units": units,
            "--verify-plan": verify_plan,
            "--verify-data": verify_data,
            "--tracker": tracker,
            "--tracer": tracer,
        },
        {"--out": out, "--report": report},
    )
    if report is not None:
        from xmalign.report import check_report_name

        check_report_name(report)
    instruments = _instrument_serials(units) if units is not None else {}
    with _progress() as progress:
        task = progress.add_task("reading plans and measurements", total=None)
        machine_, stations = _stations(plan, data, machine)
        readings = read_instruments(tracker, tracer)
        verification: list[PostResult] = []

        def on_fit(read: list[Station]) -> None:
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
                    _post_verification(verify_plan or plan[0], verify_data, machine, applied.mean)
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
        result = post_step(
            machine_,
            stations,
            out,
            machine,
            readings,
            _instrument_inputs(tracker, tracer),
            on_fit=on_fit,
            more_files=more_files,
            progress=fitting,
        ).post
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
    for warning in result.warnings:
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
    plan: Path, data: Path, machine: Path | None, applied: ErrorTables
) -> PostResult:
    """The verification run posted on its own, with the tables ``applied`` during it."""
    plan_ = read_plan(plan)
    return as_left_step(machine_for_plan(machine, plan_, plan), plan_, data, applied)


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
    tables.check_within_travel(machine_.travel_min_mm, machine_.travel_max_mm, machine_.name)
    machine_notes = tables.check_machine(machine_)  # another chain or travel: refused here
    inputs = {"--errors": errors, "--machine": machine, "--ini": ini}
    if name == "linuxcnc-volumetric":
        from xmalign.cli.linuxcnc_volumetric import volumetric_comp

        volumetric_comp(tables, machine_, ini, out, partial(_check_outputs, inputs, force=force))
        _warn(machine_notes)
        return
    output_folder(out, "--out")
    try:
        result = comp_step(
            machine_,
            tables,
            out,
            name,
            more_files=None
            if ini is None
            else partial(_linuxcnc_ini, name, machine_, ini=ini, out=out),
            check_outputs=partial(_check_outputs, inputs, force=force),
        )
    except MachineKeyError as error:
        raise error.in_file(str(machine or default_machine_path())) from error
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
    _warn(machine_notes)
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


def _warn(warnings: list[str]) -> None:
    for warning in warnings:
        error_console.print(f"[yellow]warning:[/] {warning}", highlight=False)


def _check_outputs(inputs: Mapping[str, PathsOf], paths: list[Path], force: bool) -> None:
    """A controller's files never replace an input, nor (without --force) a file in --out."""
    refuse_overwriting(inputs, {"--out": paths})
    refuse_replacing({"--out": paths}, force)


def _linuxcnc_ini(name: str, machine: Machine, result: Compensation, ini: Path, out: Path) -> dict:
    """The LinuxCNC comp files for the INI\x27s joints and the merged INI (file name -> text)."""
    if name != linuxcnc.NAME:
        raise InputError(f"--ini is for the linuxcnc controller, not \x27{name}\x27")
    text = read_text(ini)
    joints = linuxcnc.resolve_joints(machine, text.splitlines(), str(ini))
    files = linuxcnc.render(result.fit, machine, joints)
    merged = f"{ini.stem}-xmalign{ini.suffix}"
    files[merged] = linuxcnc.merge_ini(text, joints, out, str(ini), ini.resolve().parent)
    for joint in linuxcnc.backlash_joints(text, joints):
        error_console.print(
            f"[yellow]warning:[/] {ini}: [JOINT_{joint}] BACKLASH is set; the COMP_FILE\x27s"
            " reverse column already carries the reversal",
            highlight=False,
        )
    console.print(f"joints {' '.join(joints)}; start LinuxCNC with {out / merged}")
    return files


def register(app: typer.Typer) -> None:
    app.command()(post)
    app.command()(comp)
