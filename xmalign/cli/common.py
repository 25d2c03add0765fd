"""Helpers shared by the CLI commands."""

from __future__ import annotations

from pathlib import Path

from rich.console import Console

from xmalign.errors import InputError
from xmalign.formats.plan import Plan
from xmalign.machine import Machine, default_machine_path, load_machine

console = Console()
error_console = Console(stderr=True)


def machine_or_default(path: Path | None) -> Machine:
    """The machine file given, or the reference machine shipped with xmalign."""
    return load_machine(path if path is not None else default_machine_path())


def machine_for_plan(path: Path | None, plan: Plan, plan_path: Path) -> Machine:
    """The machine file given (or the reference machine), refused if the plan is for another.

    A plan names its machine and records ``machine_sha256``
    (:meth:`Machine.geometry_sha256`); a plan without it is checked by name.
    """
    machine = machine_or_default(path)
    recorded = plan.extra.get("machine_sha256")
    if plan.machine == machine.name and recorded in (None, machine.geometry_sha256()):
        return machine
    given = f"--machine {path}" if path is not None else "the reference machine (no --machine)"
    identity = f", machine_sha256 {str(recorded)[:12]}..." if recorded else ""
    raise InputError(
        f"{plan_path} was made for machine '{plan.machine}'{identity}, not for {given}"
        f" ('{machine.name}'): give the machine file the plan was made with (--machine)"
    )
