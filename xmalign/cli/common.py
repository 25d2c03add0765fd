"""Helpers shared by the CLI commands."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from xmalign.errors import InputError
from xmalign.machine import Machine, default_machine_path, load_machine

console = Console()
error_console = Console(stderr=True)


def machine_or_default(path: Path | None) -> Machine:
    """The machine file given, or the reference machine shipped with xmalign."""
    return load_machine(path if path is not None else default_machine_path())


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
_LOG_FORMAT = "%(asctime)s.%(msecs)03dZ %(name)s %(levelname)s %(message)s"


def start_log_file(path: Path | None) -> logging.Handler | None:
    """Log the wire traffic (DEBUG) of :data:`WIRE_LOGGERS` to ``path``; None does nothing.

    Returns the handler (for :func:`stop_log_file`). An unwritable path is an InputError.
    """
    if path is None:
        return None
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
    return handler


def stop_log_file(handler: logging.Handler | None) -> None:
    """Detach and close a handler of :func:`start_log_file`."""
    if handler is None:
        return
    for name in WIRE_LOGGERS:
        logging.getLogger(name).removeHandler(handler)
    handler.close()
