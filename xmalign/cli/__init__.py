"""The ``xmalign`` command line: wires the core, the drivers and the simulator together.

Each command lives in its own module with a ``register(app)`` function. Any
:class:`~xmalign.errors.XmalignError`, and any OSError (a disk or permission
problem), becomes one line on stderr and exit code 2; Ctrl-C becomes one line
and exit code 130. A command that wants to say more on Ctrl-C (e.g. how many
points were kept) raises ``KeyboardInterrupt("stopped: ...")``: that message
is printed instead of the generic one. SIGTERM and SIGHUP stop a command as
Ctrl-C does (:func:`xmalign.safety.stop_signals_as_interrupts`): the same line,
naming the signal, and exit code 128 + the signal's number (143, 129).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from typing import Annotated, Any, get_args

import typer
from typer.core import TyperGroup

from xmalign import __version__
from xmalign.cli import align, identify
from xmalign.cli import instruments as instruments_command
from xmalign.cli import mc as mc_command
from xmalign.cli import post as post_command
from xmalign.cli import program as program_command
from xmalign.cli import run as run_command
from xmalign.cli import sim as sim_command
from xmalign.cli.common import keep_library_logs_off_the_terminal
from xmalign.errors import InputError, XmalignError
from xmalign.formats.common import os_problem
from xmalign.safety import StopSignal, stop_signals_as_interrupts


def _is_usage_error(error: Exception) -> bool:
    """A click usage error (by name: recent typer versions vendor their own click)."""
    names = {cls.__name__ for cls in type(error).__mro__}
    return "UsageError" in names and "NoArgsIsHelpError" not in names


def _number(value: object) -> float | None:
    """A command-line value as a float (a text as typed, or a default), else None."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


def _not_finite(value: object) -> float | None:
    """The first NaN or infinity in an option's value (one, or several), else None."""
    values = value if isinstance(value, list | tuple) else (value,)
    numbers = (_number(v) for v in values)
    return next((v for v in numbers if v is not None and not math.isfinite(v)), None)


def _takes_floats(param: Any) -> bool:
    annotation = getattr(getattr(param, "type_descriptor", None), "annotation", None)
    return annotation is float or float in get_args(annotation)


def _finite_numbers_only(command: Any) -> None:
    """Every number option of ``command`` and its subcommands refuses NaN and infinity.

    One check for all options, before their own conversion and range (click's
    ranges let NaN through): a NaN would pass every ``value < 0`` test and end as
    a traceback, or a hang, deep in the maths.
    """
    for subcommand in getattr(command, "commands", {}).values():
        _finite_numbers_only(subcommand)
    for param in command.params:
        if _takes_floats(param) and not getattr(param, "finite_only", False):
            param.process_value = _finite_first(param.opts[0], param.process_value)
            param.finite_only = True


def _finite_first(option: str, process: Callable[..., Any]) -> Callable[..., Any]:
    def checked(ctx: Any, value: Any) -> Any:
        bad = _not_finite(value)
        if bad is not None:
            raise InputError(f"option {option}: {bad} is not a finite number")
        return process(ctx, value)

    return checked


class _OneLineUsageErrors(TyperGroup):
    """A command-line mistake (unknown option, bad value) as one line, like a bad file."""

    def invoke(self, ctx: Any) -> Any:
        _finite_numbers_only(self)
        try:
            return super().invoke(ctx)
        except Exception as error:
            if not _is_usage_error(error):
                raise
            context = getattr(error, "ctx", None) or ctx
            where = context.command_path
            raise InputError(
                f"{where}: {error.format_message()} (see '{where} --help')"  # type: ignore[attr-defined]
            ) from error


app = typer.Typer(
    cls=_OneLineUsageErrors,
    name="xmalign",
    help="Automatic setup and evaluation of a 6-DOF laser calibrator on positioning units.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # plain help: a flag reads as a flag (rich help shows every flag as "<bool>")
    rich_markup_mode=None,
)


def _print_version(asked: bool) -> None:
    if asked:
        typer.echo(f"xmalign {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="Show the version and exit."
        ),
    ] = False,
) -> None:
    """Automatic setup and evaluation of a 6-DOF laser calibrator on positioning units."""


for command_module in (
    identify,
    program_command,
    run_command,
    post_command,
    align,
    sim_command,
    mc_command,
    instruments_command,
):
    command_module.register(app)


#: Exit code of a command stopped by Ctrl-C (128 + SIGINT), as shells report it.
EXIT_INTERRUPTED = 130


def _interrupt_of(stop: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt behind an exit (typer turns Ctrl-C into exit code 130)."""
    seen: BaseException | None = stop
    while seen is not None:
        if isinstance(seen, KeyboardInterrupt):
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


def _say(line: str) -> None:
    # plain write: one line however narrow the terminal (rich would wrap it)
    sys.stderr.write(f"xmalign: {line}\n")


def _stopped(interrupt: KeyboardInterrupt | None) -> None:
    message = str(interrupt.args[0]) if interrupt is not None and interrupt.args else ""
    if not isinstance(interrupt, StopSignal):
        _say(message or "stopped by Ctrl-C")
        sys.exit(EXIT_INTERRUPTED)
    if not message:
        _say(f"stopped by {interrupt.name}")
    else:
        _say(message if interrupt.name in message else f"{interrupt.name}: {message}")
    sys.exit(128 + interrupt.signum)


def main() -> None:
    """Console-script entry point."""
    keep_library_logs_off_the_terminal()
    try:
        with stop_signals_as_interrupts():
            app()
    except SystemExit as stop:
        if stop.code == EXIT_INTERRUPTED:
            _stopped(_interrupt_of(stop))
        raise
    except KeyboardInterrupt as interrupt:
        _stopped(interrupt)
    except XmalignError as error:
        _say(f"error: {error}")
        sys.exit(2)
    except OSError as error:
        # no file behind it (a name lookup, a socket): no "file:" that names nothing
        where = f"{error.filename}: " if error.filename is not None else ""
        _say(f"error: {where}{os_problem(error)}")
        sys.exit(2)
    except UnicodeDecodeError as error:  # a reader that did not go through read_text
        _say(f"error: an input file is not UTF-8 text (byte 0x{error.object[error.start]:02x})")
        sys.exit(2)


if __name__ == "__main__":
    main()
