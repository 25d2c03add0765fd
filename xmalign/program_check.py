"""Is the program a followed controller runs xmalign's? (docs/hardware.md, "Following the
controller").

A controller spells a program's name its own way: a path (``/home/cnc/run.ngc``),
the SINUMERIK's NC notation (``/_N_MPF_DIR/_N_RUN_MPF``) or its OPC UA file path
(``Sinumerik/FileSystem/Part Program/run.mpf``), a program number (``O1000``, or
``1000``: the same program).
:func:`program_name` reduces each to the bare name, in capitals, and two
programs are the same when their bare names are.
"""

from __future__ import annotations

import re
from collections.abc import Callable

from xmalign.errors import DeviceError
from xmalign.roles import ReportsProgram

#: The SINUMERIK's NC notation of a file: ``_N_<name>_<type>`` (type MPF, SPF, ...).
_NC_NOTATION = re.compile(r"^_N_(?P<name>.+)_[A-Z]{3}$", re.IGNORECASE)
#: A program number: ``O1000``, or ``1000`` as some agents report it.
_PROGRAM_NUMBER = re.compile(r"^O?(?P<number>\d+)$", re.IGNORECASE)


def program_name(spelled: str) -> str:
    """The bare name of a program: no folder, no extension, no NC notation; capitals."""
    last = re.split(r"[/\\]", spelled.strip())[-1]
    nc = _NC_NOTATION.match(last)
    if nc is not None:
        return nc["name"].upper()
    number = _PROGRAM_NUMBER.match(last)
    if number is not None:
        return f"O{int(number['number'])}"
    stem, dot, _extension = last.rpartition(".")
    return (stem if dot and stem else last).upper()


def same_program(reported: str, expected: str) -> bool:
    """Whether the controller's ``reported`` program is the one named ``expected``."""
    return program_name(reported) == program_name(expected)


class ProgramGuard:
    """Stops a followed run when the controller runs another program than xmalign's.

    :meth:`check` reads what the controller reports: a program other than
    ``expected`` running or stopped mid-way (a stale program of an earlier run, a
    wrong one) is a DeviceError naming both and ``key`` (where the expected name is
    set); a controller that does not report its program is told once, and the
    run goes on unchecked. An idle controller is not checked: its program does
    not move the machine.

    Parameters
    ----------
    source : ReportsProgram
        The controller (its ``name`` attribute, if any, names it in messages).
    expected : str
        xmalign's program as the operator put it on the controller.
    key : str
        The ``units.yaml`` key that sets ``expected``, for the error line.
    tell : callable
        Where the once-only note goes.
    """

    def __init__(
        self, source: ReportsProgram, expected: str, key: str, tell: Callable[[str], None]
    ) -> None:
        self.source = source
        self.expected = expected
        self.key = key
        self.tell = tell
        self._said_unreported = False

    def check(self) -> None:
        """DeviceError when another program than xmalign's runs or is stopped mid-way."""
        report = self.source.program_report()
        who = getattr(self.source, "name", "the controller")
        if report is None:
            if not self._said_unreported:
                self._said_unreported = True
                self.tell(
                    f"{who} does not report its program: not checked against xmalign's"
                    f" program {self.expected} (make sure it is the one running)"
                )
            return
        if report.state == "idle" or (
            report.name is not None and same_program(report.name, self.expected)
        ):
            return
        raise DeviceError(
            f"{who} is {report.state} with program {report.name or '(none)'}, not xmalign's"
            f" program {self.expected} ({self.key}): a stale or wrong program; stop it and"
            " start xmalign's"
        )
