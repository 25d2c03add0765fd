"""``xmalign comp --controller linuxcnc-volumetric --ini MACHINE.ini``: write and report."""

from __future__ import annotations

from pathlib import Path

from xmalign.cli.common import console, error_console
from xmalign.comp.linuxcnc_volumetric import merge_config
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_text
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.machine import Machine


def write_volumetric(tables: ErrorTableSet, machine: Machine, ini: Path | None, out: Path) -> None:
    """Write the component's table file and the merged INI/HAL copies into ``out``."""
    if ini is None:
        raise InputError("--controller linuxcnc-volumetric needs --ini MACHINE.ini")
    merged = merge_config(ini, tables, machine, out)
    for name, text in merged.files.items():
        atomic_write_text(out / name, text)
    for warning in merged.warnings:
        error_console.print(f"xmalign: warning: {warning}")
    console.print(
        f"linuxcnc-volumetric: wrote {', '.join(sorted(merged.files))} in {out}; build the"
        f" component once with 'halcompile --install linuxcnc/xmalign_volcomp.comp', then start"
        f" 'linuxcnc {out / merged.ini_name}'"
    )
