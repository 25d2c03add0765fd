"""The measurement file of a run: checked, opened new or resumed, locked while it runs."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from xmalign.calibration.capture import CalibrationRun
from xmalign.environment import EnvironmentMonitor
from xmalign.errors import InputError
from xmalign.formats.common import refuse_special
from xmalign.formats.measurements import (
    NOMINAL_LIMITS,
    ChannelLimits,
    MeasurementFile,
    MeasurementRow,
    MeasurementWriter,
    RunLock,
    check_recorded_plan,
    load_measurements,
    plan_sha256,
)
from xmalign.formats.plan import Plan
from xmalign.roles import Clock, Interferometer, PositioningUnit


@dataclass
class RunOutput:
    """The measurement CSV a run appends to, and what it already held."""

    writer: MeasurementWriter
    recorded: MeasurementFile | None = None
    warnings: list[str] = field(default_factory=list)
    #: Called with the number of rows in the file after each one is saved (progress).
    on_saved: Callable[[int], None] = lambda saved: None
    #: Sampled at every point when the run records the environment.
    environment: EnvironmentMonitor | None = None
    #: Held for the whole run: no other run appends to the file meanwhile.
    lock: RunLock | None = None

    def append(self, row: MeasurementRow) -> None:
        self.writer.append(row)
        self.on_saved(self.writer.saved)

    def calibration_run(
        self,
        plan: Plan,
        launch: PositioningUnit,
        receiver: PositioningUnit,
        interferometer: Interferometer,
        clock: Clock,
    ) -> CalibrationRun:
        """A CalibrationRun recording into this file and skipping what it already holds."""
        recorded = self.recorded
        return CalibrationRun(
            plan,
            launch,
            receiver,
            interferometer,
            clock,
            record=self.append,
            record_setup=self.writer.note_setup,
            done={row.key() for row in recorded.rows} if recorded else set(),
            setups=recorded.last_setups() if recorded else {},
            last_segment=recorded.last_segments() if recorded else {},
            environment=self.environment,
        )

    def close(self) -> None:
        self.writer.close()
        if self.lock is not None:
            self.lock.release()

    def __enter__(self) -> RunOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _holds_no_points(path: Path) -> bool:
    """A measurement file with a header and not one point (a run that failed at its start)."""
    if not path.is_file() or path.stat().st_size == 0:
        return False
    try:
        recorded = load_measurements(path, torn_ok=True)
    except InputError:
        return False
    return not recorded.rows and recorded.torn is None


def check_run_output(path: Path, resume: bool) -> None:
    """Refuse an ``--out`` a run cannot use, before anything is read, created or connected."""
    if path.is_dir():
        raise InputError(f"{path}: is a folder; give a file name for --out")
    refuse_special(path, "--out")
    if resume and not path.exists():
        raise InputError(f"--resume: {path} does not exist yet; run without --resume")
    if path.exists() and path.stat().st_size > 0:
        _refuse_other_kinds(path)
    if not resume and path.exists() and path.stat().st_size > 0 and not _holds_no_points(path):
        raise InputError(
            f"{path} already holds measurements and is never replaced: add --resume to"
            " go on with it, or give another --out"
        )


def _refuse_other_kinds(path: Path) -> None:
    """An xmalign JSON file (a plan, a pose) given as ``--out`` is named for what it is."""
    with path.open("rb") as handle:
        start = handle.read(4096)
    if not start.lstrip().startswith(b"{"):
        return
    found = re.search(rb'"format"\s*:\s*"([^"]+)"', start)
    kind = found.group(1).decode("utf-8", "replace") if found else "JSON"
    name = kind.removeprefix("xmalign.").partition("/")[0]
    what = f"a {name} file ({kind})" if found else "a JSON file"
    raise InputError(
        f"{path}: --out: is {what}, not a measurement CSV; give the name of the measurement"
        " file to write (e.g. --out measurements.csv)"
    )


def _check_seed(path: Path, recorded: int | None, sim_seed: int | None) -> None:
    """A simulated run is resumed on the same virtual machine (the same ``--seed``).

    A live run is not checked: the hardware may be a served virtual machine.
    """
    if recorded is None or sim_seed is None or recorded == sim_seed:
        return
    raise InputError(
        f"--seed {sim_seed}: {path} was measured on the virtual machine of --seed {recorded};"
        f" resume it with --seed {recorded}"
    )


def _check_environment_columns(
    path: Path, recorded: tuple[str, ...], environment: EnvironmentMonitor | None
) -> None:
    """A resumed file keeps the environment columns it was started with."""
    sampled = environment.columns if environment else ()
    if set(recorded) == set(sampled):
        return
    if not sampled:
        raise InputError(
            f"{path}: was recorded with the environment ({', '.join(recorded)}); resume it"
            " with the same environment source"
        )
    raise InputError(
        f"{path}: was recorded with environment columns ({', '.join(recorded) or 'none'}),"
        f" the environment source now gives {', '.join(sampled)}; go on with another --out"
    )


def open_run_output(
    path: Path,
    plan: Plan,
    resume: bool,
    limits: ChannelLimits = NOMINAL_LIMITS,
    environment: EnvironmentMonitor | None = None,
    sim_seed: int | None = None,
) -> RunOutput:
    """Open the measurement CSV of a run: a new file, or (``resume``) the one to go on with.

    Raw measurements are never replaced: without ``resume`` an existing file is
    refused unless it holds not one point. With ``resume`` the file must have
    been recorded for ``plan`` (and, on the virtual machine, with ``sim_seed``);
    a torn last row is cut off with a warning and its point is measured again.
    With ``environment`` its first reading is taken (complete and in range, or a
    one-line error) before the file is touched, and every row records it. The
    file is locked (:class:`RunLock`) before it is read or written, until the
    output is closed.
    """
    path = Path(path)
    check_run_output(path, resume)
    if environment is not None:
        environment.prime()
    lock = RunLock(path)
    try:
        output = _open_locked(path, plan, resume, limits, environment, sim_seed)
    except BaseException:
        lock.release()
        raise
    output.lock = lock
    return output


def _open_locked(
    path: Path,
    plan: Plan,
    resume: bool,
    limits: ChannelLimits,
    environment: EnvironmentMonitor | None,
    sim_seed: int | None,
) -> RunOutput:
    columns = environment.columns if environment else ()
    if not resume or path.stat().st_size == 0:
        if _holds_no_points(path):
            os.truncate(path, 0)
        inputs = [plan.source] if plan.source is not None else []
        writer = MeasurementWriter.create(
            path, plan_sha256(plan), columns, sim_seed=sim_seed, inputs=inputs
        )
        return RunOutput(writer, environment=environment)
    recorded = load_measurements(path, limits, torn_ok=True)
    _check_seed(path, recorded.sim_seed, sim_seed)
    _check_environment_columns(path, recorded.environment_columns, environment)
    warnings = check_recorded_plan(recorded, plan)
    if recorded.torn is not None:
        warnings.append(
            f"{path}: line {recorded.torn.line_number} was cut short when the run stopped"
            f" ({recorded.torn.text[:40]!r}); it is dropped and its point measured again"
        )
    return RunOutput(
        MeasurementWriter.resume(recorded), recorded, warnings, environment=environment
    )
