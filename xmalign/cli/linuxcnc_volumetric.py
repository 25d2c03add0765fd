"""``xmalign comp --controller linuxcnc-volumetric --ini MACHINE.ini``: files and report."""

from __future__ import annotations

from pathlib import Path

from xmalign.cli.common import error_console
from xmalign.comp.linuxcnc_volumetric import merge_config
from xmalign.errors import InputError
from xmalign.formats.error_tables import ErrorTableSet
from xmalign.machine import Machine


def volumetric_files(
    tables: ErrorTableSet, machine: Machine, ini: Path | None, out: Path
) -> tuple[dict[str, str], str]:
    """The component's table file and the merged INI/HAL copies (name -> text), and what to do."""
    if ini is None:
        raise InputError("--controller linuxcnc-volumetric needs --ini MACHINE.ini")
    merged = merge_config(ini, tables, machine, out)
    for warning in merged.warnings:
        error_console.print(f"xmalign: warning: {warning}", highlight=False)
    done = (
        f"linuxcnc-volumetric: wrote {', '.join(sorted(merged.files))} in {out}; build the"
        f" component once with 'halcompile --install linuxcnc/xmalign_volcomp.comp', then start"
        f" 'linuxcnc {out / merged.ini_name}'"
    )
    return dict(merged.files), done
