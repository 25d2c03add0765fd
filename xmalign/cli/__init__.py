"""The ``xmalign`` command line: wires the core, the drivers and the simulator together.

Each command lives in its own module with a ``register(app)`` function. Any
:class:`~xmalign.errors.XmalignError` becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import sys
from typing import Annotated

import typer

from xmalign import __version__
from xmalign.cli import align, identify
from xmalign.cli import mc as mc_command
from xmalign.cli import post as post_command
from xmalign.cli import program as program_command
from xmalign.cli import run as run_command
from xmalign.cli import sim as sim_command
from xmalign.errors import XmalignError

app = typer.Typer(
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
):
    command_module.register(app)


def main() -> None:
    """Console-script entry point."""
    try:
        app()
    except XmalignError as error:
        # plain write: one line however narrow the terminal (rich would wrap it)
        sys.stderr.write(f"xmalign: error: {error}\n")
        sys.exit(2)


if __name__ == "__main__":
    main()
