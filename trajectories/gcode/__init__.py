"""G-code writers, one module per controller dialect, behind one interface.

:func:`write_program` (in :mod:`trajectories.gcode.program`) lays out the
measurement; a :class:`~trajectories.gcode.base.Dialect` only spells the blocks.
"""

from trajectories.gcode.base import Dialect
from trajectories.gcode.fanuc import IsoDialect
from trajectories.gcode.heidenhain import HeidenhainDialect
from trajectories.gcode.linuxcnc import LinuxCncDialect
from trajectories.gcode.sinumerik import SinumerikDialect

DIALECTS: dict[str, type[Dialect]] = {
    "iso": IsoDialect,
    "sinumerik": SinumerikDialect,
    "heidenhain": HeidenhainDialect,
    "linuxcnc": LinuxCncDialect,
}

__all__ = ["DIALECTS", "Dialect"]
