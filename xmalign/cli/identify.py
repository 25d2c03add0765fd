"""``xmalign identify``: the launch unit's pose from an identification session."""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from rich.table import Table

from xmalign.beam_search import BeamSearchSettings
from xmalign.cli.common import (
    ForceOption,
    LogFileOption,
    check_positions,
    check_seed,
    console,
    machine_or_default,
    named_by_options,
    start_log_file,
    stop_log_file,
)
from xmalign.errors import InputError
from xmalign.formats.common import link_target
from xmalign.formats.session import Session, read_session
from xmalign.identification_routine import RoutineEvent
from xmalign.identify import METHODS, IdentificationResult, IdentificationUncertainty
from xmalign.machine import MAX_UNCERTAINTY_UM, MAX_UNCERTAINTY_URAD, Machine
from xmalign.steps import (
    IdentifyStepResult,
    check_outputs,
    design_step,
    identify_step,
    solve_step,
    write_pose_step,
)


def _uncertainty(
    machine: Machine | None, overrides: dict[str, tuple[str, float | None]]
) -> IdentificationUncertainty:
    """The machine's (or the default) uncertainties with the options given (option name ->
    (field, value in um or urad))."""
    base = (
        IdentificationUncertainty.from_machine(machine.uncertainty)
        if machine is not None
        else IdentificationUncertainty()
    )
    scale = {
        "encoder_rad": 1e-6,
        "machine_position_mm": 1e-3,
        "unit_kinematics_mm": 1e-3,
        "zero_offset_rad": 1e-6,
        "distance_mm": 1e-3,
        "tool_rotation_rad": 1e-6,
        "tool_rotation_common_rad": 1e-6,
        "machine_common_mm": 1e-3,
        "collimation_rad": 1e-6,
    }
    for option, (key, value) in overrides.items():
        unit, limit = (
            ("um", MAX_UNCERTAINTY_UM) if option.endswith("-um") else ("urad", MAX_UNCERTAINTY_URAD)
        )
        if value is not None and not 0 < value <= limit:
            raise InputError(
                f"option {option} ({key}): {value:g}: the uncertainty must be positive and at"
                f" most {limit:g} {unit} (as in the machine file)"
            )
    changes = {key: value * scale[key] for key, value in overrides.values() if value is not None}
    return IdentificationUncertainty(**{**base.__dict__, **changes})


def print_result(result: IdentificationResult, session: Session, truth: dict | None = None) -> None:
    """A readable summary: pose with U (k=2), offsets, per-alignment contributions, warnings."""
    sigma = np.sqrt(np.diag(result.covariance))
    title = (
        f"Launch-unit pose ({result.method}, {result.n_used} of {len(session.alignments)} "
        f"alignments, chi2/dof = {result.chi2:.1f}/{result.dof})"
    )
    pose = Table(title=title, title_justify="left")
    pose.add_column("")
    pose.add_column("identified", justify="right")
    pose.add_column("U (k=2)", justify="right")
    if truth is not None:
        pose.add_column("truth", justify="right")
        pose.add_column("error", justify="right")
    for k, axis in enumerate("xyz"):
        row = [f"{axis} mm", f"{result.position_mm[k]:.4f}", f"±{2 * sigma[k] * 1e3:.1f} µm"]
        if truth is not None:
            error_um = (result.position_mm[k] - truth["position_mm"][k]) * 1e3
            row += [f"{truth['position_mm'][k]:.4f}", f"{error_um:+.1f} µm"]
        pose.add_row(*row)
    row = ["gamma °", f"{math.degrees(result.gamma_rad):.6f}", f"±{2 * sigma[3] * 1e6:.1f} µrad"]
    if truth is not None:
        error_urad = math.remainder(result.gamma_rad - truth["gamma_rad"], math.tau) * 1e6
        row += [f"{math.degrees(truth['gamma_rad']):.6f}", f"{error_urad:+.1f} µrad"]
    pose.add_row(*row)
    for k, (name, value) in enumerate(result.offsets_rad.items()):
        row = [f"{name} µrad", f"{value * 1e6:.1f}"]
        row.append(f"±{2 * np.sqrt(result.offsets_covariance[k, k]) * 1e6:.1f}")
        if truth is not None:
            row += [
                f"{truth['offsets'][name] * 1e6:.1f}",
                f"{(value - truth['offsets'][name]) * 1e6:+.1f}",
            ]
        pose.add_row(*row)
    console.print(pose)
    for name, reason in result.offsets_not_estimated.items():
        console.print(f"{name} not estimated: {reason}", markup=False)
    console.print(f"RMS beam miss {result.residual_rms_um:.1f} µm", markup=False)
    contributions = Table(title="What each alignment contributes", title_justify="left")
    for header in ("#", "machine mm", "position var %", "gamma var %", "residual / σ"):
        contributions.add_column(header, justify="right")
    for report, alignment in zip(result.alignments, session.alignments, strict=True):
        machine = ", ".join(f"{v:.0f}" for v in alignment.machine_mm)
        if report.excluded:
            contributions.add_row(str(report.index + 1), machine, "-", "-", "rejected")
            continue
        contributions.add_row(
            str(report.index + 1),
            machine,
            f"{report.share_position * 100:.0f}",
            f"{report.share_gamma * 100:.0f}",
            f"{report.normalized_residual:.2f}",
        )
    console.print(contributions)
    for warning in result.warnings:
        console.print(f"warning: {warning}", style="yellow", markup=False)


def _simulated_identification(
    machine: Machine,
    alignments: int,
    seed: int,
    method: str,
    session_path: Path,
    uncertainty: IdentificationUncertainty,
) -> tuple[IdentificationResult, dict]:
    """The identification routine on the virtual machine with simulated units."""
    from sim.dry_run import identify_virtually, virtual_setup

    setup = virtual_setup(machine, seed)
    design = design_step(machine, alignments)
    _print_design_warnings(design.warnings)
    positions = design.machine_mm
    with _progress_of_routine(alignments) as on_event:
        result = identify_virtually(
            setup,
            machine,
            positions,
            session_path,
            method,
            seed,
            on_event=on_event,
            uncertainty=uncertainty,
        )
    world = setup.world
    offsets = world.offsets
    truth = {
        "position_mm": world.launch2mcs_mm,
        "gamma_rad": world.gamma_rad,
        "offsets": {"c2": offsets.c2, "c3": offsets.c3, "c4": offsets.c4},
    }
    return result, truth


@contextmanager
def _progress_of_routine(total: int) -> Iterator[Callable[[RoutineEvent], None]]:
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), console=console
    ) as progress:
        task = progress.add_task("identification", total=total)

        def on_event(event: RoutineEvent) -> None:
            progress.update(task, description=f"identification: {event.stage}")
            if event.stage == "searching":
                progress.console.print(
                    f"position {event.index}: searching the beam (no launch azimuth in the"
                    " machine file): the launch unit turns once round, again for other places"
                    " of it near the machine file's if needed (at most"
                    f" {BeamSearchSettings().timeout_s:.0f} s)",
                    markup=False,
                    highlight=False,
                )
            if event.stage in ("recorded", "skipped"):
                progress.advance(task)

        yield on_event


def _simulated_session(
    machine: Machine,
    alignments: int,
    seed: int,
    method: str,
    session_out: Path | None,
    uncertainty: IdentificationUncertainty,
) -> tuple[IdentificationResult, Session, dict]:
    """``identify --sim``: the result, the session and the truth; the session written to
    ``session_out`` (a link's target, the link kept), else to a temporary folder removed
    at the end (nothing is left behind)."""
    with tempfile.TemporaryDirectory(prefix="xmalign-identify-") as temporary:
        session_path = session_out or Path(temporary) / "session.json"
        link_target(session_path).unlink(missing_ok=True)  # --force: a link stays a link
        result, truth = _simulated_identification(
            machine, alignments, seed, method, session_path, uncertainty
        )
        return result, read_session(session_path), truth


def _live_identification(
    machine: Machine,
    config_path: Path,
    alignments: int,
    session_path: Path,
    method: str,
    uncertainty: IdentificationUncertainty,
) -> IdentifyStepResult:
    """The identification routine on real units: the operator moves the machine (or a CNC
    position file tells where it is), the units point and fine-align, and every alignment
    is written to ``session_path`` at once, so an interrupted routine resumes."""
    from firmware_iface.config import load_units_config, open_devices
    from xmalign.alignment import AlignmentDevices
    from xmalign.cli.align import manual_alignment
    from xmalign.identification_routine import RoutineDevices
    from xmalign.roles import WallClock

    config = load_units_config(config_path)
    design = design_step(machine, alignments)
    _print_design_warnings(design.warnings)
    with open_devices(config, machine) as live:
        clock = WallClock()
        devices = RoutineDevices(live.mover, live.launch, live.receiver, live.interferometer, clock)
        jog = AlignmentDevices(live.launch, live.receiver, live.interferometer, clock, 1000.0)
        with _progress_of_routine(alignments) as on_event:
            return identify_step(
                design.machine_mm,
                machine,
                devices,
                session_path,
                method,
                uncertainty,
                manual_align=lambda: manual_alignment(jog, machine, config.timeouts.move_s),
                on_event=on_event,
                unit_timeout_s=config.timeouts.move_s,
                search=BeamSearchSettings(),
            )


def _print_design_warnings(warnings: list[str]) -> None:
    for warning in warnings:
        console.print(f"warning: identification design: {warning}", style="yellow", markup=False)


def identify_command(
    input: Annotated[
        Path | None, typer.Option("--input", help="Identification session JSON.")
    ] = None,
    out: Annotated[Path | None, typer.Option(help="Write the launch-pose JSON here.")] = None,
    method: Annotated[str, typer.Option(help=f"One of {', '.join(METHODS)}.")] = "joint",
    live: Annotated[
        bool, typer.Option("--live", help="Run the identification routine on real units.")
    ] = False,
    config: Annotated[
        Path | None, typer.Option(help="With --live: the hardware configuration units.yaml.")
    ] = None,
    session_file: Annotated[
        Path | None,
        typer.Option("--session", help="With --live: session file, written as it goes (resumed)."),
    ] = None,
    sim: Annotated[
        bool, typer.Option("--sim", help="Simulate a session on the virtual machine.")
    ] = False,
    machine: Annotated[
        Path | None, typer.Option(help="Machine YAML (uncertainty defaults; --sim machine).")
    ] = None,
    alignments: Annotated[
        int,
        typer.Option(
            min=3, help="How many alignments (identification positions), with --sim or --live."
        ),
    ] = 6,
    seed: Annotated[int, typer.Option(help="Seed of the simulation.")] = 1,
    session_out: Annotated[
        Path | None, typer.Option(help="With --sim: also write the simulated session.")
    ] = None,
    encoder_urad: Annotated[float | None, typer.Option(help="Encoder noise, µrad (k=1).")] = None,
    machine_position_um: Annotated[
        float | None, typer.Option(help="Machine positioning uncertainty, µm (k=1).")
    ] = None,
    unit_kinematics_um: Annotated[
        float | None, typer.Option(help="Units' optical-centre uncertainty, µm (k=1).")
    ] = None,
    zero_offset_urad: Annotated[
        float | None, typer.Option(help="Encoder zero-offset uncertainty, µrad (k=1).")
    ] = None,
    distance_um: Annotated[
        float | None, typer.Option(help="Distance uncertainty, µm (k=1).")
    ] = None,
    tool_rotation_urad: Annotated[
        float | None,
        typer.Option(help="Tool rotation varying between alignments, µrad (k=1)."),
    ] = None,
    tool_rotation_common_urad: Annotated[
        float | None,
        typer.Option(help="Tool rotation common to all alignments, µrad (k=1)."),
    ] = None,
    machine_common_um: Annotated[
        float | None,
        typer.Option(help="Machine position error common to all alignments, µm (k=1)."),
    ] = None,
    beam_collimation_urad: Annotated[
        float | None, typer.Option(help="Beam collimation (direction) uncertainty, µrad (k=1).")
    ] = None,
    log_file: LogFileOption = None,
    force: ForceOption = False,
) -> None:
    """Identify the launch unit's pose (position and azimuth) from aligned units."""
    if method not in METHODS:
        raise InputError(f"--method: unknown method '{method}' (choose {', '.join(METHODS)})")
    if (input is not None) + sim + live != 1:
        raise InputError("give one of --input SESSION.json, --sim or --live")
    if live and (config is None or session_file is None):
        raise InputError("--live needs --config UNITS.yaml and --session SESSION.json")
    check_seed(seed)
    if sim or live:
        check_positions(alignments, "--alignments")
    session_option = "--input" if input else "--session-out" if sim else "--session"
    caller = named_by_options(
        {"path": "--out", "session_path": session_option, "machine": "--machine"},
        read={"--input": input, "--machine": machine, "--config": config},
        appended={"--log-file": log_file},
    )
    # checked now, before the routine; the pose is written by the step at the end
    check_outputs(
        {"path": out, "--session-out": session_out}, {"--session": session_file}, force, caller
    )
    machine_model = machine_or_default(machine) if (sim or live or machine is not None) else None
    uncertainty = _uncertainty(
        machine_model,
        {
            "--encoder-urad": ("encoder_rad", encoder_urad),
            "--machine-position-um": ("machine_position_mm", machine_position_um),
            "--unit-kinematics-um": ("unit_kinematics_mm", unit_kinematics_um),
            "--zero-offset-urad": ("zero_offset_rad", zero_offset_urad),
            "--distance-um": ("distance_mm", distance_um),
            "--tool-rotation-urad": ("tool_rotation_rad", tool_rotation_urad),
            "--tool-rotation-common-urad": ("tool_rotation_common_rad", tool_rotation_common_urad),
            "--machine-common-um": ("machine_common_mm", machine_common_um),
            "--beam-collimation-urad": ("collimation_rad", beam_collimation_urad),
        },
    )
    truth = None
    if sim:
        assert machine_model is not None  # loaded above for --sim
        result, session, truth = _simulated_session(
            machine_model, alignments, seed, method, session_out, uncertainty
        )
    elif live:
        assert machine_model and config and session_file  # checked above for --live
        log_handler = start_log_file(log_file)
        try:
            identified = _live_identification(
                machine_model, config, alignments, session_file, method, uncertainty
            )
        finally:
            stop_log_file(log_handler)
        result, session = identified.result, identified.session
    else:
        assert input is not None  # one of --input, --sim, --live (checked above)
        solved = solve_step(input, uncertainty, method, machine_model)
        result, session = solved.result, solved.session
    print_result(result, session, truth)
    if out is not None:
        # --sim without --session-out: the session was not kept, the pose cannot name it
        session_used = input or (session_out if sim else session_file)
        write_pose_step(out, result, session_used, machine_model, force, caller)
        console.print(f"pose written to {out}", markup=False)
    else:
        console.print(
            "pose not written (give --out pose.json to keep it for xmalign program)",
            markup=False,
        )


def register(app: typer.Typer) -> None:
    app.command("identify")(identify_command)
