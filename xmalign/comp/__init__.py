"""Compensation tables for CNC controllers, one module per controller.

Each module has ``NAME``, ``COMPENSATES`` (the ISO 230-1 names its tables
correct, ``"squareness"`` when they carry the squareness) and
``render(tables, chain) -> {file name: text}``; the values come from an
:class:`~xmalign.formats.error_tables.ErrorTableSet` (mm, rad).
"""

from __future__ import annotations

from types import ModuleType

from xmalign.comp import fanuc, heidenhain, isg, linuxcnc, sinumerik
from xmalign.errors import InputError
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.rigid_body import ErrorTables

WRITERS: dict[str, ModuleType] = {
    module.NAME: module for module in (sinumerik, fanuc, heidenhain, linuxcnc, isg)
}


def writer(controller: str) -> ModuleType:
    """The writer module of a controller; InputError listing the known ones."""
    try:
        return WRITERS[controller]
    except KeyError:
        raise InputError(
            f"unknown controller '{controller}' (one of {', '.join(WRITERS)})"
        ) from None


def remaining_errors(tables: ErrorTableSet, controller: str) -> ErrorTables:
    """The error model left after the controller's tables compensate what they can (mean)."""
    compensated = writer(controller).COMPENSATES
    model = tables.model("")
    return ErrorTables(
        tables={n: v for n, v in model.tables.items() if n not in compensated},
        squareness={} if "squareness" in compensated else model.squareness,
    )
