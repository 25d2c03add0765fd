"""``xmalign run`` and ``xmalign dry-run``: the measurement, and the whole calibration simulated."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from xmalign.calibration import (
    CalibrationRun,
    RunOutput,
    RunStatistics,
    capture_sequence,
    check_run_output,
)
from xmalign.cli.common import (
    LogFileOption,
    check_positions,
    check_seed,
    console,
    error_console,
    machine_for_plan,
    machine_or_default,
    start_log_file,
    stop_log_file,
)
from xmalign.cli.instruments import instrument_dry_run
from xmalign.environment import EnvironmentMonitor
from xmalign.errors import InputError, XmalignError
from xmalign.formats.common import refuse_overwriting
from xmalign.formats.measurements import load_measurements
from xmalign.formats.plan import Plan, read_plan
from xmalign.machine import Machine
from xmalign.safety import like
from xmalign.steps import open_measurements_step

if TYPE_CHECKING:
    from firmware_iface.config import MachinePositionConfig
    from sim.dry_run import DryRunOptions
    from xmalign.roles import MachinePositionSource

_SHOP_HELP = (
    "the virtual shop's air and machine temperature: 'drifting' (air 22 -> 25 °C,"
    " machine 22 -> 23 °C, pressure falling) or 'reference' (20 °C)."
)
ShopOption = Annotated[str, typer.Option(help=f"With --sim: {_SHOP_HELP}")]
DryRunShopOption = Annotated[str, typer.Option(help=_SHOP_HELP[0].upper() + _SHOP_HELP[1:])]
InProcessOption = Annotated[
    bool,
    typer.Option(
        "--in-process",
        help="With --sim: the simulated devices as in-process objects, faster, instead of"
        " served over Modbus TCP, a serial pty and a position file (docs/simulator.md).",
    ),
]
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
    return sum(len(list(capture_sequence(line))) for line in plan.lines)


def _stopped(interrupt: KeyboardInterrupt, out: Path, also: str = "") -> KeyboardInterrupt:
    """Ctrl-C (SIGTERM, SIGHUP): one line saying what is kept and how to go on, and what
    the run said of it (the controller's feed held, an axis that could not be locked).

    Printed by the CLI, exit 130 (128 + the signal's number).
    """
    try:
        saved = len(load_measurements(out, torn_ok=True).rows)
    except XmalignError:
        saved = 0
    said = [str(interrupt), *getattr(interrupt, "__notes__", ())]
    more = "".join(f"; {part}" for part in said if part)
    return like(
        interrupt, f"stopped: {saved} points kept in {out}; go on with --resume{also}{more}"
    )


def _kept(error: XmalignError, output: RunOutput) -> XmalignError:
    """The same error, saying how many points the file keeps."""
    return like(error, f"{error}; {output.writer.saved} points kept in {output.writer.path}")


def _measure(output: RunOutput, plan: Plan, measure: Callable[[], CalibrationRun]) -> None:
    """Run ``measure`` with a progress bar counting the points saved in the file."""
    for warning in output.warnings:
        error_console.print(f"warning: {warning}", style="yellow", markup=False)
    with _progress() as progress:
        task = progress.add_task(
            "measuring", total=_point_count(plan), completed=output.writer.saved
        )
        output.on_saved = lambda saved: progress.update(task, completed=saved)
        try:
            run = measure()
        except XmalignError as error:
            raise _kept(error, output) from error
    for note in run.statistics.resumed + run.statistics.recovered:
        console.print(note, markup=False, soft_wrap=True)
    if run.statistics.missed:
        error_console.print(
            f"warning: {len(run.statistics.missed)} points were not captured (the machine"
            " went on before they were captured); run again with --resume to capture them",
            style="yellow",
            markup=False,
        )
    console.print(
        f"{run.statistics.points} points captured; {output.writer.saved} points in"
        f" {output.writer.path}",
        markup=False,
        soft_wrap=True,
    )


@dataclass
class Measurement:
    """What a run measures with: ``measure`` fills an output; ``environment`` its rows' air."""

    measure: Callable[[RunOutput], None]
    environment: EnvironmentMonitor | None = None


@contextmanager
def _sim_measurement(
    machine: Machine,
    plan: Plan,
    seed: int,
    program: Path | None,
    dialect: str | None,
    shop: str,
    in_process: bool,
) -> Iterator[Measurement]:
    """Check the --sim options; the measurement on the virtual machine in a simulated shop."""
    from sim.dry_run import measure_served, measure_virtually, virtual_setup
    from sim.environment import SHOPS, attach_shop
    from trajectories.gcode import resolve_dialect
    from xmalign.steps import program_gcode

    _check_shop(shop)
    if program is not None:
        dialect_name = resolve_dialect(machine, dialect)
        text = read_text(program, "G-code program")
    else:  # the program step's G-code of the plan
        dialect_name, text = program_gcode(plan, machine, dialect)
    setup = virtual_setup(machine, seed, lockstep=not in_process)
    station = attach_shop(setup.world, SHOPS[shop](), seed)

    def capture(output: RunOutput) -> CalibrationRun:
        if in_process:
            return measure_virtually(setup, plan, text, dialect_name, output)
        return measure_served(setup, machine, plan, text, dialect_name, output)

    def measure(output: RunOutput) -> None:
        _measure(output, plan, lambda: capture(output))

    yield Measurement(measure, EnvironmentMonitor(station, "simulated weather station"))


def _check_shop(shop: str) -> None:
    from sim.environment import SHOPS

    if shop not in SHOPS:
        raise InputError(f"--shop: '{shop}' is not one of {', '.join(SHOPS)}")


@contextmanager
def _live_measurement(machine: Machine, plan: Plan, config_path: Path) -> Iterator[Measurement]:
    """Check the hardware configuration, open the devices; the live measurement."""
    from firmware_iface.config import load_units_config, open_devices
    from xmalign.roles import WallClock
    from xmalign.steps import (
        RunStepDevices,
        controlled_run_step,
        following_drive,
        refuse_replacing_a_foreign_program,
        run_step,
        stepping_drive,
    )

    config = load_units_config(config_path)
    controlled = config.machine_position.controlled
    if controlled is not None:  # before anything is opened or moved
        refuse_replacing_a_foreign_program(controlled.program)
    devices = open_devices(config, machine)
    timeout_s = config.timeouts.machine_s

    def capture(output: RunOutput) -> CalibrationRun:
        roles = RunStepDevices(
            devices.launch, devices.receiver, devices.interferometer, WallClock()
        )
        if devices.controller is not None and controlled is not None:
            run = controlled_run_step(
                plan,
                machine,
                roles,
                output,
                devices.controller,
                controlled,
                timeout_s,
                _tell_operator,
            )
            _tell_machine_time(plan, machine, run.statistics)
            return run
        if config.machine_position.follows_the_machine:
            check = _program_check(config.machine_position, devices.position, plan, machine)
            drive = following_drive(
                devices.mover, _tell_operator, machine, timeout_s, check_program=check
            )
        else:
            drive = stepping_drive(devices.mover, machine)
        return run_step(plan, roles, output, drive)

    environment = (
        EnvironmentMonitor(devices.environment) if devices.environment is not None else None
    )
    with devices:
        yield Measurement(
            lambda output: _measure(output, plan, lambda: capture(output)), environment
        )


def _program_check(
    source: MachinePositionConfig,
    followed: MachinePositionSource | None,
    plan: Plan,
    machine: Machine,
) -> Callable[[], None]:
    """For a followed controller that reports its program: on a SINUMERIK with ``program``,
    put xmalign's program there (``copy_program``) and select it first; the check that
    refuses another program running (docs/hardware.md, "Following the controller")."""
    from firmware_iface.controller_config import expected_program
    from xmalign.program_check import ProgramGuard, program_name
    from xmalign.roles import ReportsProgram
    from xmalign.steps import program_gcode, program_name_on_controller

    section = source.mtconnect or source.sinumerik
    if section is None or not isinstance(followed, ReportsProgram):
        return lambda: None
    expected, key = expected_program(section, program_name_on_controller(machine))
    nc = source.sinumerik
    if nc is not None and nc.program is not None:
        from firmware_iface.sinumerik_opcua import SinumerikMachine  # asyncua: only here

        if isinstance(followed, SinumerikMachine):
            name = program_name(nc.program)
            text = program_gcode(plan, machine, "sinumerik", name)[1] if nc.copy_program else None
            _tell_operator(followed.prepare_run(nc.program, expected, text))
    return ProgramGuard(followed, expected, key, _tell_operator).check


def _tell_machine_time(plan: Plan, machine: Machine, statistics: RunStatistics) -> None:
    """The program's time on the machine against the G-code's own estimate."""
    from trajectories.gcode.program import estimate_machine_time

    assert statistics.program_s is not None
    estimate = estimate_machine_time(plan, machine).total_s
    console.print(
        f"machine time {statistics.program_s - statistics.stopped_s:.1f} s without the"
        f" {statistics.stopped_s:.1f} s at the stops for the units (G-code estimate"
        f" {estimate:.1f} s); program {statistics.program_s:.1f} s from start to end",
        markup=False,
        soft_wrap=True,
    )


def _tell_operator(message: str) -> None:
    console.print(message, markup=False, soft_wrap=True)  # one line: the terminal wraps it


def read_text(path: Path, what: str) -> str:
    """A UTF-8 text file; every failure is one line naming the file."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise InputError(f"{path}: {what} is not UTF-8 text") from error
    except OSError as error:
        raise InputError(f"{path}: cannot read {what} ({error.strerror})") from error


def run_command(
    plan: Annotated[Path, typer.Option(help="Measurement plan JSON (xmalign program --plan-out).")],
    out: Annotated[
        Path,
        typer.Option(help="Measurement CSV, new (never replaced), saved point by point."),
    ],
    machine: MachineOption = None,
    sim: Annotated[bool, typer.Option("--sim", help="Run on the virtual machine.")] = False,
    config: Annotated[
        Path | None, typer.Option(help="Hardware configuration units.yaml (live run).")
    ] = None,
    resume: Annotated[
        bool,
        typer.Option("--resume", help="Go on with the points already in --out (same plan)."),
    ] = False,
    seed: Annotated[
        int, typer.Option(help="With --sim: the virtual machine's seed (the same to resume).")
    ] = 1,
    program: Annotated[
        Path | None, typer.Option(help="With --sim: execute this G-code (default: from the plan).")
    ] = None,
    dialect: Annotated[str | None, typer.Option(help="G-code dialect of --program.")] = None,
    shop: ShopOption = "drifting",
    in_process: InProcessOption = False,
    log_file: LogFileOption = None,
) -> None:
    """Drive the units, lock them, step the machine through the plan and capture every point.

    Every point is saved to --out before the machine moves on. Ctrl-C stops the
    units, locks them and keeps every saved point; --resume goes on after them.
    """
    if sim == (config is not None):
        raise InputError("give either --sim or --config UNITS.yaml")
    if in_process and not sim:
        raise InputError("--in-process is for --sim (a live run always uses the hardware)")
    check_seed(seed)
    refuse_overwriting(
        {"--plan": plan, "--machine": machine, "--config": config, "--program": program},
        {"--out": out},
        {"--log-file": log_file},
    )
    check_run_output(out, resume)
    plan_model = read_plan(plan)
    machine_model = machine_for_plan(machine, plan_model, plan)
    # the options are checked: only now are devices opened and --out created or opened
    log_handler = start_log_file(log_file)
    try:
        with (
            _measurement(
                machine_model, plan_model, sim, config, seed, program, dialect, shop, in_process
            ) as measurement,
            open_measurements_step(
                out,
                plan_model,
                machine_model,
                resume,
                measurement.environment,
                seed if sim else None,
            ) as output,
        ):
            try:
                measurement.measure(output)
            except KeyboardInterrupt as interrupt:
                raise _stopped(interrupt, out) from None
    finally:
        stop_log_file(log_handler)


def _measurement(
    machine: Machine,
    plan: Plan,
    sim: bool,
    config: Path | None,
    seed: int,
    program: Path | None,
    dialect: str | None,
    shop: str,
    in_process: bool = False,
) -> AbstractContextManager[Measurement]:
    if sim:
        return _sim_measurement(machine, plan, seed, program, dialect, shop, in_process)
    assert config is not None
    return _live_measurement(machine, plan, config)


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
        "  without air/material comp.",
        f"{report.volumetric_uncompensated_um:.2f} µm after",
        "the same readings",
        "tables fitted to the uncompensated readings",
    )
    if report.as_left is not None:
        table.add_row(
            "  as left (verification)",
            f"{report.as_left.volumetric_measured_um:.2f} µm measured",
            f"{report.as_left.volumetric_true_um:.2f} µm true",
            f"{report.as_left.measurement_error_um:.2f} µm off; {report.as_left.controller}"
            f" tables loaded, as found {report.volumetric_before_um:.1f} µm",
        )
    table.add_row(
        "on-machine time",
        f"{report.on_machine_s / 60:.1f} min",
        "measuring ≤ 12 min",
        f"identify {report.identification_s / 60:.1f}, align {report.alignment_s / 60:.1f}, "
        f"measure {report.measuring_s / 60:.1f} min",
    )
    return table


def _dry_run_stopped(
    interrupt: KeyboardInterrupt,
    out: Path,
    stage: str,
    seed: int,
    machine: Path | None,
    dialect: str | None,
    shop: str,
    in_process: bool = False,
) -> KeyboardInterrupt:
    """Ctrl-C in a dry run: what is kept, and for the run stage how to go on."""
    if stage != "run":
        return like(interrupt, f"stopped during {stage}: the files so far are in {out}/")
    options = f" --machine {machine}" if machine else ""
    options += f" --dialect {dialect}" if dialect else ""
    options += f" --shop {shop}"
    options += " --in-process" if in_process else ""
    return _stopped(
        interrupt,
        out / "measurements.csv",
        f" (xmalign run --sim --seed {seed}{options} --plan {out / 'plan.json'}"
        f" --out {out / 'measurements.csv'} --resume)",
    )


def dry_run_command(
    machine: MachineOption = None,
    seed: Annotated[int, typer.Option(help="Seed of the virtual machine and units.")] = 1,
    out: Annotated[
        Path, typer.Option(help="New folder for every file of the calibration (never replaced).")
    ] = Path("xmalign-dry-run"),
    dialect: Annotated[
        str | None, typer.Option(help="G-code dialect (default: controller's).")
    ] = None,
    identification_positions: Annotated[int, typer.Option(min=3, help="Alignments.")] = 6,
    stations: Annotated[
        int,
        typer.Option(
            min=1, max=2, help="Launch-unit stations: 2 adds the proposed second station."
        ),
    ] = 1,
    shop: DryRunShopOption = "drifting",
    verify: Annotated[
        bool,
        typer.Option(
            "--verify",
            help="Then load the controller's tables into the virtual CNC and measure again"
            " (verification.csv: as left).",
        ),
    ] = False,
    in_process: Annotated[
        bool,
        typer.Option(
            "--in-process",
            help="Measure with the simulated devices in-process (faster) instead of over"
            " Modbus TCP, a serial pty and a position file (docs/simulator.md).",
        ),
    ] = False,
    instrument: Annotated[
        str,
        typer.Option(help="xm60, or a laser 'tracker', 'tracer' or 'xm60+tracker' (in-process)."),
    ] = "xm60",
    simultaneous: Annotated[
        bool,
        typer.Option(
            "--simultaneous",
            help="With --instrument tracer: every tracer follows the SMR in the same run.",
        ),
    ] = False,
) -> None:
    """The whole calibration on the virtual machine: identify, program, run, post, comp."""
    from sim.dry_run import STAGES, DryRunOptions, check_dry_run_folder, simulate_calibration
    from trajectories.gcode import resolve_dialect

    check_seed(seed)
    if instrument != "xm60":
        instrument_dry_run(
            machine_or_default(machine), out, instrument, seed, dialect, simultaneous
        )
        return
    if simultaneous:
        raise InputError("--simultaneous is for --instrument tracer")
    check_positions(identification_positions, "--identification-positions")
    _check_shop(shop)
    machine_model = machine_or_default(machine)
    resolve_dialect(machine_model, dialect)  # a bad --dialect before any folder is made
    check_dry_run_folder(out)
    options = DryRunOptions(
        seed=seed,
        identification_positions=identification_positions,
        dialect=dialect,
        shop=shop,
        verify=verify,
        served=not in_process,
    )
    if stations == 2:
        if verify:
            raise InputError("--verify is for one station (give --stations 1)")
        _two_station_dry_run(machine_model, out, options)
        return
    started: list[str] = []
    with _progress() as progress:
        stages = len(STAGES) + verify
        task = progress.add_task("dry run", total=stages)

        def on_stage(name: str) -> None:
            if started:
                progress.advance(task)
            started.append(name)
            progress.update(task, description=f"dry run: {name}")

        def on_point(saved: int) -> None:
            progress.update(task, description=f"dry run: run, {saved} points saved")

        try:
            report = simulate_calibration(machine_model, out, options, on_stage, on_point)
        except KeyboardInterrupt as interrupt:
            stage = started[-1] if started else "start"
            raise _dry_run_stopped(
                interrupt, out, stage, seed, machine, dialect, shop, in_process
            ) from None
        progress.update(task, completed=stages, description="dry run: done")
    console.print(_results_table(report))
    design = [f"identification design: {warning}" for warning in report.design_warnings]
    for warning in design + report.identification.warnings + report.plan.warnings:
        console.print(f"warning: {warning}", style="yellow", markup=False)
    console.print(
        f"files in {out}/: " + ", ".join(p.name for p in report.files.values()), markup=False
    )


def _two_station_dry_run(machine: Machine, out: Path, options: DryRunOptions) -> None:
    """``dry-run --stations 2``: both stations, one post, the residuals against the truth."""
    from sim.two_stations import simulate_two_stations

    if (out / "station1-plan.json").exists():
        raise InputError(f"{out}/ already holds a two-station dry run; give another --out")
    with console.status("dry run, two stations"):
        report = simulate_two_stations(machine, out, options)
    proposal = report.proposal
    where = ", ".join(f"{v:.0f}" for v in proposal.position_mm)
    covered = ", ".join(f"{axis} {100 * v:.0f} %" for axis, v in proposal.coverage.items())
    console.print(
        f"second station: launch cp at [{where}] mm, lines {','.join(proposal.line_ids)};"
        f" both stations cover {covered} of the strokes",
        markup=False,
    )
    for number, station in enumerate(report.stations, start=1):
        for warning in station.design_warnings:
            console.print(
                f"warning: station {number}: identification design: {warning}",
                style="yellow",
                markup=False,
            )
        console.print(
            f"station {number}: on-machine time {station.on_machine_s / 60:.1f} min"
            f" (lines {' '.join(line.line.id for line in station.plan.lines)})",
            markup=False,
        )
    console.print(
        f"volumetric error (RMS, rigid motion removed) against the truth:"
        f" {report.strokes_um:.2f} um over the measured strokes,"
        f" {report.travel_um:.2f} um over the whole travel",
        markup=False,
    )
    console.print(f"files in {out}/: station1-*, station2-*, errors.csv", markup=False)


def register(app: typer.Typer) -> None:
    app.command("run")(run_command)
    app.command("dry-run")(dry_run_command)
