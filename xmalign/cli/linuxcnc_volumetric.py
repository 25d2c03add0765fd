"""``xmalign comp --controller linuxcnc-volumetric --ini MACHINE.ini``: files and report."""

from __future__ import annotations

from pathlib import Path

from xmalign.cli.common import console, warn
from xmalign.errors import InputError
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.machine import Machine
from xmalign.steps import Caller, volumetric_comp_step


def volumetric_comp(
    tables: ErrorTableSet,
    machine: Machine,
    ini: Path | None,
    out: Path,
    force: bool,
    caller: Caller,
) -> None:
    """The component's table file and the merged INI/HAL copies written into ``out`` by
    the step layer (:func:`~xmalign.steps.volumetric_comp_step`), and what to do next."""
    if ini is None:
        raise InputError("--controller linuxcnc-volumetric needs --ini MACHINE.ini")
    merged = volumetric_comp_step(machine, tables, out, ini, force, caller, warn)
    console.print(
        f"linuxcnc-volumetric: wrote {', '.join(sorted(merged.files))} in {out}; build the"
        f" component once with 'halcompile --install linuxcnc/xmalign_volcomp.comp', then start"
        f" 'linuxcnc {out / merged.ini_name}'",
        highlight=False,
    )
