"""``xmalign post --tracker/--tracer`` and ``xmalign program --instrument``."""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table as RichTable

from trajectories.gcode import make_dialect, resolve_dialect
from trajectories.instruments import (
    machine_time_note,
    plan_instrument,
    point_list_csv,
    write_instrument_program,
)
from xmalign.cli.common import console, error_console, machine_or_default, output_folder
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text, refuse_overwriting
from xmalign.formats.instrument_checks import UNITS_MM
from xmalign.formats.instruments import (
    read_tracer_lengths,
    read_tracker_points,
    write_tracker_points,
)
from xmalign.formats.spatial_analyzer import (
    NAMING,
    read_point_list,
    tracker_file_from_export,
    unmeasured,
)
from xmalign.instrument_text import instrument_lines
from xmalign.machine import Machine
from xmalign.post.evaluate import Instruments
from xmalign.post.instruments import MIN_TRACER_PLACES

if TYPE_CHECKING:  # the simulator is loaded only by the commands that use it
    from sim.machine import ErrorAmplitudes


def read_instruments(
    tracker: list[Path], tracer: list[Path], knot_spacing_mm: float | None = None
) -> Instruments:
    """The tracker-point and tracer-length files given (each option repeatable)."""
    return Instruments(
        trackers=tuple(read_tracker_points(path) for path in tracker),
        tracers=tuple(read_tracer_lengths(path) for path in tracer),
        knot_spacing_mm=knot_spacing_mm,
    )


def count_readings(instruments: Instruments) -> str:
    """``"500 tracker points, 1760 tracer lengths"`` (what is being fitted besides the lines)."""
    points = sum(len(file.points) for file in instruments.trackers)
    lengths = sum(len(file.lengths) for file in instruments.tracers)
    parts = [f"{points} tracker points"] if points else []
    return ", ".join(parts + ([f"{lengths} tracer lengths"] if lengths else []))


def check_inputs(
    plans: list[Path], tracker: list[Path], tracer: list[Path], verify_needs_plan: bool
) -> None:
    """Refuse a ``post`` with nothing to fit, or a verification without a plan (one line)."""
    if not plans and not tracker and not tracer:
        raise InputError(
            "post: nothing to fit; give --plan/--data pairs, --tracker FILE or --tracer FILE"
        )
    if not plans and verify_needs_plan:
        raise InputError("post: --verify-data needs --verify-plan when no --plan is given")


INSTRUMENTS = ("tracker", "tracer")


@dataclass(frozen=True)
class InstrumentRequest:
    """``xmalign program --instrument ...``: what to plan and where to write it."""

    instrument: str
    on_the_fly: bool
    places: int
    out: Path | None
    points_out: Path | None
    dialect: str | None
    simultaneous: bool = False


def check_instrument_options(
    instrument: str | None, on_the_fly: bool, places: int | None, simultaneous: bool = False
) -> None:
    """One line for an instrument option that does not fit the others."""
    if instrument is None:
        if on_the_fly or places is not None or simultaneous:
            option = (
                "--on-the-fly" if on_the_fly else "--places" if places is not None
                else "--simultaneous"
            )  # fmt: skip
            raise InputError(f"{option} needs --instrument tracker or tracer")
        return
    if instrument not in INSTRUMENTS:
        raise InputError(f"--instrument '{instrument}' is not known (known: tracker, tracer)")
    if instrument == "tracer" and on_the_fly:
        raise InputError("--on-the-fly is for --instrument tracker (a tracer measures lengths)")
    if instrument == "tracker" and (places is not None or simultaneous):
        option = "--places" if places is not None else "--simultaneous"
        raise InputError(f"{option} is for --instrument tracer")
    if places is not None and not MIN_TRACER_PLACES <= places <= 12:
        raise InputError(f"--places {places}: give {MIN_TRACER_PLACES} to 12 tracer places")


def program_instrument(machine: Machine, request: InstrumentRequest) -> None:
    """Plan a tracker (points or paths on the fly) or tracer (places and points) calibration
    (:func:`trajectories.instruments.plan_instrument`).

    Writes the G-code (stdout or ``out``), the point list for the instrument's own
    software (``points_out``), and tells on stderr where the instrument stands,
    which SMR to mount when, the machine time and how well the plan determines the
    errors.
    """
    refuse_overwriting({}, {"--out": request.out, "--points-out": request.points_out})
    dialect_name = resolve_dialect(machine, request.dialect)
    name = request.out.stem if request.out is not None else "XMALIGN"
    dialect = make_dialect(dialect_name, machine, name)
    plan = plan_instrument(
        machine, request.instrument, request.on_the_fly, request.places, request.simultaneous
    )
    text, time = write_instrument_program(
        plan.program, machine, dialect, f"xmalign {request.instrument}"
    )
    for note in [*plan.notes, machine_time_note(plan, time)]:
        error_console.print(note, highlight=False, markup=False, soft_wrap=True)
    if request.points_out is not None:
        atomic_write_text(request.points_out, point_list_csv(plan.program, machine.smr_offset))
    if request.out is not None:
        atomic_write_text(request.out, text)
    else:
        sys.stdout.write(text)


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (the provenance of what was converted)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _export(spatial_analyzer: Path | None, name_xyz: Path | None) -> tuple[Path, str, str]:
    """The export given, its option and its default naming; one of the two options."""
    if (spatial_analyzer is None) == (name_xyz is None):
        raise InputError("import: give one of --spatial-analyzer FILE and --name-xyz FILE")
    if spatial_analyzer is not None:
        return spatial_analyzer, "--spatial-analyzer", "collection-group-target"
    assert name_xyz is not None
    return name_xyz, "--name-xyz", "target"


def import_points(
    points: Annotated[
        Path,
        typer.Option(help="The point list of xmalign program --instrument tracker --points-out."),
    ],
    out: Annotated[Path, typer.Option(help="Tracker-points CSV to write (for post --tracker).")],
    spatial_analyzer: Annotated[
        Path | None,
        typer.Option(
            "--spatial-analyzer",
            help="SpatialAnalyzer ASCII export (point names, X Y Z, optional further columns;"
            " spaces, commas or tabs).",
        ),
    ] = None,
    name_xyz: Annotated[
        Path | None,
        typer.Option(
            "--name-xyz",
            help="A plain Name,X,Y,Z export of other tracker software (optional header line).",
        ),
    ] = None,
    naming: Annotated[
        str | None,
        typer.Option(
            help="The export's point names: collection-group-target (SpatialAnalyzer's"
            " default), group-target or target (--name-xyz's).",
        ),
    ] = None,
    units: Annotated[
        str, typer.Option(help="The export's length unit: mm, in or m (checked).")
    ] = "mm",
    station: Annotated[str, typer.Option(help="The tracker station's name.")] = "T1",
    machine: Annotated[
        Path | None, typer.Option(help="Machine YAML with smr_offset_mm (default: reference).")
    ] = None,
) -> None:
    """Convert a tracker's point export into tracker points for ``xmalign post --tracker``.

    Target names are the point indices of the point list; the export's groups
    are the runs, in the order they first appear (without groups, a name measured
    again starts the next run). The distances between the points must be the
    commanded moves': an export in another unit than --units, or with names that
    do not match the point list, is refused naming the first row that does not.
    """
    export, option, default_naming = _export(spatial_analyzer, name_xyz)
    if naming is not None and naming not in NAMING:
        raise InputError(f"--naming '{naming}' is not known ({', '.join(NAMING)})")
    if units not in UNITS_MM:
        raise InputError(f"--units '{units}' is not known ({', '.join(UNITS_MM)})")
    refuse_overwriting({option: export, "--points": points, "--machine": machine}, {"--out": out})
    machine_model = machine_or_default(machine)
    listed = read_point_list(points)
    file = tracker_file_from_export(
        machine_model, export, listed, station, naming or default_naming, units
    )
    inputs = {str(path): file_sha256(path) for path in (export, points)}
    write_tracker_points(out, file.points, inputs)
    runs = len({row.run for row in file.points})
    missing = unmeasured(listed, file)
    error_console.print(
        f"wrote {out}: {len(file.points)} points of station {station} in {runs} run(s),"
        f" read in {units}"
        + (
            f"; {len(missing)} listed points not measured (first '{missing[0]}')" if missing else ""
        ),
        highlight=False,
    )


def register(app: typer.Typer) -> None:
    app.command(name="import")(import_points)


def instrument_dry_run(
    machine: Machine,
    out: Path,
    instrument: str,
    seed: int,
    dialect: str | None,
    simultaneous: bool = False,
) -> None:
    """``xmalign dry-run --instrument``: the simulated chain and its figures against the truth."""
    from sim.instrument_dry_run import MATERIAL_C, simulate_instruments

    with error_console.status(f"dry run, {instrument}"):
        report = simulate_instruments(machine, out, instrument, seed, dialect, simultaneous)
    assert report.result.instruments is not None and report.machine is not None
    for line in instrument_lines(report.result.instruments):
        error_console.print(line, highlight=False, markup=False, soft_wrap=True)
    tracker, tracer = report.machine.tracker, report.machine.tracer
    smr = ", ".join(report.machine.smr_offsets_mm) or "one"
    time = f"machine time: {instrument} {report.instrument_min:.0f} min"
    if report.other_way_min is not None:
        other = "one place at a time" if report.simultaneous else "all tracers at once"
        way = "all tracers at once" if report.simultaneous else "one place at a time"
        time += f" ({way}; {other}: {report.other_way_min:.0f} min)"
    if report.xm60_after_um is not None:
        time += f", XM-60 station {report.xm60_min:.0f} min"
    errors = (
        f"tracer scale {tracer.scale_ppm:g} ppm per run"
        if instrument == "tracer"
        else f"tracker angle errors {tracker.angle_systematic_urad:g} urad, scale"
        f" {tracker.scale_ppm:g} ppm per run"
    )
    lines = [
        f"virtual instruments: SMR positions {smr}; {errors}; the machine's scales at"
        f" {MATERIAL_C[0]:g} to {MATERIAL_C[1]:g} degC through each run (material_c)",
        time,
        f"volumetric error over the whole travel (RMS, rigid motion removed, at the"
        f" {report.functional_point}): before {report.volumetric_before_um:.2f} um, after"
        f" {report.volumetric_after_um:.2f} um"
        + (
            f" (the XM-60 station alone: {report.xm60_after_um:.2f} um)"
            if report.xm60_after_um is not None
            else ""
        ),
        f"files in {out}/: " + ", ".join(path.name for path in report.files.values()),
    ]
    for line in lines:
        console.print(line, highlight=False, markup=False, soft_wrap=True)


def compare_instruments_command(
    machine: Machine, trials: int, seed: int, amplitudes: ErrorAmplitudes, out: Path
) -> None:
    """``xmalign mc --mode instruments``: every instrument on the same random machines."""
    from sim.instrument_study import compare_instruments

    path = out / "mc-instruments.json"
    refuse_overwriting({}, {"--out": path})
    output_folder(out, "--out")
    with error_console.status(f"{trials} machines, every instrument"):
        results = compare_instruments(machine, trials, seed, amplitudes)
    document = {
        "format": "xmalign-mc-instruments/1",
        "machine": machine.name,
        "trials": trials,
        "seed": seed,
        "strategies": [
            {"name": r.name, "residual_um": r.residual_um, "machine_time_min": r.minutes}
            for r in results
        ],
    }
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(document, indent=2) + "\n")
    table = RichTable(title="Residual over the whole travel (um RMS) and machine time")
    for column in ("strategy", "mean", "std", "95 %", "min"):
        table.add_column(column, justify="left" if column == "strategy" else "right")
    for r in results:
        table.add_row(
            r.name, f"{r.mean_um:.2f}", f"{r.std_um:.2f}", f"{r.p95_um:.2f}", f"{r.minutes:.0f}"
        )
    console.print(table)
    console.print(f"wrote {path}", highlight=False)
