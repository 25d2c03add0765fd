"""The five calibration steps as functions on role objects and files: the one pipeline.

identify, program, run, post and comp are wired here once; every CLI command,
the dry run (``sim/dry_run.py``, ``sim/two_stations.py``, served and
in-process) and the Monte Carlo study call these functions with real devices
or the simulator's behind the same roles (:mod:`xmalign.roles`). The step layer
writes every pose (:func:`write_pose_step`), opens every measurement file
(:func:`open_measurements_step`), posts one or more stations with the plan check
(:func:`post_step`) and writes every controller's files (:func:`comp_step`,
:func:`volumetric_comp_step`); a command adds only its output checks and what it
shows, by hooks. Only what differs between a controller running the program and
an operator stepping the machine is given by the caller: the *drive* of
:func:`run_step` (:func:`program_drive`, :func:`stepping_drive`,
:func:`following_drive`, :func:`controlled_drive`); a run on a controller xmalign
starts and resumes its program on is :func:`controlled_run_step`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from trajectories.gcode import make_dialect, resolve_dialect
from trajectories.gcode.fanuc import PROGRAM_NUMBER
from trajectories.gcode.program import PROGRAM_MARK, write_program
from trajectories.identification_design import IdentificationDesign, design_identification
from trajectories.planner import MeasurementPlan, plan_measurement
from xmalign.calibration import (
    CalibrationRun,
    ControlledProgram,
    ProgramEvent,
    ProgramWay,
    RunOutput,
    capture_program,
    control_program,
    follow_machine,
    open_run_output,
    step_through,
)
from xmalign.comp import Compensation, compensate
from xmalign.comp.linuxcnc_volumetric import MergedConfig, merge_config
from xmalign.environment import EnvironmentMonitor
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_files, refuse_special
from xmalign.formats.error_tables import ErrorTableSet, error_tables_text
from xmalign.formats.instrument_checks import check_instrument_files
from xmalign.formats.measurements import ChannelLimits, check_recorded_plan, load_measurements
from xmalign.formats.plan import Plan, read_plan, write_plan
from xmalign.formats.pose import LaunchPose, write_pose
from xmalign.formats.provenance import FileSource, sources
from xmalign.formats.session import NOMINAL_STRAIGHTNESS_RANGE_UM, Session, read_session
from xmalign.formats.studies import write_design
from xmalign.identification_routine import (
    PoseGuess,
    RoutineDevices,
    RoutineEvent,
    run_identification,
)
from xmalign.identify import IdentificationResult, IdentificationUncertainty, identify
from xmalign.machine import Machine
from xmalign.post.evaluate import Instruments, PostResult, Station, post_stations
from xmalign.rigid_body import ErrorTables
from xmalign.roles import (
    Clock,
    Interferometer,
    MachineMover,
    MachinePositionSource,
    PositioningUnit,
    ProgramControl,
)
from xmalign.safety import units_locked_on_exit

#: File name ending of a program in each dialect, as the controllers expect.
PROGRAM_SUFFIX = {"sinumerik": ".mpf", "heidenhain": ".h", "iso": ".nc", "linuxcnc": ".ngc"}
#: The program file's name in the usual calibration (``xmalign program --out run.nc``, the
#: dry run's ``run<suffix>``): the program a followed controller is expected to run.
PROGRAM_STEM = "run"
#: Alignments after which a quick identification points the units better than the guess.
REFINE_AFTER = 3


def refine_guess(session: Session) -> PoseGuess | None:
    """After :data:`REFINE_AFTER` alignments, point the units with a quick identification."""
    if len(session.alignments) < REFINE_AFTER:
        return None
    result = identify(session, "intersection")
    return PoseGuess(result.position_mm, result.gamma_rad)


def machine_guess(machine: Machine) -> PoseGuess | None:
    """The machine file's coarse launch-unit position as the first pointing guess."""
    if machine.launch_unit is None:
        return None
    return PoseGuess(np.asarray(machine.launch_unit.position_mm, dtype=float))


def design_step(
    machine: Machine, count: int, out: Path | None = None, machine_path: Path | None = None
) -> IdentificationDesign:
    """The identification positions for ``count`` alignments (``warnings`` to be shown);
    written to ``out`` (with the SHA-256 of ``machine_path``) when given."""
    design = design_identification(machine, count)
    if out is not None:
        write_design(
            out,
            machine.name,
            design.machine_mm,
            design.pose_covariance,
            sources(machine=machine_path),
        )
    return design


def write_pose_step(
    path: Path,
    result: IdentificationResult,
    session_path: Path | None = None,
    machine_path: Path | None = None,
) -> Path:
    """Write the identified pose (``xmalign program`` reads it) with the SHA-256 of the
    session it was solved from and of the machine file. Every pose file is written here."""
    write_pose(path, result.to_pose(), sources(session=session_path, machine=machine_path))
    return path


@dataclass
class IdentifyStepResult:
    """The solved identification and the session it came from."""

    result: IdentificationResult
    session: Session
    session_path: Path

    @property
    def converged(self) -> bool:
        return bool(self.result.converged)


def identify_step(
    positions_mm: np.ndarray,
    machine: Machine,
    devices: RoutineDevices,
    session_path: Path,
    method: str = "joint",
    uncertainty: IdentificationUncertainty | None = None,
    manual_align: Callable[[], None] | None = None,
    on_event: Callable[[RoutineEvent], None] | None = None,
    unit_timeout_s: float = 30.0,
    pose_path: Path | None = None,
    machine_path: Path | None = None,
) -> IdentifyStepResult:
    """Align at each position (session written as it goes, resumed), then solve the pose.

    The units are locked on every exit. ``uncertainty`` defaults to the
    machine file's ``uncertainty`` section. With ``pose_path`` the pose is
    written there (:func:`write_pose_step`).
    """
    with units_locked_on_exit(devices.launch, devices.receiver):
        session = run_identification(
            positions_mm,
            machine,
            devices,
            session_path,
            guess=machine_guess(machine),
            manual_align=manual_align,
            refine_guess=refine_guess,
            on_event=on_event,
            unit_timeout_s=unit_timeout_s,
        )
    if uncertainty is None:
        uncertainty = IdentificationUncertainty.from_machine(machine.uncertainty)
    result = identify(session, method, uncertainty, str(session_path))
    if pose_path is not None:
        write_pose_step(pose_path, result, Path(session_path), machine_path)
    return IdentifyStepResult(result, session, Path(session_path))


def solve_step(
    session_path: Path,
    uncertainty: IdentificationUncertainty,
    method: str = "joint",
    machine: Machine | None = None,
) -> IdentifyStepResult:
    """The pose from a recorded session (``xmalign identify --input``), read with the
    machine's straightness range (the nominal one without a machine file)."""
    range_um = (
        machine.interferometer.straightness_range_um
        if machine is not None
        else NOMINAL_STRAIGHTNESS_RANGE_UM
    )
    session = read_session(session_path, range_um)
    result = identify(session, method, uncertainty, str(session_path))
    return IdentifyStepResult(result, session, Path(session_path))


@dataclass
class ProgramStepResult:
    """The measurement plan (as read back from its file) and the G-code program."""

    measurement: MeasurementPlan
    plan: Plan
    dialect: str
    program: str
    files: dict[str, Path] = field(default_factory=dict)

    @property
    def warnings(self) -> list[str]:
        return list(self.measurement.warnings)


def program_gcode(
    plan: Plan, machine: Machine, dialect: str | None = None, name: str = "XMALIGN"
) -> tuple[str, str]:
    """The G-code of ``plan`` (dialect name, program text): the dialect asked for or the
    controller's, the program named ``name`` (Heidenhain wants the file's name)."""
    dialect_name = resolve_dialect(machine, dialect)
    return dialect_name, write_program(plan, machine, make_dialect(dialect_name, machine, name))


def program_name_on_controller(machine: Machine) -> str:
    """The name a followed controller reports for xmalign's program: on a Fanuc the
    number in it (a Fanuc names a program by its number), elsewhere the program file's
    name in the usual calibration (``run``)."""
    return PROGRAM_NUMBER if machine.controller == "fanuc" else PROGRAM_STEM


def program_file(plan_path: Path, machine: Machine, dialect: str | None = None) -> Path:
    """Where :func:`program_step` writes the program by default: ``run<suffix>`` of the
    dialect next to the plan."""
    suffix = PROGRAM_SUFFIX[resolve_dialect(machine, dialect)]
    return plan_path.with_name(f"{PROGRAM_STEM}{suffix}")


def program_step(
    machine: Machine,
    pose: LaunchPose | IdentificationResult,
    plan_path: Path | None,
    program_path: Path | None = None,
    dialect: str | None = None,
    pose_path: Path | None = None,
    line_ids: tuple[str, ...] | None = None,
    machine_path: Path | None = None,
    write_program_file: bool = True,
    check_plan: Callable[[MeasurementPlan], None] | None = None,
    check_outputs: Callable[[list[Path]], None] | None = None,
) -> ProgramStepResult:
    """Plan the lines for the identified pose, write the plan and the G-code.

    The plan is read back from ``plan_path`` as ``xmalign run --plan`` reads it
    (the same plan identity); with ``plan_path`` None it is not written and the
    program is made from the plan as planned. ``program_path`` None: the suffix
    of the dialect next to the plan as ``run<suffix>`` (:func:`program_file`);
    ``write_program_file`` False: the program is only returned (stdout). The
    program is named after its file (``XMALIGN`` without one). The plan records
    the SHA-256 of ``pose_path`` (the file the pose was written to or read from)
    and of ``machine_path``. ``check_outputs(paths)`` may refuse the files about
    to be written (raise) before the planning, ``check_plan(measurement)`` the
    plan before anything is written.
    """
    if isinstance(pose, IdentificationResult):
        pose = pose.to_pose()
    dialect_name = resolve_dialect(machine, dialect)
    if write_program_file and program_path is None:
        if plan_path is None:
            raise ValueError("program_step: a program file needs program_path or plan_path")
        program_path = program_file(plan_path, machine, dialect_name)
    if not write_program_file:
        program_path = None
    if check_outputs is not None:
        check_outputs([path for path in (plan_path, program_path) if path is not None])
    measurement = (
        plan_measurement(machine, pose)
        if line_ids is None
        else plan_measurement(machine, pose, line_ids)
    )
    if check_plan is not None:
        check_plan(measurement)
    files: dict[str, Path] = {}
    plan = measurement.plan
    if plan_path is not None:
        write_plan(plan_path, plan, sources(pose=pose_path, machine=machine_path))
        plan = read_plan(plan_path)
        files["plan"] = plan_path
    name = program_path.stem if program_path is not None else "XMALIGN"
    _, program = program_gcode(plan, machine, dialect_name, name)
    if program_path is not None:
        atomic_write_files({program_path: program.encode("utf-8")})
        files["program"] = program_path
    return ProgramStepResult(measurement, plan, dialect_name, program, files)


#: How a run captures: given the CalibrationRun, capture every point of its plan.
Drive = Callable[[CalibrationRun], None]


def program_drive(events: Iterable[ProgramEvent]) -> Drive:
    """Capture at the stops and dwells a controller running the program reports."""
    return lambda run: capture_program(run, events)


def stepping_drive(mover: MachineMover, machine: Machine) -> Drive:
    """Capture by moving the machine to each target in turn (measuring feed, overrun)."""

    def drive(run: CalibrationRun) -> None:
        step_through(
            run, mover, run.plan.lines, machine.feed_mm_min.measure, machine.measurement.overrun_mm
        )

    return drive


def following_drive(
    position: MachinePositionSource,
    tell: Callable[[str], None],
    machine: Machine,
    timeout_s: float,
    poll_s: float = 0.05,
    check_program: Callable[[], None] = lambda: None,
) -> Drive:
    """Capture while the controller runs the program, at each standstill on a target
    (the units set at each line's pre-position, the machine file's overrun before it);
    ``tell`` says the operator's part (run the program, press cycle start); ``timeout_s``:
    the longest the machine may take to its next stop (``timeouts.machine_s``); ``poll_s``:
    how often the position is read while waiting; ``check_program()`` refuses a
    controller running another program (:class:`xmalign.program_check.ProgramGuard`)."""
    return lambda run: follow_machine(
        run,
        position,
        run.plan.lines,
        tell,
        program_way(machine),
        timeout_s=timeout_s,
        poll_s=poll_s,
        check_program=check_program,
    )


def program_way(machine: Machine) -> ProgramWay:
    """Where the program :func:`program_step` writes for ``machine`` moves it between stops."""
    return ProgramWay(machine.measurement.overrun_mm, float(machine.travel_max_mm[2]))


def controlled_drive(
    controller: ProgramControl,
    program_path: str,
    tell: Callable[[str], None],
    machine: Machine,
    tolerance_mm: float,
    timeout_s: float,
) -> Drive:
    """Capture while xmalign runs its program on the controller (start, hold, resume): the
    program at ``program_path`` as the controller opens it (:func:`write_controller_program`
    wrote it); a point only with the machine at rest within ``tolerance_mm`` of the plan's."""
    program = ControlledProgram(
        controller, program_path, program_way(machine), tolerance_mm, timeout_s
    )
    return lambda run: control_program(run, program, tell)


class ControllerProgramFiles(Protocol):
    """Where a controller xmalign runs its program on has it (a ``units.yaml`` section)."""

    @property
    def program(self) -> Path:
        """The program file xmalign writes."""
        ...

    @property
    def cnc_program_path(self) -> str:
        """The same file as the controller opens it."""
        ...

    @property
    def tolerance_mm(self) -> float:
        """A point is captured only with the machine at rest this close to it, mm."""
        ...


def controlled_run_step(
    plan: Plan,
    machine: Machine,
    devices: RunStepDevices,
    output: RunOutput,
    controller: ProgramControl,
    files: ControllerProgramFiles,
    timeout_s: float,
    tell: Callable[[str], None],
) -> CalibrationRun:
    """:func:`run_step` with xmalign running its program on a LinuxCNC: the program written
    for the plan (:func:`write_controller_program`), then started, held and resumed
    (:func:`controlled_drive`). ``xmalign run --config`` and the dry run call this."""
    write_controller_program(plan, machine, "linuxcnc", files.program)
    drive = controlled_drive(
        controller, files.cnc_program_path, tell, machine, files.tolerance_mm, timeout_s
    )
    return run_step(plan, devices, output, drive)


def write_controller_program(plan: Plan, machine: Machine, dialect: str, path: Path) -> str:
    """Write the plan's program for a controller xmalign runs it on: a programmed stop at
    each point instead of the dwell (xmalign resumes it once the point is captured);
    readable by all (the controller may run as another user); replaced on every run (it
    is made from the plan), but never a file xmalign did not write (InputError naming it)."""
    program = write_program(plan, machine, make_dialect(dialect, machine, "run", True))
    refuse_replacing_a_foreign_program(path)
    atomic_write_files({path: program.encode("utf-8")})
    path.chmod(0o644)
    return program


def refuse_replacing_a_foreign_program(path: Path) -> None:
    """InputError when ``path`` holds something else than a program xmalign wrote (its
    mark in the first lines): the controller's folder may hold the shop's own programs.
    A folder, a device or a FIFO there is refused without being opened."""
    refuse_special(path, "the program of units.yaml's machine_position")
    try:
        with path.open("rb") as existing:
            head = existing.read(4096)
    except FileNotFoundError:
        return
    except OSError as error:
        raise InputError(f"{path}: cannot read the program there ({error.strerror})") from error
    if PROGRAM_MARK.encode() not in head:
        raise InputError(
            f"{path}: exists and is not a program xmalign wrote; it is not replaced: move it,"
            " or name another file in units.yaml (machine_position: ... program)"
        )


@dataclass
class RunStepDevices:
    """What a run uses: both units, the interferometer and the clock."""

    launch: PositioningUnit
    receiver: PositioningUnit
    interferometer: Interferometer
    clock: Clock


def open_measurements_step(
    path: Path,
    plan: Plan,
    machine: Machine,
    resume: bool = False,
    environment: EnvironmentMonitor | None = None,
    sim_seed: int | None = None,
) -> RunOutput:
    """Open the measurement file of a run (new, or ``resume``: the one to go on with).

    Locked until closed, recorded for ``plan`` (its SHA-256 and file), with the
    virtual machine's ``sim_seed`` and ``environment``'s columns; a resumed file
    is read with the machine's interferometer ranges. Every run opens its file here.
    """
    limits = ChannelLimits.of_ranges(**machine.interferometer.ranges())
    return open_run_output(path, plan, resume, limits, environment, sim_seed)


def run_step(
    plan: Plan, devices: RunStepDevices, output: RunOutput, drive: Drive
) -> CalibrationRun:
    """Capture every point of ``plan`` into ``output`` (points it holds are skipped).

    The units are locked on every exit; each point is in the file once captured.
    """
    with units_locked_on_exit(devices.launch, devices.receiver):
        run = output.calibration_run(
            plan, devices.launch, devices.receiver, devices.interferometer, devices.clock
        )
        drive(run)
    return run


@dataclass
class PostStepResult:
    """The fitted error tables, the stations they were fitted to, where they were written."""

    post: PostResult
    errors_path: Path
    stations: list[Station] = field(default_factory=list)

    @property
    def tables(self) -> ErrorTableSet:
        return self.post.fit.tables


def read_station(machine: Machine, plan: Plan, measurements_path: Path) -> Station:
    """One station's measurement, read with the machine's interferometer ranges; the file
    must have been recorded for ``plan``."""
    limits = ChannelLimits.of_ranges(**machine.interferometer.ranges())
    recorded = load_measurements(measurements_path, limits)
    check_recorded_plan(recorded, plan, check_points=False)
    return Station(plan, recorded.rows, str(measurements_path))


def post_step(
    machine: Machine,
    stations: Sequence[tuple[Plan, Path]],
    errors_path: Path,
    machine_path: Path | None = None,
    instruments: Instruments | None = None,
    instrument_files: Sequence[FileSource] = (),
    on_fit: Callable[[list[Station]], None] | None = None,
    more_files: Callable[[PostResult], dict[Path, bytes]] | None = None,
) -> PostStepResult:
    """Fit the 21 errors to every station's measurement (and ``instruments``' readings) and
    write the error tables.

    ``stations``: each station's plan (read from its file) and measurement file, in order;
    each file must have been recorded for its plan (:func:`read_station`). The tables name
    ``machine`` and the SHA-256 of each station's measurements and plan, ``machine_path``
    and ``instrument_files``. ``on_fit(stations)`` is told before the fit;
    ``more_files(result)`` adds files written together with the tables (the report): all
    of them, or none.
    """
    read = [read_station(machine, plan, path) for plan, path in stations]
    if instruments is not None:
        check_instrument_files(machine, instruments.trackers, instruments.tracers)
    if on_fit is not None:
        on_fit(read)
    post = post_stations(machine, read, instruments=instruments)
    inputs: list[FileSource] = []
    for plan, path in stations:
        inputs += sources(measurements=path)
        inputs += [plan.source] if plan.source is not None else []
    inputs += sources(machine=machine_path) + list(instrument_files)
    files = {errors_path: error_tables_text(post.fit.tables, inputs, machine).encode("utf-8")}
    if more_files is not None:
        files |= more_files(post)
    atomic_write_files(files)
    return PostStepResult(post, errors_path, read)


def as_left_step(
    machine: Machine, plan: Plan, verification_path: Path, applied: ErrorTables
) -> PostResult:
    """As found / as left: the verification run, measured with the controller's tables
    ``applied`` loaded, posted on its own.

    The file must have been recorded for ``plan``. The result's ``fit`` is the
    machine's own geometry again (as found, measured through the compensation) and
    :meth:`~xmalign.post.evaluate.PostResult.tool_point_errors` what the
    compensation leaves (as left). ``xmalign post --verify-data`` and the dry run's
    ``--verify`` call this one function.
    """
    return post_stations(machine, [read_station(machine, plan, verification_path)], applied)


def comp_step(
    machine: Machine,
    tables: ErrorTableSet,
    out_dir: Path,
    controller: str | None = None,
    more_files: Callable[[Compensation], dict[str, str]] | None = None,
    check_outputs: Callable[[list[Path]], None] | None = None,
) -> Compensation:
    """Fit the controller's model and write all of its files into ``out_dir`` (or none).

    ``more_files(compensation)`` adds files made from the fit (a merged LinuxCNC INI);
    ``check_outputs(paths)`` may refuse the paths about to be written (raise). The
    returned compensation's ``files`` are all that was written. LinuxCNC's volumetric
    component has no fitted tables: :func:`volumetric_comp_step`.
    """
    compensation = compensate(machine, tables, controller or machine.controller)
    if more_files is not None:
        compensation.files.update(more_files(compensation))
    _write_controller_files(out_dir, compensation.files, check_outputs)
    return compensation


def volumetric_comp_step(
    machine: Machine,
    tables: ErrorTableSet,
    out_dir: Path,
    ini: Path,
    check_outputs: Callable[[list[Path]], None] | None = None,
) -> MergedConfig:
    """``linuxcnc-volumetric``: the component's table file and the merged copies of the
    machine's INI and HAL files, written into ``out_dir`` (all or none) as
    :func:`comp_step` writes a controller's tables."""
    merged = merge_config(ini, tables, machine, out_dir)
    _write_controller_files(out_dir, dict(merged.files), check_outputs)
    return merged


def _write_controller_files(
    out_dir: Path, files: dict[str, str], check_outputs: Callable[[list[Path]], None] | None
) -> None:
    paths = {out_dir / name: text.encode("utf-8") for name, text in files.items()}
    if check_outputs is not None:
        check_outputs(list(paths))
    atomic_write_files(paths)
