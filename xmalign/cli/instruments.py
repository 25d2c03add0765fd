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
    InstrumentProgram,
    fly_paths,
    information_limit_um,
    point_list_csv,
    propose_tracer_places,
    tracer_points,
    tracker_place,
    tracker_points,
    write_instrument_program,
)
from xmalign.cli.common import console, error_console, machine_or_default, output_folder
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text, refuse_overwriting
from xmalign.formats.instruments import (
    read_tracer_lengths,
    read_tracker_points,
    write_tracker_points,
)
from xmalign.formats.spatial_analyzer import (
    read_point_list,
    read_spatial_analyzer,
    tracker_points_from_export,
)
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.post.evaluate import Instruments
from xmalign.post.instruments import MIN_TRACER_PLACES, instrument_lines
from xmalign.steps import import_stream_step

if TYPE_CHECKING:  # the simulator is loaded only by the commands that use it
    from sim.machine import ErrorAmplitudes


def read_instruments(tracker: list[Path], tracer: list[Path]) -> Instruments:
    """The tracker-point and tracer-length files given (each option repeatable)."""
    return Instruments(
        trackers=tuple(read_tracker_points(path) for path in tracker),
        tracers=tuple(read_tracer_lengths(path) for path in tracer),
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


def _triple(values: Vec, digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


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


def check_instrument_options(instrument: str | None, on_the_fly: bool, places: int | None) -> None:
    """One line for an instrument option that does not fit the others."""
    if instrument is None:
        if on_the_fly or places is not None:
            option = "--on-the-fly" if on_the_fly else "--places"
            raise InputError(f"{option} needs --instrument tracker or tracer")
        return
    if instrument not in INSTRUMENTS:
        raise InputError(f"--instrument '{instrument}' is not known (known: tracker, tracer)")
    if instrument == "tracer" and on_the_fly:
        raise InputError("--on-the-fly is for --instrument tracker (a tracer measures lengths)")
    if instrument == "tracker" and places is not None:
        raise InputError("--places is for --instrument tracer")
    if places is not None and not MIN_TRACER_PLACES <= places <= 12:
        raise InputError(f"--places {places}: give {MIN_TRACER_PLACES} to 12 tracer places")


def program_instrument(machine: Machine, request: InstrumentRequest) -> None:
    """Plan a tracker (points or paths on the fly) or tracer (places and points) calibration.

    Writes the G-code (stdout or ``out``), the point list for the instrument's own
    software (``points_out``), and tells on stderr where the instrument stands,
    the machine time and how well the plan determines the errors.
    """
    refuse_overwriting({}, {"--out": request.out, "--points-out": request.points_out})
    dialect_name = resolve_dialect(machine, request.dialect)
    name = request.out.stem if request.out is not None else "XMALIGN"
    dialect = make_dialect(dialect_name, machine, name)
    if request.instrument == "tracker":
        program = (
            InstrumentProgram(paths_mm=fly_paths(machine))
            if request.on_the_fly
            else InstrumentProgram(points_mm=tracker_points(machine))
        )
        runs = 1 if request.on_the_fly else 2
        where = tracker_place(machine)
        limit = information_limit_um(machine, [program], tracker_mm=where, runs=runs)
        what = (
            f"{len(program.paths_mm)} paths on the fly"
            if request.on_the_fly
            else (f"{len(program.points_mm)} points, run it twice (runs 0 and 1)")
        )
        notes = [
            f"tracker: {what}; stand it on the table near {_triple(where, 0)} mm (MCS),"
            " the SMR at the machine file's smr_offset_mm"
        ]
        minutes = runs
    else:
        places = propose_tracer_places(machine, request.places)
        program = InstrumentProgram(points_mm=tracer_points(machine))
        limit = information_limit_um(machine, [program] * len(places), pivots_mm=places)
        notes = [
            f"tracer place P{i + 1}: pivot near {_triple(p, 0)} mm (MCS); run the program once"
            for i, p in enumerate(places)
        ]
        notes.append(f"tracer: {len(program.points_mm)} points from each of {len(places)} places")
        minutes = len(places)
    text, time = write_instrument_program(
        program, machine, dialect, f"xmalign {request.instrument}"
    )
    notes.append(
        f"machine time: {time.total_s / 60:.1f} min per run, {minutes * time.total_s / 60:.1f} min"
        f" in all; the volumetric error over the whole travel to about {limit:.2f} um"
        " (standard uncertainty from the machine file's instrument uncertainty, RMS over the"
        " travel; the machine's repeatability and the tables' model error come on top)"
    )
    for note in notes:
        error_console.print(note, highlight=False, markup=False, soft_wrap=True)
    if request.points_out is not None:
        atomic_write_text(request.points_out, point_list_csv(program, machine.smr_offset))
    if request.out is not None:
        atomic_write_text(request.out, text)
    else:
        sys.stdout.write(text)


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's bytes (the provenance of what was converted)."""
    return hashlib.sha256(path.read_bytes()).hexdigest()


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
            help="SpatialAnalyzer ASCII export (Collection Group Target X Y Z, mm).",
        ),
    ] = None,
    tracker_stream: Annotated[
        Path | None,
        typer.Option(
            "--tracker-stream",
            help="A tracker's stream of an on-the-fly program (station,run,time_s,tx_mm..).",
        ),
    ] = None,
    station: Annotated[str, typer.Option(help="The tracker station's name.")] = "T1",
    machine: Annotated[
        Path | None, typer.Option(help="Machine YAML with smr_offset_mm (default: reference).")
    ] = None,
) -> None:
    """Convert a tracker's export or stream into tracker points for ``xmalign post --tracker``.

    --spatial-analyzer: target names are the point indices of the point list; the
    export's groups are the runs, in the order they first appear.

    --tracker-stream: the samples are assigned to the point list's paths by the
    stream's own geometry (no clock shared with the CNC); the moves between
    paths, accelerations and stops are dropped; rows on the fly are written
    (docs/formats.md). The stream names its stations and runs (--station is not used).
    """
    if (spatial_analyzer is None) == (tracker_stream is None):
        raise InputError("import: give one of --spatial-analyzer FILE or --tracker-stream FILE")
    refuse_overwriting(
        {
            "--spatial-analyzer": spatial_analyzer,
            "--tracker-stream": tracker_stream,
            "--points": points,
            "--machine": machine,
        },
        {"--out": out},
    )
    machine_model = machine_or_default(machine)
    if tracker_stream is not None:
        with error_console.status(f"assigning {tracker_stream} to the program's paths"):
            result = import_stream_step(machine_model, tracker_stream, points, out)
        for name, run, a in result.runs:
            error_console.print(
                f"station {name} run {run}: {len(a.sample)} samples on {len(set(a.path.tolist()))}"
                f" paths ({a.off_path_um:.1f} um RMS from them), {a.dropped} dropped (moves"
                " between paths, accelerations, stops)",
                highlight=False,
            )
        error_console.print(f"wrote {out}: {result.rows} points on the fly", highlight=False)
        return
    assert spatial_analyzer is not None
    exported = read_spatial_analyzer(spatial_analyzer)
    rows = tracker_points_from_export(
        exported, read_point_list(points), machine_model.smr_offset, station, str(spatial_analyzer)
    )
    inputs = {str(path): file_sha256(path) for path in (spatial_analyzer, points)}
    write_tracker_points(out, rows, inputs)
    runs = len({row.run for row in rows})
    error_console.print(
        f"wrote {out}: {len(rows)} points of station {station} in {runs} run(s)", highlight=False
    )


def register(app: typer.Typer) -> None:
    app.command(name="import")(import_points)


def instrument_dry_run(
    machine: Machine,
    out: Path,
    instrument: str,
    seed: int,
    dialect: str | None,
    on_the_fly: bool = False,
) -> None:
    """``xmalign dry-run --instrument``: the simulated chain and its figures against the truth.

    ``on_the_fly``: the tracker logs a stream of the on-the-fly program, which is
    imported as ``import --tracker-stream`` does.
    """
    from sim.instrument_dry_run import simulate_instruments

    what = f"{instrument}{' on the fly' if on_the_fly else ''}"
    with error_console.status(f"dry run, {what}"):
        report = simulate_instruments(machine, out, instrument, seed, dialect, on_the_fly)
    assert report.result.instruments is not None
    for line in instrument_lines(report.result.instruments):
        error_console.print(line, highlight=False, markup=False, soft_wrap=True)
    lines = [
        f"machine time: {instrument} {report.instrument_min:.0f} min"
        + (
            f", XM-60 station {report.xm60_min:.0f} min" if report.xm60_after_um is not None else ""
        ),
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
