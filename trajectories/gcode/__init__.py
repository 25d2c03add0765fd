"""G-code writers, one module per controller dialect, behind one interface.

:func:`write_program` (in :mod:`trajectories.gcode.program`) lays out the
measurement; a :class:`~trajectories.gcode.base.Dialect` only spells the blocks.
"""

from trajectories.gcode.base import Dialect
from trajectories.gcode.fanuc import IsoDialect
from trajectories.gcode.heidenhain import HeidenhainDialect
from trajectories.gcode.linuxcnc import LinuxCncDialect
from trajectories.gcode.sinumerik import SinumerikDialect
from xmalign.errors import InputError
from xmalign.machine import Machine

DIALECTS: dict[str, type[Dialect]] = {
    "iso": IsoDialect,
    "sinumerik": SinumerikDialect,
    "heidenhain": HeidenhainDialect,
    "linuxcnc": LinuxCncDialect,
}

#: G-code dialect of each controller of the machine file.
CONTROLLER_DIALECTS = {
    "sinumerik": "sinumerik",
    "fanuc": "iso",
    "heidenhain": "heidenhain",
    "linuxcnc": "linuxcnc",
}


def make_dialect(
    name: str, machine: Machine, program_name: str = "XMALIGN", stop_at_points: bool = False
) -> Dialect:
    """The dialect ``name`` for ``machine`` (its ``cnc.work_offset``), naming the program;
    ``stop_at_points``: a programmed stop instead of each dwell (xmalign resumes it)."""
    return DIALECTS[name](program_name, machine.cnc.work_offset, stop_at_points)


def resolve_dialect(machine: Machine, dialect: str | None, option: str = "--dialect") -> str:
    """The dialect asked for, or the machine controller's; InputError if there is none,
    naming ``option`` (how the caller names the dialect: ``dialect`` in the Python API)."""
    if dialect is not None:
        if dialect not in DIALECTS:
            raise InputError(f"{option} '{dialect}' is not known (known: {', '.join(DIALECTS)})")
        return dialect
    if machine.controller not in CONTROLLER_DIALECTS:
        raise InputError(
            f"controller '{machine.controller}' has no G-code dialect of its own;"
            f" choose one with {option} ({', '.join(DIALECTS)})"
        )
    return CONTROLLER_DIALECTS[machine.controller]


__all__ = ["CONTROLLER_DIALECTS", "DIALECTS", "Dialect", "make_dialect", "resolve_dialect"]
