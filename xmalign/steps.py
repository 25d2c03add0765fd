"""The five calibration steps as functions on role objects and files: the one pipeline.

identify, program, run, post and comp are wired here once; every CLI command,
the dry run (``sim/dry_run.py``, ``sim/two_stations.py``, served and
in-process) and the Monte Carlo study call these functions with real devices
or the simulator's behind the same roles (:mod:`xmalign.roles`). The step layer
writes every pose (:func:`write_pose_step`), opens every measurement file
(:func:`open_measurements_step`), posts one or more stations with the plan check
(:func:`post_step`) and writes every controller's files (:func:`comp_step`,
:func:`volumetric_comp_step`); a command adds only what it shows, by hooks.

The steps keep the promises themselves, for the commands, the dry run and a
script alike (docs/api.md, "What the steps refuse"): an output is never one of
the step's inputs, never a device, FIFO or folder, and an existing file is
replaced only with ``replace=True`` (the commands' ``--force``)
(:func:`check_outputs`); a link is followed to the file it names; a plan or
error tables made for another machine are refused (:func:`check_plan_machine`,
:func:`check_tables_machine`); every file written names the machine file the
:class:`~xmalign.machine.Machine` was read from (:attr:`Machine.source`).

Only what differs between a controller running the program and an operator
stepping the machine is given by the caller: the *drive* of
:func:`run_step` (:func:`program_drive`, :func:`stepping_drive`,
:func:`following_drive`, :func:`controlled_drive`); a run on a controller xmalign
starts and resumes its program on is :func:`controlled_run_step`.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, TypeVar

import numpy as np

from trajectories.gcode import make_dialect, resolve_dialect
from trajectories.gcode.fanuc import PROGRAM_NUMBER
from trajectories.gcode.machine_time import MachineTime
from trajectories.gcode.program import PROGRAM_MARK, write_program
from trajectories.identification_design import IdentificationDesign, design_identification
from trajectories.instruments import (
    InstrumentProgram,
    machine_time_note,
    plan_instrument,
    point_list_files,
    write_instrument_program,
)
from trajectories.lines import LINE_IDS
from trajectories.planner import MeasurementPlan, plan_measurement
from xmalign.beam_search import BeamSearchSettings
from xmalign.calibration import (
    CalibrationRun,
    ControlledProgram,
    ProgramEvent,
    ProgramWay,
    RunOutput,
    capture_program,
    check_run_output,
    control_program,
    follow_machine,
    open_run_output,
    step_through,
)
from xmalign.calibration.controller_lock import ControllerLock, new_run_id, run_id_comment
from xmalign.comp import Compensation, compensate, linuxcnc
from xmalign.comp.linuxcnc_volumetric import MergedConfig, merge_config
from xmalign.environment import EnvironmentMonitor
from xmalign.errors import InputError
from xmalign.formats.common import (
    PathsOf,
    atomic_write_files,
    check_output_folder,
    refuse_overwriting,
    refuse_replacing,
    refuse_special,
    same_file,
    shown_value,
)
from xmalign.formats.common import path_argument as _path
from xmalign.formats.error_tables import ErrorTableSet, error_tables_text, read_error_tables
from xmalign.formats.instrument_checks import UNITS_MM, check_instrument_files
from xmalign.formats.instruments import TrackerPoint, write_tracker_points
from xmalign.formats.measurements import ChannelLimits, check_recorded_plan, load_measurements
from xmalign.formats.plan import Plan, read_plan, write_plan
from xmalign.formats.pose import LaunchPose, write_pose
from xmalign.formats.provenance import FileSource, history_path
from xmalign.formats.session import NOMINAL_STRAIGHTNESS_RANGE_UM, Session, read_session
from xmalign.formats.spatial_analyzer import (
    NAMING,
    read_point_list,
    tracker_file_from_export,
    unmeasured,
)
from xmalign.formats.studies import write_design
from xmalign.formats.tracker_stream import (
    FlyRun,
    program_paths,
    read_tracker_stream,
    write_fly_rows,
)
from xmalign.identification_routine import (
    PoseGuess,
    RoutineDevices,
    RoutineEvent,
    run_identification,
)
from xmalign.identify import IdentificationResult, IdentificationUncertainty, identify
from xmalign.machine import Machine, default_machine_path
from xmalign.post.evaluate import Instruments, PostResult, Station, post_stations
from xmalign.post.instruments import MIN_TRACER_PLACES, Progress
from xmalign.post.stream_assign import StreamAssignment, assign_stream
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
#: Plan targets this far outside the machine's travel are refused, mm.
TRAVEL_TOLERANCE_MM = 1e-3

T = TypeVar("T")


@dataclass(frozen=True)
class Caller:
    """How the caller of a step names the step's files, and what else it reads and writes.

    The Python API keeps the steps' parameter names (``errors_path``) and says
    ``replace=True``; a command names its options (``names={"errors_path": "--out"}``)
    and says ``--force``. ``read``, ``written`` and ``appended`` (a log) are the
    files of the caller's own options (``--units``, ``--report``, ``--log-file``),
    checked together with the step's own: option -> path(s), None when not given.
    """

    names: Mapping[str, str] = field(default_factory=dict)
    read: Mapping[str, PathsOf] = field(default_factory=dict)
    written: Mapping[str, PathsOf] = field(default_factory=dict)
    appended: Mapping[str, PathsOf] = field(default_factory=dict)
    replace_option: str = "replace=True"


#: A script's call: the steps' parameter names, ``replace=True``.
SCRIPT = Caller()


def check_outputs(
    outputs: Mapping[str, PathsOf],
    inputs: Mapping[str, PathsOf],
    replace: bool = False,
    caller: Caller | None = None,
) -> None:
    """Refuse, before any work, outputs that would destroy something.

    ``outputs`` and ``inputs``: the step's files by parameter name (named in messages
    as ``caller`` names them), with the caller's own (:class:`Caller`). Refused: an
    output that is an input or another output (the same file once links are followed,
    or the same device and inode), that exists and is not a regular file (a folder, a
    device, a FIFO, a link that loops), or an existing file without ``replace``. A link
    is followed: its target is what is checked (and written, the link left a link).

    Raises
    ------
    InputError
        Naming the file and the parameters (options) involved.
    OutputError
        A folder, device, FIFO or looping link in an output's place.
    """
    caller = caller or SCRIPT
    named_inputs = {caller.names.get(k, k): v for k, v in inputs.items()} | dict(caller.read)
    named_outputs = {caller.names.get(k, k): v for k, v in outputs.items()} | dict(caller.written)
    refuse_overwriting(named_inputs, named_outputs, caller.appended)
    refuse_replacing(named_outputs, replace, caller.replace_option)


def machine_file(machine: Machine) -> list[FileSource]:
    """The machine file ``machine`` was read from, as a file's input (none: made in code)."""
    return [machine.source] if machine.source is not None else []


def _machine_path(machine: Machine) -> Path | None:
    return Path(machine.source.path) if machine.source is not None else None


def check_argument(value: object, kind: type[T], name: str, what: str) -> T:
    """``value`` when it is a ``kind``; else one InputError naming the argument (a script
    passing a path where a Plan is expected gets this, not an AttributeError)."""
    if not isinstance(value, kind):
        raise InputError(f"{name}: {shown_value(value)} is not {what}")
    return value


def _optional_path(value: object, name: str) -> Path | None:
    return None if value is None else _path(value, name)


def _machine(value: object) -> Machine:
    return check_argument(value, Machine, "machine", "a Machine (load it with load_machine)")


def _plan(value: object, name: str = "plan") -> Plan:
    return check_argument(value, Plan, name, "a Plan (read it with read_plan)")


def _plan_file(plan: Plan) -> Path | None:
    return Path(plan.source.path) if plan.source is not None else None


def _describe(machine: Machine) -> str:
    """``machine`` as a message names it: its file, or that it was made in code."""
    if machine.source is None:
        return "the machine given (made in code)"
    if same_file(Path(machine.source.path), default_machine_path()):
        return "the reference machine"
    return f"machine file {machine.source.path}"


def check_plan_machine(plan: Plan, machine: Machine) -> list[str]:
    """Refuse a plan made for another machine; warnings where only the file differs.

    A plan names its machine and records ``machine_sha256``
    (:meth:`Machine.geometry_sha256`: name, chain, travel, receiver offset, spindle
    angle); another name or geometry is fatal (the plan's points and angles would be
    another machine's). A machine file whose bytes differ from the one the plan was
    made with, with the same geometry (uncertainties, feeds, ranges edited), is a
    warning. Every target must lie within the machine's travel.

    Raises
    ------
    InputError
        Naming the plan's file, both machines, or the first target outside the travel.
    """
    where = str(_plan_file(plan) or "the plan")
    _refuse_another_machine(where, "plan", plan.machine, plan.extra.get("machine_sha256"), machine)
    for line in plan.lines:
        outside = ~machine.within_travel(line.target_points_mm(), TRAVEL_TOLERANCE_MM)
        if outside.any():
            index = int(np.argmax(outside))
            raise InputError(
                f"{where}: line {line.id} target {index}"
                f" {np.round(line.target_points_mm()[index], 3).tolist()} mm lies outside the"
                f" travel of machine '{machine.name}'"
            )
    made_with = plan.history.input("machine") if plan.history is not None else None
    return _other_machine_file(where, made_with, machine)


def check_pose_machine(pose: LaunchPose, machine: Machine) -> list[str]:
    """Refuse a pose identified on another machine; warnings where only the file differs.

    A pose written with a machine names it and records ``machine_sha256``, as a plan
    does (:func:`check_plan_machine`: another name or geometry is fatal, another machine
    file of the same geometry a warning). A pose that does not name its machine (written
    before poses did, or ``identify --input`` without ``--machine``) is not checked.

    Raises
    ------
    InputError
        Naming the pose's file and both machines.
    """
    if pose.machine is None:
        return []
    where = str(pose.source.path) if pose.source is not None else "the pose"
    _refuse_another_machine(where, "pose", pose.machine, pose.machine_sha256, machine)
    made_with = pose.history.input("machine") if pose.history is not None else None
    return _other_machine_file(where, made_with, machine)


def _refuse_another_machine(
    where: str, what: str, name: str, recorded: object, machine: Machine
) -> None:
    """InputError when ``what`` (a plan, a pose) at ``where`` names another machine than
    ``machine``, or records another geometry (``recorded``: its ``machine_sha256``)."""
    if name != machine.name or recorded not in (None, machine.geometry_sha256()):
        identity = f", machine_sha256 {str(recorded)[:12]}..." if recorded else ""
        raise InputError(
            f"{where} was made for machine '{name}'{identity}, not for"
            f" {_describe(machine)} ('{machine.name}'): give the machine file the {what} was"
            " made with"
        )


def _other_machine_file(where: str, made_with: FileSource | None, machine: Machine) -> list[str]:
    """A warning when ``where`` was made with a machine file other than ``machine``'s."""
    given = machine.source
    if made_with is None or given is None or made_with.sha256 == given.sha256:
        return []
    return [
        f"{where} was made with machine file {made_with.path} (SHA-256"
        f" {made_with.sha256[:12]}...), not {given.path} ({given.sha256[:12]}...): the same"
        " chain and travel, another file; check that its edits are meant"
    ]


def check_tables_machine(tables: ErrorTableSet, machine: Machine) -> list[str]:
    """Refuse error tables measured on another machine; warnings to be shown.

    Fatal: another chain or travel (the tables' file names the machine it was
    measured on), or a table whose positions all lie outside the travel. A
    warning: another name, a file that does not say (version 1), or another
    machine file with the same chain and travel. Tables not read from a file (made in
    code) are checked against the travel only.

    Raises
    ------
    InputError
        Naming the tables' file and what differs.
    """
    tables.check_within_travel(machine.travel_min_mm, machine.travel_max_mm, machine.name)
    if tables.history is None:  # made in code, not read from a file
        return []
    notes = tables.check_machine(machine)
    return notes + _other_machine_file(tables.source, tables.history.input("machine"), machine)


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
    machine: Machine,
    count: int,
    out: str | Path | None = None,
    replace: bool = False,
    caller: Caller | None = None,
) -> IdentificationDesign:
    """The identification positions for ``count`` alignments (``warnings`` to be shown);
    written to ``out`` (with the SHA-256 of the machine's file) when given
    (:func:`check_outputs`, before the design)."""
    machine, out = _machine(machine), _optional_path(out, "out")
    check_argument(count, int, "count", "a whole number of alignments")
    check_outputs({"out": out}, {"machine": _machine_path(machine)}, replace, caller)
    design = design_identification(machine, count)
    if out is not None:
        write_design(
            out, machine.name, design.machine_mm, design.pose_covariance, machine_file(machine)
        )
    return design


def write_pose_step(
    path: str | Path,
    result: IdentificationResult,
    session_path: str | Path | None = None,
    machine: Machine | None = None,
    replace: bool = False,
    caller: Caller | None = None,
) -> Path:
    """Write the identified pose (``xmalign program`` reads it) with the SHA-256 of the
    session it was solved from and of ``machine``'s file, naming ``machine``
    (:func:`check_pose_machine`). Every pose file is written here, never over the
    session, the machine file or an existing file without ``replace``
    (:func:`check_outputs`)."""
    path, session_path = _path(path, "path"), _optional_path(session_path, "session_path")
    check_argument(result, IdentificationResult, "result", "an IdentificationResult")
    machine = None if machine is None else _machine(machine)
    inputs = {"session_path": session_path, "machine": _machine_path(machine) if machine else None}
    check_outputs({"path": path}, inputs, replace, caller)
    session = [FileSource.of("session", session_path)] if session_path is not None else []
    pose = result.to_pose()
    if machine is not None:
        pose.machine, pose.machine_sha256 = machine.name, machine.geometry_sha256()
    write_pose(path, pose, session + (machine_file(machine) if machine else []))
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
    replace: bool = False,
    caller: Caller | None = None,
    search: BeamSearchSettings | None = None,
) -> IdentifyStepResult:
    """Align at each position (session written as it goes, resumed), then solve the pose.

    With ``search``, the first alignment finds the beam itself where the machine
    file gives no azimuth (:func:`~xmalign.beam_search.search_first_beam`).
    The units are locked on every exit. ``uncertainty`` defaults to the
    machine file's ``uncertainty`` section. With ``pose_path`` the pose is
    written there (:func:`write_pose_step`; checked before the first alignment).
    """
    machine, session_path = _machine(machine), _path(session_path, "session_path")
    pose_path = _optional_path(pose_path, "pose_path")
    machine_path = {"machine": _machine_path(machine)}
    # the session is resumed, never replaced; the pose is written at the end
    check_outputs({"session_path": session_path}, machine_path, True, caller)
    pose_inputs = {"session_path": session_path} | machine_path
    check_outputs({"pose_path": pose_path}, pose_inputs, replace, caller)
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
            search=search,
        )
    if uncertainty is None:
        uncertainty = IdentificationUncertainty.from_machine(machine.uncertainty)
    result = identify(session, method, uncertainty, str(session_path))
    if pose_path is not None:
        write_pose_step(pose_path, result, session_path, machine, replace, caller)
    return IdentifyStepResult(result, session, session_path)


def solve_step(
    session_path: Path,
    uncertainty: IdentificationUncertainty,
    method: str = "joint",
    machine: Machine | None = None,
) -> IdentifyStepResult:
    """The pose from a recorded session (``xmalign identify --input``), read with the
    machine's straightness range (the nominal one without a machine file)."""
    session_path = _path(session_path, "session_path")
    machine = None if machine is None else _machine(machine)
    range_um = (
        machine.interferometer.straightness_range_um
        if machine is not None
        else NOMINAL_STRAIGHTNESS_RANGE_UM
    )
    session = read_session(session_path, range_um)
    result = identify(session, method, uncertainty, str(session_path))
    return IdentifyStepResult(result, session, session_path)


@dataclass
class ProgramStepResult:
    """The measurement plan (as read back from its file) and the G-code program."""

    measurement: MeasurementPlan
    plan: Plan
    dialect: str
    program: str
    files: dict[str, Path] = field(default_factory=dict)
    #: What the check of the pose found (another machine file of the same machine).
    checks: list[str] = field(default_factory=list)

    @property
    def warnings(self) -> list[str]:
        return self.checks + list(self.measurement.warnings)


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


def _dialect_name(caller: Caller | None) -> str:
    """How ``caller`` names the dialect argument (``--dialect`` for a command)."""
    return (caller or SCRIPT).names.get("dialect", "dialect")


def _line_ids(value: object, caller: Caller) -> tuple[str, ...] | None:
    """``line_ids`` as given when they are distinct lines of :data:`LINE_IDS`; else one
    line naming the argument (the command's ``--lines``)."""
    if value is None:
        return None
    name = caller.names.get("line_ids", "line_ids")
    chosen = tuple(value) if isinstance(value, tuple | list) else None
    if (
        not chosen
        or any(line not in LINE_IDS for line in chosen)
        or len(set(chosen)) != len(chosen)
    ):
        shown = f"'{','.join(map(str, chosen))}'" if chosen is not None else shown_value(value)
        raise InputError(
            f"{name} {shown}: give distinct lines out of {', '.join(LINE_IDS)}, comma-separated"
        )
    return chosen


def program_step(
    machine: Machine,
    pose: LaunchPose | IdentificationResult,
    plan_path: str | Path | None,
    program_path: str | Path | None = None,
    dialect: str | None = None,
    pose_path: str | Path | None = None,
    line_ids: tuple[str, ...] | None = None,
    write_program_file: bool = True,
    check_plan: Callable[[MeasurementPlan], None] | None = None,
    replace: bool = False,
    caller: Caller | None = None,
    max_length_mm: float | None = None,
) -> ProgramStepResult:
    """Plan the lines for the identified pose, write the plan and the G-code.

    ``max_length_mm`` cuts every line to at most that length (a try-out).
    The plan is read back from ``plan_path`` as ``xmalign run --plan`` reads it
    (the same plan identity); with ``plan_path`` None it is not written and the
    program is made from the plan as planned. ``program_path`` None: the suffix
    of the dialect next to the plan as ``run<suffix>`` (:func:`program_file`);
    ``write_program_file`` False: the program is only returned (stdout). The
    program is named after its file (``XMALIGN`` without one). The plan records
    the SHA-256 of ``pose_path`` (the file the pose was written to or read from;
    by default the file a ``LaunchPose`` was read from) and of the machine's file.
    The pose must have been identified on ``machine`` (:func:`check_pose_machine`; the
    result's ``warnings`` hold what it found). The plan and the program are checked
    before the planning (:func:`check_outputs`:
    never the pose's or the machine's file, an existing file only with ``replace``);
    ``check_plan(measurement)`` may refuse the plan before anything is written.
    """
    machine = _machine(machine)
    plan_path, program_path = (
        _optional_path(plan_path, "plan_path"),
        _optional_path(program_path, "program_path"),
    )
    pose_path = _optional_path(pose_path, "pose_path")
    line_ids = _line_ids(line_ids, caller or SCRIPT)
    if isinstance(pose, IdentificationResult):
        pose = pose.to_pose()
    check_argument(pose, LaunchPose, "pose", "a LaunchPose or an IdentificationResult")
    checks = check_pose_machine(pose, machine)
    if pose_path is None and pose.source is not None:  # read from a file: that file
        pose_path = Path(pose.source.path)
    dialect_name = resolve_dialect(machine, dialect, _dialect_name(caller))
    if write_program_file and program_path is None:
        if plan_path is None:
            raise InputError("program_step: a program file needs program_path or plan_path")
        program_path = program_file(plan_path, machine, dialect_name)
    if not write_program_file:
        program_path = None
    check_outputs(
        {"plan_path": plan_path, "program_path": program_path},
        {"pose_path": pose_path, "machine": _machine_path(machine)},
        replace,
        caller,
    )
    measurement = plan_measurement(
        machine, pose, LINE_IDS if line_ids is None else line_ids, max_length_mm
    )
    if check_plan is not None:
        check_plan(measurement)
    files: dict[str, Path] = {}
    plan = measurement.plan
    if plan_path is not None:
        pose_file = [FileSource.of("pose", pose_path)] if pose_path is not None else []
        write_plan(plan_path, plan, pose_file + machine_file(machine))
        plan = read_plan(plan_path)
        files["plan"] = plan_path
    name = program_path.stem if program_path is not None else "XMALIGN"
    _, program = program_gcode(plan, machine, dialect_name, name)
    if program_path is not None:
        atomic_write_files({program_path: program.encode("utf-8")})
        files["program"] = program_path
    return ProgramStepResult(measurement, plan, dialect_name, program, files, checks)


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
        controller,
        program_path,
        program_way(machine),
        tolerance_mm,
        timeout_s,
        slowest_feed_mm_min=min(machine.feed_mm_min.measure, machine.transit_feed_mm_min),
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
    run_id = new_run_id()
    with ControllerLock(files.program, run_id, output.writer.path):  # one run per controller
        write_controller_program(plan, machine, "linuxcnc", files.program, run_id)
        drive = controlled_drive(
            controller, files.cnc_program_path, tell, machine, files.tolerance_mm, timeout_s
        )
        return run_step(plan, devices, output, drive)


def write_controller_program(
    plan: Plan, machine: Machine, dialect: str, path: Path, run_id: str
) -> str:
    """Write the plan's program for a controller xmalign runs it on: a programmed stop at
    each point instead of the dwell (xmalign resumes it once the point is captured), the
    run's id in a comment after xmalign's mark; readable by all (the controller may run
    as another user); replaced on every run (it is made from the plan), but never a file
    xmalign did not write (InputError naming it)."""
    language = make_dialect(dialect, machine, "run", True)
    lines = write_program(plan, machine, language).splitlines(keepends=True)
    mark = next(number for number, line in enumerate(lines) if PROGRAM_MARK in line)
    lines.insert(mark + 1, language.comment(run_id_comment(run_id)) + "\n")
    program = "".join(lines)
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


def check_run_step(
    path: str | Path,
    plan: Plan,
    machine: Machine,
    resume: bool = False,
    caller: Caller | None = None,
) -> list[str]:
    """Refuse a run that cannot start, before any device is opened; warnings to be shown.

    The plan must be for ``machine`` (:func:`check_plan_machine`); the measurement
    file never the plan's or the machine's file (nor the caller's), never a folder,
    device, FIFO or looping link, and an existing file with points only to
    ``resume`` (measurements are never replaced, whatever ``replace`` a caller has).

    Raises
    ------
    InputError
        Naming the file and what is wrong.
    """
    path, plan, machine = _path(path, "path"), _plan(plan), _machine(machine)
    notes = check_plan_machine(plan, machine)
    inputs = {"plan": _plan_file(plan), "machine": _machine_path(machine)}
    check_outputs({"path": path}, inputs, True, caller)
    check_run_output(path, resume)
    return notes


def open_measurements_step(
    path: str | Path,
    plan: Plan,
    machine: Machine,
    resume: bool = False,
    environment: EnvironmentMonitor | None = None,
    sim_seed: int | None = None,
    caller: Caller | None = None,
) -> RunOutput:
    """Open the measurement file of a run (new, or ``resume``: the one to go on with).

    Checked first (:func:`check_run_step`); locked until closed, recorded for
    ``plan`` (its SHA-256 and file), with the virtual machine's ``sim_seed`` and
    ``environment``'s columns; a resumed file is read with the machine's
    interferometer ranges. Every run opens its file here.
    """
    notes = check_run_step(path, plan, machine, resume, caller)
    limits = ChannelLimits.of_ranges(**machine.interferometer.ranges())
    output = open_run_output(Path(path), plan, resume, limits, environment, sim_seed)
    output.warnings[:0] = notes
    return output


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
    """The fit, the error tables as written (read back from ``errors_path``, as ``xmalign
    comp`` reads them: their history names the file), the stations they were fitted to."""

    post: PostResult
    errors_path: Path
    tables: ErrorTableSet
    stations: list[Station] = field(default_factory=list)
    #: What the checks of the inputs found (another machine file of the same machine...).
    warnings: list[str] = field(default_factory=list)


def read_station(machine: Machine, plan: Plan, measurements_path: Path) -> Station:
    """One station's measurement, read with the machine's interferometer ranges; the file
    must have been recorded for ``plan``."""
    limits = ChannelLimits.of_ranges(**machine.interferometer.ranges())
    recorded = load_measurements(measurements_path, limits)
    check_recorded_plan(recorded, plan, check_points=False)
    return Station(plan, recorded.rows, str(measurements_path))


def post_step(
    machine: Machine,
    stations: Sequence[tuple[Plan, str | Path]],
    errors_path: str | Path,
    instruments: Instruments | None = None,
    instrument_files: Sequence[FileSource] = (),
    on_fit: Callable[[list[Station]], None] | None = None,
    more_files: Callable[[PostResult], dict[Path, bytes]] | None = None,
    replace: bool = False,
    caller: Caller | None = None,
    progress: Progress | None = None,
) -> PostStepResult:
    """Fit the 21 errors to every station's measurement (and ``instruments``' readings) and
    write the error tables.

    ``stations``: each station's plan (read from its file) and measurement file, in order;
    each plan must be for ``machine`` (:func:`check_plan_machine`), each file recorded for
    its plan (:func:`read_station`) and given once. The tables name ``machine`` and the
    SHA-256 of each station's measurements and plan, of the machine's file and of
    ``instrument_files``; they never replace one of these, nor an existing file without
    ``replace`` (:func:`check_outputs`, before anything is read). ``on_fit(stations)`` is
    told before the fit; ``more_files(result)`` adds files written together with the
    tables (the report, named in ``caller.written``): all of them, or none. The result's
    ``tables`` are read back from ``errors_path``: given to :func:`comp_step`, the
    controller files' history names that file.
    ``progress(done, total, what)`` is told how far the instruments' fit is
    (:func:`xmalign.post.instruments.fit_joint`).
    """
    machine, errors_path = _machine(machine), _path(errors_path, "errors_path")
    pairs = _stations(stations)
    notes = [note for plan, _ in pairs for note in check_plan_machine(plan, machine)]
    inputs = _post_inputs(machine, pairs, instrument_files)
    check_outputs({"errors_path": errors_path}, inputs, replace, caller)
    read = [read_station(machine, plan, path) for plan, path in pairs]
    if instruments is not None:
        check_instrument_files(machine, instruments.trackers, instruments.tracers)
    if on_fit is not None:
        on_fit(read)
    post = fit_step(machine, read, instruments, progress=progress)
    history: list[FileSource] = []
    for plan, path in pairs:
        history += [FileSource.of("measurements", path)]
        history += [plan.source] if plan.source is not None else []
    history += machine_file(machine) + list(instrument_files)
    files = {errors_path: error_tables_text(post.fit.tables, history, machine).encode("utf-8")}
    if more_files is not None:
        more = more_files(post)
        check_outputs({"more_files": list(more)}, inputs, True, caller)
        files |= more
    atomic_write_files(files)
    return PostStepResult(post, errors_path, read_error_tables(errors_path), read, notes)


def _stations(stations: object) -> list[tuple[Plan, Path]]:
    """The (plan, measurement file) pairs of :func:`post_step`, each file given once."""
    if isinstance(stations, str | bytes | os.PathLike) or not isinstance(stations, Sequence):
        raise InputError(
            f"stations: {shown_value(stations)} is not a list of (plan, measurement file) pairs"
        )
    pairs: list[tuple[Plan, Path]] = []
    for number, pair in enumerate(stations, start=1):
        if not isinstance(pair, tuple | list) or len(pair) != 2:
            raise InputError(
                f"stations: station {number}: {shown_value(pair)} is not a (plan, file) pair"
            )
        plan = _plan(pair[0], f"stations: station {number}: the plan")
        path = _path(pair[1], f"stations: station {number}: the measurement file")
        _refuse_twice(path, [p for _, p in pairs])
        pairs.append((plan, path))
    return pairs


def _refuse_twice(path: Path, earlier: list[Path]) -> None:
    """A measurement file given for two stations, or a copy of one: its points would count
    twice (a copy is found by its bytes' SHA-256)."""
    for number, other in enumerate(earlier, start=1):
        if same_file(path, other) or (
            path.is_file()
            and other.is_file()
            and FileSource.of("m", path).sha256 == FileSource.of("m", other).sha256
        ):
            raise InputError(
                f"{path}: given for station {len(earlier) + 1} is station {number}'s measurement"
                f" ({other}) or a copy of it; its points would count twice (give each station's"
                " data once)"
            )


def _post_inputs(
    machine: Machine, pairs: list[tuple[Plan, Path]], instrument_files: Sequence[FileSource]
) -> dict[str, PathsOf]:
    """The files :func:`post_step` reads, by parameter name (never written over)."""
    inputs: dict[str, PathsOf] = {
        "measurements": [path for _, path in pairs],
        "plan": [p for p in map(_plan_file, (plan for plan, _ in pairs)) if p is not None],
        "machine": _machine_path(machine),
    }
    for source in instrument_files:
        listed = inputs.setdefault(source.role, [])
        assert isinstance(listed, list)
        listed.append(Path(source.path))
    return inputs


def as_left_step(
    machine: Machine, plan: Plan, verification_path: Path, applied: ErrorTables
) -> PostResult:
    """As found / as left: the verification run, measured with the controller's tables
    ``applied`` loaded, posted on its own.

    The file must have been recorded for ``plan``. The result's ``fit`` is the
    machine's own geometry again (as found, measured through the compensation) and
    :meth:`~xmalign.post.evaluate.PostResult.tool_point_errors` what the
    compensation leaves (as left). ``xmalign post --verify-data`` and the dry run's
    ``--verify`` call this one function. The plan must be for ``machine``
    (:func:`check_plan_machine`).
    """
    machine, plan = _machine(machine), _plan(plan)
    check_plan_machine(plan, machine)
    station = read_station(machine, plan, _path(verification_path, "verification_path"))
    return fit_step(machine, [station], applied=applied)


def comp_step(
    machine: Machine,
    tables: ErrorTableSet,
    out_dir: str | Path,
    controller: str | None = None,
    ini: str | Path | None = None,
    replace: bool = False,
    caller: Caller | None = None,
    on_warning: Callable[[str], None] | None = None,
) -> Compensation:
    """Fit the controller's model and write all of its files into ``out_dir`` (or none).

    The tables must have been measured on ``machine`` (:func:`check_tables_machine`:
    another chain or travel refused, another name or machine file told to
    ``on_warning``, by default a Python warning). ``ini`` (LinuxCNC only): the
    machine's INI, read and checked before the fit; its joints' comp files and a
    merged copy ``<ini stem>-xmalign<suffix>`` are written too (the returned
    ``merged_ini`` and ``joints``), and a ``BACKLASH`` LinuxCNC would ignore is told
    to ``on_warning``. No file replaces the tables', the machine's or the INI's file
    (or the caller's inputs), nor an existing file without ``replace``
    (:func:`check_outputs`). The returned compensation's ``files`` are all that was
    written. LinuxCNC's volumetric component has no fitted tables:
    :func:`volumetric_comp_step`.
    """
    machine, out_dir = _machine(machine), _path(out_dir, "out_dir")
    ini_path = _optional_path(ini, "ini")
    tables = check_argument(tables, ErrorTableSet, "tables", "an ErrorTableSet (read_error_tables)")
    names = (caller or SCRIPT).names
    check_output_folder(out_dir, names.get("out_dir", "out_dir"))
    controller = controller or machine.controller
    machine_ini = None if ini_path is None else _machine_ini(machine, ini_path, controller, names)
    notes = check_tables_machine(tables, machine)
    compensation = compensate(machine, tables, controller)
    if machine_ini is not None:
        files = compensation.files | linuxcnc.ini_files(
            compensation.fit, machine, machine_ini, out_dir
        )
        compensation = dataclasses.replace(
            compensation,
            files=files,
            merged_ini=out_dir / machine_ini.merged_name,
            joints=tuple(machine_ini.joints),
        )
        notes += linuxcnc.backlash_warnings(machine_ini, machine)
    inputs = _comp_inputs(machine, tables) | {"ini": ini_path}
    _write_controller_files(out_dir, compensation.files, inputs, replace, caller)
    for note in notes:
        (on_warning or _python_warning)(note)
    return compensation


def _machine_ini(
    machine: Machine, path: Path, controller: str, names: Mapping[str, str]
) -> linuxcnc.MachineIni:
    if controller != linuxcnc.NAME:
        raise InputError(
            f"{names.get('ini', 'ini')} is for the linuxcnc controller, not '{controller}'"
        )
    return linuxcnc.read_machine_ini(machine, path)


def volumetric_comp_step(
    machine: Machine,
    tables: ErrorTableSet,
    out_dir: str | Path,
    ini: str | Path,
    replace: bool = False,
    caller: Caller | None = None,
    on_warning: Callable[[str], None] | None = None,
) -> MergedConfig:
    """``linuxcnc-volumetric``: the component's table file and the merged copies of the
    machine's INI and HAL files, written into ``out_dir`` (all or none) as
    :func:`comp_step` writes a controller's tables, with its checks (the INI an input);
    what the merge warns about (``MergedConfig.warnings``) goes to ``on_warning`` too."""
    machine, out_dir, ini = _machine(machine), _path(out_dir, "out_dir"), _path(ini, "ini")
    tables = check_argument(tables, ErrorTableSet, "tables", "an ErrorTableSet (read_error_tables)")
    check_output_folder(out_dir, (caller or SCRIPT).names.get("out_dir", "out_dir"))
    notes = check_tables_machine(tables, machine)
    merged = merge_config(ini, tables, machine, out_dir)
    inputs = _comp_inputs(machine, tables) | {"ini": ini}
    _write_controller_files(out_dir, dict(merged.files), inputs, replace, caller)
    for note in [*notes, *merged.warnings]:
        (on_warning or _python_warning)(note)
    return merged


def _python_warning(text: str) -> None:
    warnings.warn(text, UserWarning, stacklevel=3)


def _comp_inputs(machine: Machine, tables: ErrorTableSet) -> dict[str, PathsOf]:
    read_from = Path(tables.source) if tables.history is not None else None
    return {"tables": read_from, "machine": _machine_path(machine)}


def _write_controller_files(
    out_dir: Path,
    files: dict[str, str],
    inputs: Mapping[str, PathsOf],
    replace: bool,
    caller: Caller | None,
) -> None:
    paths = {out_dir / name: text.encode("utf-8") for name, text in files.items()}
    check_outputs({"out_dir": list(paths)}, inputs, replace, caller)
    atomic_write_files(paths)


def fit_step(
    machine: Machine,
    stations: Sequence[Station],
    instruments: Instruments | None = None,
    applied: ErrorTables | None = None,
    progress: Progress | None = None,
) -> PostResult:
    """The fit of :func:`post_step` with nothing read or written: the stations' lines as
    measured (``applied``: the tables loaded while measuring) and ``instruments``'
    readings (``progress``: :func:`xmalign.post.instruments.fit_joint`'s). The studies
    that compare strategies on virtual machines call it."""
    return post_stations(_machine(machine), list(stations), applied, instruments, progress)


#: The instruments :func:`instrument_program_step` plans for.
INSTRUMENTS = ("tracker", "tracer")


@dataclass
class InstrumentProgramStepResult:
    """An instrument's program: what it measures, its G-code and machine time (one run or
    place), and what the operator is told (``notes``); ``files``: what was written."""

    instrument: str
    program: InstrumentProgram
    gcode: str
    machine_time: MachineTime
    notes: list[str] = field(default_factory=list)
    files: dict[str, Path] = field(default_factory=dict)


def write_instrument_step(
    machine: Machine,
    program: InstrumentProgram,
    program_path: str | Path | None = None,
    points_path: str | Path | None = None,
    dialect: str | None = None,
    title: str = "xmalign",
    replace: bool = False,
    caller: Caller | None = None,
) -> tuple[str, MachineTime, dict[str, Path]]:
    """The G-code of an instrument's program (the dialect asked for or the controller's,
    named after its file) and its machine time; written to ``program_path``, the point
    list for the instrument's software to ``points_path`` with its ``NAME.history`` (each
    when given; checked first, :func:`check_outputs`). Every instrument program is made
    here."""
    machine = _machine(machine)
    program_path = _optional_path(program_path, "program_path")
    points_path = _optional_path(points_path, "points_path")
    points = [points_path, history_path(points_path)] if points_path is not None else None
    outputs = {"program_path": program_path, "points_path": points}
    check_outputs(outputs, {"machine": _machine_path(machine)}, replace, caller)
    name = program_path.stem if program_path is not None else "XMALIGN"
    dialect_name = resolve_dialect(machine, dialect, _dialect_name(caller))
    dialect_made = make_dialect(dialect_name, machine, name)
    gcode, time = write_instrument_program(program, machine, dialect_made, title)
    files: dict[Path, bytes] = {}
    if points_path is not None:
        files.update(point_list_files(points_path, program, machine.smr_offset))
    if program_path is not None:
        files[program_path] = gcode.encode("utf-8")
    atomic_write_files(files)
    written = {"program": program_path, "points": points_path}
    return gcode, time, {key: path for key, path in written.items() if path is not None}


#: Tracer places :func:`instrument_program_step` plans: the fewest that place the points
#: in space (the fit needs them), the most it proposes, and the default.
TRACER_PLACES = (MIN_TRACER_PLACES, 12, 4)


def check_instrument_request(
    instrument: object,
    on_the_fly: bool,
    places: object,
    caller: Caller | None = None,
    simultaneous: bool = False,
) -> int:
    """The tracer places to plan (:data:`TRACER_PLACES`' default when ``places`` is None);
    one line naming the argument (the command's option) for an unknown instrument,
    ``on_the_fly`` with a tracer, ``simultaneous`` or ``places`` with a tracker, or
    ``places`` outside 4 to 12."""
    name = (caller or SCRIPT).names.get
    if instrument not in INSTRUMENTS:
        raise InputError(
            f"{name('instrument', 'instrument')} {shown_value(instrument)} is not known"
            f" (known: {', '.join(INSTRUMENTS)})"
        )
    if instrument == "tracer" and on_the_fly:
        raise InputError(
            f"{name('on_the_fly', 'on_the_fly')} is for {name('instrument', 'instrument')}"
            " tracker (a tracer measures lengths)"
        )
    if instrument == "tracker" and simultaneous:
        raise InputError(
            f"{name('simultaneous', 'simultaneous')} is for {name('instrument', 'instrument')}"
            " tracer (tracers following the SMR)"
        )
    if places is None:
        return TRACER_PLACES[2]
    if instrument == "tracker":
        raise InputError(
            f"{name('places', 'places')} is for {name('instrument', 'instrument')} tracer"
        )
    low, high, _ = TRACER_PLACES
    if isinstance(places, bool) or not isinstance(places, int) or not low <= places <= high:
        raise InputError(
            f"{name('places', 'places')} {shown_value(places)}: give {low} to {high} tracer places"
        )
    return places


def instrument_program_step(
    machine: Machine,
    instrument: str,
    on_the_fly: bool = False,
    places: int | None = None,
    program_path: str | Path | None = None,
    points_path: str | Path | None = None,
    dialect: str | None = None,
    replace: bool = False,
    caller: Caller | None = None,
    simultaneous: bool = False,
) -> InstrumentProgramStepResult:
    """Plan a laser-tracker (points, or paths ``on_the_fly``) or laser-tracer (``places``
    places, 4 by default, the same points from each; ``simultaneous``: every tracer
    following the SMR in the same run) calibration over the whole travel with the machine
    file's SMR positions, or three proposed (:func:`trajectories.instruments.plan_instrument`),
    and write its program and point list (:func:`write_instrument_step`); the request is
    checked first (:func:`check_instrument_request`).

    ``notes`` say where the instrument stands, which SMR to mount when, the machine time
    and how well the plan determines the volumetric error (the machine file's instrument
    uncertainties).
    """
    machine = _machine(machine)
    places = check_instrument_request(instrument, on_the_fly, places, caller, simultaneous)
    plan = plan_instrument(machine, instrument, on_the_fly, places, simultaneous)
    gcode, time, files = write_instrument_step(
        machine,
        plan.program,
        program_path,
        points_path,
        dialect,
        f"xmalign {instrument}",
        replace,
        caller,
    )
    notes = [*plan.notes, machine_time_note(plan, time)]
    return InstrumentProgramStepResult(instrument, plan.program, gcode, time, notes, files)


@dataclass
class ImportTrackerStepResult:
    """The tracker points imported (:func:`import_tracker_step`) and the names of the point
    list's points that no row measured."""

    points: list[TrackerPoint]
    unmeasured: list[str]


#: The export's point names a tracker's software may write (:data:`NAMING`), by default
#: SpatialAnalyzer's.
DEFAULT_NAMING = "collection-group-target"


def import_tracker_step(
    export_path: str | Path,
    points_path: str | Path,
    out: str | Path,
    machine: Machine,
    station: str = "T1",
    replace: bool = False,
    caller: Caller | None = None,
    naming: str = DEFAULT_NAMING,
    units: str = "mm",
) -> ImportTrackerStepResult:
    """A tracker's export (SpatialAnalyzer's ASCII variants or a plain ``Name,X,Y,Z``
    list, its point names as ``naming`` says, lengths in ``units``: mm, in or m) turned
    into the tracker-points file ``out`` (for :func:`post_step`'s ``instruments``):
    target names are the indices of the point list at ``points_path``
    (:func:`write_instrument_step`), the export's groups the runs. The distances between
    the points must be the commanded moves' (another unit, names shifted against the list:
    refused at the first row that does not fit). ``out`` never replaces an input, nor an
    existing file without ``replace``."""
    caller = caller or SCRIPT
    export_path, points_path = _path(export_path, "export_path"), _path(points_path, "points_path")
    out, machine = _path(out, "out"), _machine(machine)
    for name, value, known in (("naming", naming, NAMING), ("units", units, UNITS_MM)):
        if value not in known:
            option = caller.names.get(name, name)
            raise InputError(f"{option} '{value}' is not known ({', '.join(known)})")
    inputs = {
        "export_path": export_path,
        "points_path": points_path,
        "machine": _machine_path(machine),
    }
    check_outputs({"out": out}, inputs, replace, caller)
    listed = read_point_list(points_path)
    file = tracker_file_from_export(machine, export_path, listed, station, naming, units)
    made_from = [FileSource.of("export", export_path), FileSource.of("points", points_path)]
    write_tracker_points(out, file.points, made_from)
    return ImportTrackerStepResult(file.points, unmeasured(listed, file))


@dataclass(frozen=True)
class StreamImportResult:
    """What :func:`import_stream_step` wrote: the rows kept and dropped per (station, run)."""

    out: Path
    runs: list[tuple[str, int, StreamAssignment]]

    @property
    def rows(self) -> int:
        return sum(len(a.sample) for _, _, a in self.runs)


def import_stream_step(
    stream_path: str | Path,
    points_path: str | Path,
    out: str | Path,
    machine: Machine,
    replace: bool = False,
    caller: Caller | None = None,
) -> StreamImportResult:
    """A tracker's stream of an on-the-fly program turned into the tracker-points file
    ``out`` (docs/formats.md).

    Each (station, run) of the stream is assigned to the measuring paths of the point
    list at ``points_path`` (:func:`xmalign.post.stream_assign.assign_stream`); the rows
    carry the commanded tool point at the path's start and end (the list's SMR points
    less the machine's ``smr_offset_mm``) and the SHA-256 of both inputs. ``out`` never
    replaces an input, nor an existing file without ``replace``.
    """
    stream_path, points_path = _path(stream_path, "stream_path"), _path(points_path, "points_path")
    out, machine = _path(out, "out"), _machine(machine)
    inputs = {
        "stream_path": stream_path,
        "points_path": points_path,
        "machine": _machine_path(machine),
    }
    check_outputs({"out": out}, inputs, replace, caller)
    stream = read_tracker_stream(stream_path)
    starts, ends = program_paths(read_point_list(points_path), str(points_path))
    smr = machine.smr_offset
    assigned, rows = [], []
    for run in stream.runs():
        a = assign_stream(run.time_s, run.tracker_mm, starts, ends, run.line, str(stream_path))
        assigned.append((run.station, run.run, a))
        rows.append(
            FlyRun(
                station=run.station,
                run=run.run,
                start_mm=starts[a.path] - smr,
                end_mm=ends[a.path] - smr,
                tracker_mm=run.tracker_mm[a.sample],
                time_s=run.time_s[a.sample],
                u_radial_um=run.u_radial_um[a.sample],
                u_transverse_um=run.u_transverse_um[a.sample],
            )
        )
    made_from = [FileSource.of("stream", stream_path), FileSource.of("points", points_path)]
    write_fly_rows(out, rows, made_from)
    return StreamImportResult(out, assigned)


# -- one launch-unit station: identify -> program -> run ------------------------------------


@dataclass(frozen=True)
class StationFiles:
    """Where one launch-unit station's files go; ``program`` None: ``run<suffix>`` next to
    the plan (:func:`program_file`)."""

    session: Path
    pose: Path
    plan: Path
    measurements: Path
    program: Path | None = None


@dataclass(frozen=True)
class StationOptions:
    """How a station is identified, planned and recorded (the defaults of ``xmalign``)."""

    method: str = "joint"
    dialect: str | None = None
    #: The lines to plan (default: all six).
    line_ids: tuple[str, ...] | None = None
    #: The virtual machine's seed, recorded in the measurement file (dry runs).
    sim_seed: int | None = None


#: How a station's run captures: the programmed plan into its open measurement file (the
#: caller's way of driving the machine: a controller running the program, a followed CNC).
Measure = Callable[[ProgramStepResult, RunOutput], CalibrationRun]


@dataclass
class StationStepResult:
    """One station identified, programmed and measured; durations on the devices' clock."""

    identification: IdentificationResult
    programmed: ProgramStepResult
    run: CalibrationRun
    files: StationFiles
    identify_s: float
    run_s: float


def station_step(
    machine: Machine,
    positions_mm: np.ndarray,
    devices: RoutineDevices,
    files: StationFiles,
    measure: Measure,
    options: StationOptions = StationOptions(),
    manual_align: Callable[[], None] | None = None,
    environment: EnvironmentMonitor | None = None,
    on_stage: Callable[[str], None] | None = None,
) -> StationStepResult:
    """One launch-unit station: identify at ``positions_mm`` (CNC points (N, 3), mm; session
    and pose written), plan its lines (plan and G-code written), then capture them into
    ``files.measurements`` with ``measure``. ``on_stage`` is told ``identify``, ``program``
    and ``run`` as each starts. The dry run and the two-station dry run measure here.
    """
    stage = on_stage or (lambda name: None)
    clock = devices.clock
    started = clock.now()
    stage("identify")
    identified = identify_step(
        positions_mm,
        machine,
        devices,
        files.session,
        options.method,
        manual_align=manual_align,
        pose_path=files.pose,
    ).result
    identify_s = clock.now() - started
    stage("program")
    programmed = program_step(
        machine,
        identified,
        files.plan,
        files.program,
        options.dialect,
        files.pose,
        options.line_ids,
    )
    stage("run")
    started = clock.now()
    with open_measurements_step(
        files.measurements,
        programmed.plan,
        machine,
        environment=environment,
        sim_seed=options.sim_seed,
    ) as output:
        run = measure(programmed, output)
    return StationStepResult(identified, programmed, run, files, identify_s, clock.now() - started)


def plan_session_step(
    session: Session, machine: Machine, method: str = "joint"
) -> tuple[IdentificationResult, MeasurementPlan]:
    """The pose solved from a session held in memory (the machine file's uncertainty) and
    the lines planned for it, no file written: a Monte Carlo identification trial."""
    uncertainty = IdentificationUncertainty.from_machine(machine.uncertainty)
    result = identify(session, method, uncertainty)
    planned = program_step(machine, result, None, write_program_file=False)
    return result, planned.measurement
