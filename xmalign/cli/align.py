"""``xmalign align``: align the launch and receiver units to each other.

``--sim`` builds a virtual setup (seeded), puts the units a given distance off
alignment and shows the automatic fine alignment converging, in simulated
time. ``--live --config units.yaml`` does the same on the hardware the
configuration names. ``--manual`` first lets the operator jog the axes from
the terminal until every beam is in range. The units are left stopped and
locked however the command ends.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.table import Table

from xmalign.alignment import (
    DISTANCE_LIMITS_MM,
    AlignmentDevices,
    AlignmentStep,
    FineAlignmentResult,
    FineAlignmentSettings,
    fine_align,
    jog,
    parse_jog,
    range_used,
)
from xmalign.cli.common import (
    LogFileOption,
    check_seed,
    console,
    machine_or_default,
    start_log_file,
    stop_log_file,
)
from xmalign.errors import InputError, OutOfRangeError, XmalignError
from xmalign.formats.common import refuse_overwriting
from xmalign.machine import Machine
from xmalign.roles import WallClock
from xmalign.safety import interrupted, units_locked_on_exit

#: Column names of the aligned channels (xmalign.alignment.ALIGNED_CHANNELS order).
_SHORT = ("sv um", "sw um", "aw urad", "av urad", "au urad")


def _step_table() -> Table:
    table = Table(title="Fine alignment", title_justify="left")
    table.add_column("t s", justify="right")
    for name in _SHORT:
        table.add_column(name, justify="right")
    table.add_column("l mm", justify="right")
    return table


def _step_adder(table: Table) -> Callable[[AlignmentStep], None]:
    """Add each step as a row; times from the first reading (the interferometer's clock,
    which is not the host's)."""
    first_s: list[float] = []

    def add(step: AlignmentStep) -> None:
        first_s[:] = first_s or [step.time_s]
        values = [f"{v:+.2f}" for v in step.error] + [""] * (len(_SHORT) - len(step.error))
        table.add_row(f"{step.time_s - first_s[0]:.3f}", *values, f"{step.distance_mm:.0f}")

    return add


def run_fine_alignment(
    devices: AlignmentDevices, settings: FineAlignmentSettings, time_label: str
) -> FineAlignmentResult:
    """Fine-align with a live table of the steps; the units are locked on any exit."""
    table = _step_table()
    with units_locked_on_exit(devices.launch, devices.receiver):
        result = fine_align(
            devices.launch,
            devices.receiver,
            devices.interferometer,
            devices.clock,
            devices.distance_mm,
            settings,
            on_step=_step_adder(table),
        )
    console.print(table)
    console.print(
        f"converged in {result.elapsed_s:.3f} s of {time_label} after {len(result.steps)} steps;"
        " units locked",
        markup=False,
    )
    return result


def manual_alignment(devices: AlignmentDevices, machine: Machine, move_timeout_s: float) -> None:
    """Jog loop: show how much of each range the channels use until the operator is done."""
    ranges = machine.interferometer
    console.print(
        "Jog: 'a<n> <deg>' moves axis a<n> (e.g. 'a2 -0.01'); Enter when all beams are in range.",
        markup=False,
    )
    while True:
        reading = devices.interferometer.read()
        if reading.beam_ok:
            used = range_used(reading, ranges.straightness_range_um, ranges.angle_range_urad)
            shown = ", ".join(
                f"{name.split()[0]} {100 * u:.0f}%" for name, u in zip(_SHORT, used, strict=True)
            )
            console.print(f"beam in range: {shown}", markup=False)
        else:
            console.print("beam out of range", markup=False)
        try:
            text = input("jog> ")
        except EOFError as error:
            raise XmalignError("no answer from the operator (end of input)") from error
        if not text.strip():
            if reading.beam_ok:
                return
            console.print("the beam is not in range yet", markup=False)
            continue
        try:
            jog(devices.launch, devices.receiver, parse_jog(text), move_timeout_s)
        except (InputError, OutOfRangeError) as error:  # a typo or a refused step: ask again
            console.print(str(error), markup=False)


def _parse_at(text: str | None, machine: Machine) -> np.ndarray:
    if text is None:
        low, high = machine.travel_min_mm, machine.travel_max_mm
        return low + np.array([0.8, 0.7, 0.8]) * (high - low)
    try:
        position = np.array([float(v) for v in text.split(",")])
    except ValueError as error:
        raise InputError(f"option --at: '{text}' is not 'x,y,z' in mm") from error
    if position.shape != (3,):
        raise InputError(f"option --at: '{text}' is not 'x,y,z' in mm")
    if not machine.within_travel(position):
        raise InputError(f"option --at: {text} is outside the travel of '{machine.name}'")
    return position


def register(app: typer.Typer) -> None:
    @app.command()
    def align(
        sim: Annotated[bool, typer.Option("--sim", help="Align in a simulated setup.")] = False,
        live: Annotated[bool, typer.Option("--live", help="Align the units of --config.")] = False,
        config: Annotated[Path | None, typer.Option(help="units.yaml for --live.")] = None,
        machine_file: Annotated[
            Path | None, typer.Option("--machine", help="Machine YAML.")
        ] = None,
        manual: Annotated[bool, typer.Option(help="Jog into range first.")] = False,
        at: Annotated[str | None, typer.Option(help="--sim: CNC tool point 'x,y,z' mm.")] = None,
        seed: Annotated[int, typer.Option(help="--sim: seed of the virtual setup.")] = 1,
        start_um: Annotated[float, typer.Option(help="--sim: initial beam miss, um.")] = 200.0,
        start_urad: Annotated[float, typer.Option(help="--sim: initial angle error, urad.")] = 300,
        distance_mm: Annotated[
            float | None,
            typer.Option(
                min=DISTANCE_LIMITS_MM[0],
                max=DISTANCE_LIMITS_MM[1],
                help="First guess of the cp-to-cp distance, mm (--sim: the true one,"
                " --live: 1000).",
            ),
        ] = None,
        timeout_s: Annotated[
            float, typer.Option("--timeout", min=0, help="Give up after, s.")
        ] = 5.0,
        log_file: LogFileOption = None,
    ) -> None:
        """Fine-align the launch and receiver units on the interferometer channels."""
        if sim == live:
            raise InputError("choose one of --sim and --live")
        check_seed(seed)
        refuse_overwriting(
            {"--config": config, "--machine": machine_file}, {}, {"--log-file": log_file}
        )
        machine = machine_or_default(machine_file)
        settings = FineAlignmentSettings(timeout_s=timeout_s)
        log_handler = start_log_file(log_file)
        try:
            if sim:
                from sim.alignment_setup import simulated_setup

                _, devices = simulated_setup(
                    machine, _parse_at(at, machine), seed, start_um, start_urad
                )
                devices.distance_mm = distance_mm or devices.distance_mm
                if manual:
                    manual_alignment(devices, machine, 60.0)
                run_fine_alignment(devices, settings, "simulated time")
                return
            if config is None:
                raise InputError("--live needs --config units.yaml")
            _align_live(config, machine, settings, distance_mm or 1000.0, manual)
        except KeyboardInterrupt as error:
            raise interrupted(error) from error
        finally:
            stop_log_file(log_handler)


def _align_live(
    config_path: Path,
    machine: Machine,
    settings: FineAlignmentSettings,
    distance_mm: float,
    manual: bool,
) -> None:
    from firmware_iface.config import load_units_config, open_devices

    config = load_units_config(config_path)
    with open_devices(config, machine) as live:
        devices = AlignmentDevices(
            live.launch, live.receiver, live.interferometer, WallClock(), distance_mm
        )
        with units_locked_on_exit(live.launch, live.receiver):
            if manual:
                manual_alignment(devices, machine, config.timeouts.move_s)
        run_fine_alignment(devices, settings, "wall time")
