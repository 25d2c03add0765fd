"""Helpers shared by the CLI commands."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from xmalign.machine import Machine, default_machine_path, load_machine

console = Console()
error_console = Console(stderr=True)


def machine_or_default(path: Path | None) -> Machine:
    """The machine file given, or the reference machine shipped with xmalign."""
    return load_machine(path if path is not None else default_machine_path())
