"""Helpers shared by the CLI commands."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from xmalign.errors import InputError, OutputError
from xmalign.formats.common import (
    PathsOf,
    check_output_folder,
    located,
    os_problem,
    refuse_special,
)
from xmalign.machine import Machine, default_machine_path, load_machine
from xmalign.steps import Caller

console = Console()
error_console = Console(stderr=True)


def machine_or_default(path: Path | None) -> Machine:
    """The machine file given, or the reference machine shipped with xmalign."""
    return load_machine(path if path is not None else default_machine_path())


def named_by_options(
    names: Mapping[str, str],
    read: Mapping[str, PathsOf] | None = None,
    written: Mapping[str, PathsOf] | None = None,
    appended: Mapping[str, PathsOf] | None = None,
) -> Caller:
    """How a command names a step's files in messages: by its options (``names``: the
    step's parameter -> the option), with its own files read, written and appended to
    (option -> path), and ``--force`` to replace (:func:`xmalign.steps.check_outputs`)."""
    return Caller(names, read or {}, written or {}, appended or {}, "--force")


def warn(warning: str) -> None:
    """A warning on stderr (one line)."""
    error_console.print(f"[yellow]warning:[/] {warning}", highlight=False)


def refuse_unused_options(given: dict[str, bool], why: str) -> None:
    """Refuse the first option that is given (``given[option]``) but would be ignored.

    Raises
    ------
    InputError
        ``OPTION is not used WHY: leave it out``.
    """
    unused = next((option for option, is_given in given.items() if is_given), None)
    if unused is not None:
        raise InputError(f"{unused} is not used {why}: leave it out")


def output_folder(path: Path, option: str) -> Path:
    """An output folder, created if missing; a file in its place is refused.

    Raises
    ------
    InputError
        ``path`` is an existing file.
    OutputError
        The folder cannot be created (no permission, read-only, disk full).
    """
    check_output_folder(path, option)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise OutputError(located(path, "cannot create the folder", os_problem(error))) from error
    return path


def check_positions(count: int, option: str) -> int:
    """A number of identification positions the design can serve (limit and why)."""
    from trajectories.identification_design import count_problem

    problem = count_problem(count)
    if problem is not None:
        raise InputError(f"option {option}: {problem}")
    return count


def check_seed(seed: int, option: str = "--seed") -> int:
    """A seed of the random generators must be 0 or more (numpy's rule)."""
    if seed < 0:
        raise InputError(f"option {option}: {seed} must be 0 or more")
    return seed


#: The ``--force`` option of the commands whose outputs a later step or a user relies on.
ForceOption = Annotated[
    bool,
    typer.Option(
        "--force",
        help="Replace output files that already exist (without it they are never replaced).",
    ),
]

#: The ``--log-file PATH`` option of every command that talks to devices.
LogFileOption = Annotated[
    Path | None,
    typer.Option(
        "--log-file",
        help="Append every register, SDO and serial line that crosses the wire, "
        "with a UTC timestamp, to this file (docs/hardware.md, Wire log).",
    ),
]

#: Packages whose loggers record the wire traffic (drivers, simulated servers, core).
WIRE_LOGGERS = ("firmware_iface", "sim", "xmalign")
#: Third-party protocol libraries: their own warnings (retries, aborted transfers) go to
#: the log file too, at the level they log at; never to the terminal.
LIBRARY_LOGGERS = ("pymodbus", "canopen", "can")
_LOG_FORMAT = "%(asctime)s.%(msecs)03dZ %(name)s %(levelname)s %(message)s"


def start_log_file(path: Path | None) -> logging.Handler | None:
    """Log the wire traffic (DEBUG) of :data:`WIRE_LOGGERS` to ``path``; None does nothing.

    Returns the handler (for :func:`stop_log_file`). An unwritable path is an InputError.
    """
    if path is None:
        return None
    refuse_special(path, "--log-file", appended=True)
    try:
        handler = logging.FileHandler(path, encoding="utf-8")
    except OSError as error:
        raise InputError(f"--log-file {path}: cannot write it ({error.strerror})") from error
    formatter = logging.Formatter(_LOG_FORMAT, datefmt="%Y-%m-%dT%H:%M:%S")
    formatter.converter = time.gmtime
    handler.setFormatter(formatter)
    handler.setLevel(logging.DEBUG)
    for name in WIRE_LOGGERS:
        logger = logging.getLogger(name)
        logger.setLevel(logging.DEBUG)
        logger.addHandler(handler)
    for name in LIBRARY_LOGGERS:
        logging.getLogger(name).addHandler(handler)
    return handler


def keep_library_logs_off_the_terminal() -> None:
    """Without any handler, Python prints a library's warnings on stderr (pymodbus'
    "Connection ... failed", canopen's "Transfer aborted"), next to the one-line error."""
    root = logging.getLogger()
    if not root.handlers:
        root.addHandler(logging.NullHandler())


def stop_log_file(handler: logging.Handler | None) -> None:
    """Detach and close a handler of :func:`start_log_file`."""
    if handler is None:
        return
    for name in WIRE_LOGGERS + LIBRARY_LOGGERS:
        logging.getLogger(name).removeHandler(handler)
    handler.close()
