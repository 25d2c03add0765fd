"""``xmalign post --tracker/--tracer`` and ``xmalign program --instrument``."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table as RichTable

from xmalign.cli.common import (
    ForceOption,
    console,
    error_console,
    machine_or_default,
    named_by_options,
    output_folder,
    refuse_unused_options,
)
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text, refuse_overwriting
from xmalign.formats.instruments import read_tracer_lengths, read_tracker_points
from xmalign.instrument_text import instrument_lines
from xmalign.machine import Machine
from xmalign.post.evaluate import Instruments
from xmalign.steps import (
    DEFAULT_NAMING,
    Caller,
    check_instrument_request,
    import_stream_step,
    import_tracker_step,
    instrument_program_step,
)

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


@dataclass(frozen=True)
class InstrumentRequest:
    """``xmalign program --instrument ...``: what to plan and where to write it."""

    instrument: str
    on_the_fly: bool
    #: Tracer places (None: the step's default).
    places: int | None
    out: Path | None
    points_out: Path | None
    dialect: str | None
    simultaneous: bool = False


#: What ``xmalign program --instrument`` calls :func:`~xmalign.steps.instrument_program_step`'s
#: arguments.
INSTRUMENT_OPTIONS = {
    "instrument": "--instrument",
    "on_the_fly": "--on-the-fly",
    "places": "--places",
    "simultaneous": "--simultaneous",
    "dialect": "--dialect",
    "program_path": "--out",
    "points_path": "--points-out",
    "machine": "--machine",
}


def check_instrument_options(
    instrument: str | None, on_the_fly: bool, places: int | None, simultaneous: bool = False
) -> None:
    """One line for an instrument option that does not fit the others (before the machine
    is read; the step's own check, :func:`~xmalign.steps.check_instrument_request`)."""
    if instrument is None:
        if on_the_fly or places is not None or simultaneous:
            option = (
                "--on-the-fly" if on_the_fly else "--places" if places is not None
                else "--simultaneous"
            )  # fmt: skip
            raise InputError(f"{option} needs --instrument tracker or tracer")
        return
    check_instrument_request(
        instrument, on_the_fly, places, named_by_options(INSTRUMENT_OPTIONS), simultaneous
    )


def program_instrument(machine: Machine, request: InstrumentRequest, force: bool) -> None:
    """Plan a tracker (points or paths on the fly) or tracer (places and points) calibration
    (:func:`~xmalign.steps.instrument_program_step`).

    Writes the G-code (stdout or ``out``), the point list for the instrument's own
    software (``points_out``), and tells on stderr where the instrument stands,
    which SMR to mount when, the machine time and how well the plan determines the
    errors.
    """
    programmed = instrument_program_step(
        machine,
        request.instrument,
        request.on_the_fly,
        request.places,
        request.out,
        request.points_out,
        request.dialect,
        replace=force,
        caller=named_by_options(INSTRUMENT_OPTIONS),
        simultaneous=request.simultaneous,
    )
    for note in programmed.notes:
        error_console.print(note, highlight=False, markup=False, soft_wrap=True)
    if request.out is None:
        sys.stdout.write(programmed.gcode)


def _export(
    spatial_analyzer: Path | None, name_xyz: Path | None, tracker_stream: Path | None
) -> tuple[Path, str, str]:
    """The export or stream given, its option and an export's default naming; one only."""
    given = {
        "--spatial-analyzer": (spatial_analyzer, DEFAULT_NAMING),
        "--name-xyz": (name_xyz, "target"),
        "--tracker-stream": (tracker_stream, ""),
    }
    named = [(option, path, naming) for option, (path, naming) in given.items() if path]
    if len(named) != 1:
        raise InputError(f"import: give one of {', '.join(given)} (each with FILE)")
    option, path, naming = named[0]
    return path, option, naming


def _import_stream(
    stream: Path, points: Path, out: Path, machine: Machine, force: bool, caller: Caller
) -> None:
    """``import --tracker-stream`` (:func:`~xmalign.steps.import_stream_step`), told per run."""
    with error_console.status(f"assigning {stream} to the program's paths"):
        result = import_stream_step(stream, points, out, machine, force, caller)
    for name, run, a in result.runs:
        error_console.print(
            f"station {name} run {run}: {len(a.sample)} samples on {len(set(a.path.tolist()))}"
            f" paths ({a.off_path_um:.1f} um RMS from them), {a.dropped} dropped (moves"
            " between paths, accelerations, stops)",
            highlight=False,
        )
    error_console.print(f"wrote {out}: {result.rows} points on the fly", highlight=False)


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
    tracker_stream: Annotated[
        Path | None,
        typer.Option(
            "--tracker-stream",
            help="A tracker's stream of an on-the-fly program (station,run,time_s,tx_mm..).",
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
    force: ForceOption = False,
) -> None:
    """Convert a tracker's export or stream into tracker points for ``xmalign post --tracker``.

    --spatial-analyzer or --name-xyz: target names are the point indices of the point
    list; the export's groups are the runs, in the order they first appear (without
    groups, a name measured again starts the next run). The distances between the
    points must be the commanded moves': an export in another unit than --units, or
    with names that do not match the point list, is refused naming the first row
    that does not.

    --tracker-stream: the samples are assigned to the point list's paths by the
    stream's own geometry (no clock shared with the CNC); the moves between
    paths, accelerations and stops are dropped; rows on the fly are written
    (docs/formats.md). The stream names its stations and runs, in mm.
    """
    export, option, default_naming = _export(spatial_analyzer, name_xyz, tracker_stream)
    options = {
        "export_path": option,
        "stream_path": option,
        "points_path": "--points",
        "out": "--out",
        "machine": "--machine",
        "naming": "--naming",
        "units": "--units",
    }
    caller = named_by_options(options)
    if tracker_stream is not None:
        refuse_unused_options(
            {
                "--naming": naming is not None,
                "--units": units != "mm",
                "--station": station != "T1",
            },
            "with --tracker-stream (the stream names its stations and runs, in mm)",
        )
        _import_stream(export, points, out, machine_or_default(machine), force, caller)
        return
    imported = import_tracker_step(
        export,
        points,
        out,
        machine_or_default(machine),
        station,
        replace=force,
        caller=caller,
        naming=naming or default_naming,
        units=units,
    )
    runs = len({row.run for row in imported.points})
    missing = imported.unmeasured
    error_console.print(
        f"wrote {out}: {len(imported.points)} points of station {station} in {runs} run(s),"
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
    on_the_fly: bool = False,
) -> None:
    """``xmalign dry-run --instrument``: the simulated chain and its figures against the truth.

    ``on_the_fly``: the tracker logs a stream of the on-the-fly program, which is
    imported as ``import --tracker-stream`` does.
    """
    from sim.instrument_dry_run import MATERIAL_C, simulate_instruments

    what = f"{instrument}{' on the fly' if on_the_fly else ''}"
    with error_console.status(f"dry run, {what}"):
        report = simulate_instruments(
            machine, out, instrument, seed, dialect, simultaneous, on_the_fly
        )
    assert report.result.instruments is not None and report.machine is not None
    for line in instrument_lines(report.result.instruments):
        error_console.print(line, highlight=False, markup=False, soft_wrap=True)
    tracker, tracer = report.machine.tracker, report.machine.tracer
    smr = "one" if on_the_fly else ", ".join(report.machine.smr_offsets_mm) or "one"
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
        f"virtual instruments: SMR positions {smr}; {errors}"
        + (
            "; a stream on the fly, at 20 degC"
            if on_the_fly
            else f"; the machine's scales at {MATERIAL_C[0]:g} to {MATERIAL_C[1]:g} degC"
            " through each run (material_c)"
        ),
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
