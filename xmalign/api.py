"""xmalign for people who script: load a calibration's files, run the steps, get tables.

Everything in :data:`__all__` is the public surface, documented with examples
in docs/api.md; the rest of the package may change between versions. The
steps are those of the command line (:mod:`xmalign.steps`); results come back
as dataclasses, and as pandas DataFrames with units in the column names
(pandas is the optional extra ``xmalign[pandas]``).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from xmalign import identify as identification
from xmalign.calibration import open_run_output
from xmalign.errors import InputError, XmalignError
from xmalign.formats import error_tables, measurements, plan, pose, provenance, session, studies
from xmalign.formats.common import path_argument
from xmalign.formats.error_tables import ErrorTableSet, file_unit
from xmalign.formats.measurements import MeasurementFile
from xmalign.formats.plan import Plan
from xmalign.formats.pose import LaunchPose
from xmalign.formats.provenance import FileSource, Provenance
from xmalign.formats.session import Session
from xmalign.identify import IdentificationResult
from xmalign.machine import Machine, default_machine_path, load_machine
from xmalign.post.evaluate import Instruments, PostResult
from xmalign.post.iso230_2 import PositioningFigures
from xmalign.roles import CHANNELS
from xmalign.steps import (
    RunStepDevices,
    check_argument,
    check_plan_machine,
    check_pose_machine,
    check_tables_machine,
    comp_step,
    design_step,
    following_drive,
    identify_step,
    import_stream_step,
    import_tracker_step,
    instrument_program_step,
    open_measurements_step,
    post_step,
    program_drive,
    program_step,
    run_step,
    stepping_drive,
    volumetric_comp_step,
    write_pose_step,
)

if TYPE_CHECKING:
    import pandas as pd

R = TypeVar("R")


def _path_first(reader: Callable[..., R]) -> Callable[..., R]:
    """``reader`` refusing, with one InputError naming it, a first argument that is not a
    file's path (a number, None, a Plan...): the readers would end in a TypeError."""

    @functools.wraps(reader)
    def checked(path: str | os.PathLike[str], *args: Any, **kwargs: Any) -> R:
        return reader(path_argument(path, reader.__name__), *args, **kwargs)

    return checked


read_error_tables = _path_first(error_tables.read_error_tables)
load_measurements = _path_first(measurements.load_measurements)
read_plan = _path_first(plan.read_plan)
read_pose = _path_first(pose.read_pose)
file_sha256 = _path_first(provenance.file_sha256)
read_session = _path_first(session.read_session)
read_design = _path_first(studies.read_design)
read_study = _path_first(studies.read_study)


@functools.wraps(identification.identify)
def identify(session: Session, *args: Any, **kwargs: Any) -> IdentificationResult:
    check_argument(session, Session, "identify: session", "a Session (read it with read_session)")
    return identification.identify(session, *args, **kwargs)


__all__ = [
    "Calibration",
    "ErrorTableSet",
    "FileSource",
    "IdentificationResult",
    "InputError",
    "Instruments",
    "LaunchPose",
    "Machine",
    "MeasurementFile",
    "Plan",
    "PostResult",
    "Provenance",
    "RunStepDevices",
    "Session",
    "XmalignError",
    "check_plan_machine",
    "check_pose_machine",
    "check_tables_machine",
    "comp_step",
    "default_machine_path",
    "design_step",
    "error_table_frames",
    "file_sha256",
    "following_drive",
    "identify",
    "identify_step",
    "import_stream_step",
    "import_tracker_step",
    "instrument_program_step",
    "iso230_2_frame",
    "load_calibration",
    "load_machine",
    "load_measurements",
    "measurements_frame",
    "open_measurements_step",
    "open_run_output",
    "post_step",
    "program_drive",
    "program_step",
    "read_design",
    "read_error_tables",
    "read_plan",
    "read_pose",
    "read_session",
    "read_study",
    "run_step",
    "squareness_frame",
    "stepping_drive",
    "volumetric_comp_step",
    "write_pose_step",
]

#: The file names the steps write in a calibration's folder (as ``xmalign dry-run`` does).
FILE_NAMES = {
    "session": "session.json",
    "pose": "pose.json",
    "plan": "plan.json",
    "measurements": "measurements.csv",
    "errors": "errors.csv",
}


@dataclass
class Calibration:
    """The files of one calibration, each None where the folder does not hold it."""

    folder: Path
    machine: Machine
    session: Session | None = None
    pose: LaunchPose | None = None
    plan: Plan | None = None
    measurements: MeasurementFile | None = None
    errors: ErrorTableSet | None = None


def load_calibration(folder: str | Path, machine: str | Path | None = None) -> Calibration:
    """Read the calibration files in ``folder`` (:data:`FILE_NAMES`) that are there.

    ``machine`` is the machine file (default: the reference machine).

    Raises
    ------
    InputError
        ``folder`` is not a folder, or a file is there but cannot be used (one line
        naming it and the key or line), or ``machine`` cannot be read.
    """
    folder = path_argument(folder, "load_calibration", "a folder's path")
    if not folder.is_dir():
        problem = "not a folder" if folder.exists() else "no such folder"
        raise InputError(f"{folder}: {problem}; give the folder of a calibration's files")
    readers: dict[str, Callable[[Path], Any]] = {
        "session": read_session,
        "pose": read_pose,
        "plan": read_plan,
        "measurements": load_measurements,
        "errors": read_error_tables,
    }

    def read(key: str) -> Any:
        path = folder / FILE_NAMES[key]
        there = path.exists() or path.is_symlink()  # a link that loops: named when read
        return readers[key](path) if there else None

    return Calibration(
        folder,
        load_machine(machine or default_machine_path()),
        session=read("session"),
        pose=read("pose"),
        plan=read("plan"),
        measurements=read("measurements"),
        errors=read("errors"),
    )


def _pandas() -> Any:
    """pandas, or an ImportError saying how to install it (an optional extra)."""
    try:
        import pandas
    except ImportError as error:
        raise ImportError("the DataFrames need pandas: pip install 'xmalign[pandas]'") from error
    return pandas


def measurements_frame(measurements: MeasurementFile | str | Path) -> pd.DataFrame:
    """One row per captured point, the file's columns (units in their names).

    ``time_s`` is NaN for rows of a version 1 file; the environment columns are
    there when the file has them.
    """
    pd = _pandas()
    recorded = (
        measurements
        if isinstance(measurements, MeasurementFile)
        else load_measurements(measurements)
    )
    records = []
    for row in recorded.rows:
        record: dict[str, object] = {
            "line": row.line,
            "run": row.run,
            "direction": row.direction,
            "index": row.index,
            "target_mm": row.target_mm,
            "x_mm": row.machine_mm[0],
            "y_mm": row.machine_mm[1],
            "z_mm": row.machine_mm[2],
            **dict(zip(CHANNELS, (float(v) for v in row.channels), strict=True)),
            "segment": row.segment,
            "time_s": math.nan if row.time_s is None else row.time_s,
            **row.environment,
        }
        if recorded.environment_columns:
            record["environment_flags"] = row.environment_flags
        records.append(record)
    return pd.DataFrame.from_records(records)


def _scale(unit: str) -> float:
    return 1e3 if unit == "um" else 1e6


def error_table_frames(tables: ErrorTableSet) -> dict[str, pd.DataFrame]:
    """The error tables in a wide form, one DataFrame per axis (``"X"``, ``"Y"``, ``"Z"``).

    Each is indexed by ``position_mm`` (the union of the tables' positions) and
    has, per table of that axis, ``NAME_UNIT`` and ``NAME_u95_UNIT`` (``EXX_um``,
    ``EXX_u95_um``, ``EBX_urad``; a direction stays in the name: ``EXX+_um``) and
    ``NAME_measured`` (False beyond the measured stroke). Squareness:
    :func:`squareness_frame`.
    """
    check_argument(tables, ErrorTableSet, "tables", "an ErrorTableSet (read_error_tables)")
    pd = _pandas()
    frames: dict[str, list[Any]] = {}
    for name, table in tables.tables.items():
        unit = file_unit(name)
        scale = _scale(unit)
        columns = {
            f"{name}_{unit}": table.values * scale,
            f"{name}_u95_{unit}": table.u95 * scale,
            f"{name}_measured": table.measured_mask(),
        }
        index = pd.Index(table.positions_mm, name="position_mm")
        frames.setdefault(name.rstrip("+-")[-1], []).append(pd.DataFrame(columns, index=index))
    return {axis: pd.concat(parts, axis=1).sort_index() for axis, parts in sorted(frames.items())}


def squareness_frame(tables: ErrorTableSet) -> pd.DataFrame:
    """The squareness errors: index ``name`` (``EC0Y`` ...), ``value_urad``, ``u95_urad``."""
    check_argument(tables, ErrorTableSet, "tables", "an ErrorTableSet (read_error_tables)")
    pd = _pandas()
    rows = {name: (value * 1e6, u95 * 1e6) for name, (value, u95) in tables.squareness.items()}
    frame = pd.DataFrame.from_dict(rows, orient="index", columns=["value_urad", "u95_urad"])
    frame.index.name = "name"
    return frame


def iso230_2_frame(result: PostResult | list[PositioningFigures]) -> pd.DataFrame:
    """ISO 230-2 figures of every axis line, µm: one row per line (``line``), columns
    ``A_um``, ``B_um``, ``E_um``, ``M_um``, ``R_um`` ... (``_up`` / ``_down``: one
    direction; NaN where the figure needs what was not measured) and ``runs``."""
    if not isinstance(result, list):
        check_argument(result, PostResult, "result", "a PostResult (post_step(...).post)")
    pd = _pandas()
    figures = result.positioning if isinstance(result, PostResult) else result
    records = []
    for figure in figures:
        record: dict[str, object] = {"line": figure.line_id, "runs": figure.runs}
        record |= {f"{name}_um": value for name, value in figure.as_dict().items()}
        records.append(record)
    return pd.DataFrame.from_records(records).set_index("line")
