"""Running a measurement plan on the units, the interferometer and the machine (roles only).

Per line: drive the units to the plan's angles, fine-align at the line start,
lock, then follow the machine through the targets and capture the six
channels averaged over each dwell. Every captured point is appended to the
measurement CSV and flushed at once; a resumed run skips the points already
recorded. A device fault stops the line with the units locked.

A beam lost while capturing is searched for like fine alignment does
(:func:`xmalign.alignment.find_beam`: back to the line's locked angles, then
spiral searches within the units' pointing uncertainty); found, both units
align to it, they are locked, the alignment is recorded as a new
setup segment (the interferometer lost its count, and the beam may point a
little differently), the datum is set again and the point is captured again.
Only when the search fails does the run stop and ask a person.

Each alignment of a line is recorded with the locked unit angles. A resumed
line keeps its setup when the units still stand where they were locked;
otherwise it is aligned again and its further rows form a new setup segment,
which ``post`` fits with its own setup terms.

The interferometer reports in its own frame, the launch head's (``u`` from the
launch unit towards the receiver), with the raw displacement since its datum;
the rows are written in the line frame of docs/conventions.md, with ``linear_um`` the actual
minus the commanded displacement from the run's first point (where the datum
is set).

The package by concern: :mod:`.capture` (the capture order and :class:`CalibrationRun`),
the three drives (:mod:`.stepping`, :mod:`.followed`, :mod:`.controlled`) with what they
share (:mod:`.way`, :mod:`.waiting`), :mod:`.events` (a program's reported events) and
:mod:`.output` (the measurement file's open, resume and lock).
"""

from xmalign.calibration.capture import (
    AVERAGE_END_FRACTION,
    BEAM_PROBE_S,
    BEAM_WAIT_S,
    DEFAULT_START_DISTANCE_MM,
    LINE_START_ALIGNMENT,
    SETTLE_FRACTION,
    SETTLE_PROBE_S,
    SETTLED_UM,
    SETUP_KEPT_RAD,
    STANDING_READINGS,
    UNIT_MOVE_TIMEOUT_S,
    CalibrationRun,
    CapturePoint,
    RunStatistics,
    capture_sequence,
    head_frame,
    line_channels,
)
from xmalign.calibration.controlled import ControlledProgram, control_program
from xmalign.calibration.events import (
    STOP_OFF_LINE_MM,
    ProgramEvent,
    capture_program,
    check_program_position,
    check_program_stop,
)
from xmalign.calibration.followed import PRESS_CYCLE_START, follow_machine
from xmalign.calibration.output import RunOutput, check_run_output, open_run_output
from xmalign.calibration.stepping import step_through
from xmalign.calibration.way import ProgramWay, check_stop_on_way, pre_position_mm

__all__ = [
    "AVERAGE_END_FRACTION",
    "BEAM_PROBE_S",
    "BEAM_WAIT_S",
    "CalibrationRun",
    "CapturePoint",
    "ControlledProgram",
    "DEFAULT_START_DISTANCE_MM",
    "DEVICE_CHECK_S",
    "LINE_START_ALIGNMENT",
    "PRESS_CYCLE_START",
    "ProgramEvent",
    "ProgramWay",
    "RunOutput",
    "RunStatistics",
    "SETTLED_UM",
    "SETTLE_FRACTION",
    "SETTLE_PROBE_S",
    "SETUP_KEPT_RAD",
    "STANDING_READINGS",
    "STOP_OFF_LINE_MM",
    "UNIT_MOVE_TIMEOUT_S",
    "capture_program",
    "capture_sequence",
    "check_program_position",
    "check_program_stop",
    "check_run_output",
    "check_stop_on_way",
    "control_program",
    "follow_machine",
    "has_left",
    "head_frame",
    "line_channels",
    "open_run_output",
    "point_where",
    "pre_position_mm",
    "stands_at",
    "step_through",
    "wait_for",
]
