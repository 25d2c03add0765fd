"""``xmalign mc``: Monte Carlo planning of a calibration, strategies side by side."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich import box
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table as RichTable

from xmalign.cli.common import (
    check_seed,
    console,
    error_console,
    machine_or_default,
    output_folder,
    refuse_unused_options,
)
from xmalign.cli.instruments import compare_instruments_command
from xmalign.errors import InputError, TransportError, XmalignError
from xmalign.formats.common import (
    MAX_ERROR_RAD,
    atomic_write_text,
    check_output_folder,
    refuse_overwriting,
)
from xmalign.formats.provenance import FileSource, sources
from xmalign.formats.studies import study_document

if TYPE_CHECKING:
    from sim.mc import StrategyResult, StudySettings

#: The quantity a tolerance applies to, per mode.
TOLERANCE_QUANTITY = {
    "identification": "position_error_um",
    "calibration": "volumetric_after_um",
}


@contextmanager
def _executor(scheduler: str | None, workers: int) -> Iterator[Executor]:
    """Local processes, or the Dask cluster whose scheduler is at ``scheduler``."""
    if scheduler is None:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            yield pool
        return
    try:
        from dask.distributed import Client
    except ImportError as error:
        raise InputError(
            "--scheduler needs dask.distributed: pip install 'xmalign[cluster]'"
        ) from error
    try:
        client = Client(scheduler, timeout="5s")
    except (OSError, TimeoutError) as error:
        raise TransportError(f"--scheduler {scheduler}: cannot connect ({error})") from error
    with client:
        yield client.get_executor(pure=False)


#: Decimals shown at most.
MAX_DECIMALS = 6


def estimate_decimals(mean: float, uncertainty: float) -> int:
    """Decimals for a mean and its uncertainty: two significant digits of the uncertainty,
    but no finer than four of the mean (a near-constant quantity reads ``351.0 ± 0.0``)."""
    resolution = max(abs(uncertainty) / 10, abs(mean) * 1e-3)
    if not math.isfinite(resolution) or resolution == 0:
        return 0
    return int(min(MAX_DECIMALS, max(0, -math.floor(math.log10(resolution)))))


def _estimate_cells(result: StrategyResult, name: str) -> tuple[str, str]:
    """``mean ± u`` and ``[low, high]`` with sensible digits, or dashes."""
    if result.study.values(name).size < 2:
        return "-", "-"
    s = result.study.summaries()[name]
    d = estimate_decimals(s.mean, s.standard_uncertainty)
    return f"{s.mean:.{d}f} ± {s.standard_uncertainty:.{d}f}", f"[{s.low:.{d}f}, {s.high:.{d}f}]"


def _table(results: Sequence[StrategyResult], tolerance_um: float | None, mode: str) -> RichTable:
    """A row per quantity, then one per strategy: the width does not grow with the strategies."""
    from sim.mc import quantity_label

    table = RichTable(
        title="Monte Carlo: mean ± standard uncertainty, 95 % interval",
        title_justify="left",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
    )
    table.add_column("quantity / strategy", no_wrap=True)
    table.add_column("mean ± u", justify="right", no_wrap=True)
    table.add_column("95 % interval", justify="right", no_wrap=True)

    def group(label: str, cells: Sequence[tuple[str, str]]) -> None:
        table.add_row(label, "", "", style="bold")
        for result, (value, interval) in zip(results, cells, strict=True):
            table.add_row(f"  {result.strategy.name}", value, interval)

    names = list(dict.fromkeys(n for r in results for n in r.study.names))
    for name in names:
        group(quantity_label(name), [_estimate_cells(r, name) for r in results])
    if tolerance_um is not None:
        quantity = TOLERANCE_QUANTITY[mode]
        group(
            f"P({quantity_label(quantity).split(',')[0]} <= {tolerance_um:g} um)",
            [(_within(r, quantity, tolerance_um), "") for r in results],
        )
    group("trials (failed)", [(f"{r.trials} ({len(r.failures)})", "") for r in results])
    group("stable (GUM S1 7.9)", [("yes" if r.stable else "no", "") for r in results])
    return table


def _within(result: StrategyResult, quantity: str, tolerance_um: float) -> str:
    values = result.study.values(quantity)
    if not result.trials:
        return "-"
    # a failed trial did not meet the tolerance either
    return f"{np.count_nonzero(values <= tolerance_um) / result.trials:.1%}"


def _refuse_if_every_trial_failed(results: Sequence[StrategyResult]) -> None:
    """A study whose every trial failed has no result: say why, exit non-zero."""
    failures = [failure for result in results for failure in result.failures]
    trials = sum(result.trials for result in results)
    if trials and len(failures) == trials:
        raise XmalignError(f"every trial failed ({trials} of {trials}), e.g. {failures[0]}")


def _plot(draw: Callable[[], Path | None], name: str) -> Path | None:
    """Draw one figure; a failure is a warning (the results are already written)."""
    try:
        return draw()
    except Exception as error:  # noqa: BLE001 - no plot is worth the study's results
        error_console.print(
            f"warning: {name} not drawn ({type(error).__name__}: {error})",
            style="yellow",
            markup=False,
        )
        return None


def _results_json(
    results: Sequence[StrategyResult],
    settings: StudySettings,
    machine_name: str,
    inputs: Sequence[FileSource] = (),
) -> str:
    body = {
        "machine": machine_name,
        "mode": settings.mode,
        "digits": settings.digits,
        "batch": settings.batch,
        "seed": settings.seed,
        "strategies": [
            {
                "name": r.strategy.name,
                "placement": r.strategy.placement,
                "identification": r.strategy.identification,
                "alignments": r.strategy.alignments,
                "target_spacing_mm": r.strategy.target_spacing_mm,
                "runs": r.strategy.runs,
                "diagonal_runs": r.strategy.diagonal_runs,
                "trials": r.trials,
                "failed": len(r.failures),
                "failures": sorted(set(r.failures)),
                "stable": r.stable,
                "quantities": {
                    name: {
                        "mean": s.mean,
                        "standard_uncertainty": s.standard_uncertainty,
                        "low_95": s.low,
                        "high_95": s.high,
                        "count": s.count,
                    }
                    for name, s in r.study.summaries().items()
                },
            }
            for r in results
        ],
    }
    return json.dumps(study_document(body, inputs), indent=2) + "\n"


def mc(
    machine: Annotated[
        Path | None, typer.Option(help="Machine YAML (default: the reference machine).")
    ] = None,
    trials: Annotated[
        int, typer.Option(help="Most trials per strategy (fewer once the results are stable).")
    ] = 100,
    vary: Annotated[
        str | None,
        typer.Option(
            help="Decisions to compare, comma-separated: launch-position, identification, "
            "alignments, targets, runs, diagonal-runs; NAME=V1:V2 lists the values (e.g."
            " targets=100:50)."
        ),
    ] = None,
    mode: Annotated[
        str,
        typer.Option(
            help="calibration (the whole dry run, ~1 s a trial), identification "
            "(identification and line planning only, ~10 ms) or instruments (laser tracker,"
            " tracers and XM-60 compared on the same machines, ~10 s a trial)."
        ),
    ] = "calibration",
    batch: Annotated[
        int | None, typer.Option(help="Trials per batch of the adaptive procedure (default 20).")
    ] = None,
    digits: Annotated[
        int | None,
        typer.Option(
            help="Significant digits of the standard uncertainties to stabilise (default 1)."
        ),
    ] = None,
    scheduler: Annotated[
        str | None, typer.Option(help="Dask scheduler address (default: local processes).")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(min=0, help="Local worker processes (default, or 0: every core).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the study; every strategy sees it.")] = 0,
    method: Annotated[
        str | None, typer.Option(help="Identification method (default: joint).")
    ] = None,
    error_scale: Annotated[
        float,
        typer.Option(min=0, help="Factor on the machine-error amplitudes (seed 003 Table 1)."),
    ] = 1.0,
    squareness_urad: Annotated[
        float,
        typer.Option(
            min=0,
            max=MAX_ERROR_RAD * 1e6,
            help="Half-width of the random squareness errors, urad (at most what an error"
            " table holds).",
        ),
    ] = 20.0,
    tolerance_um: Annotated[
        float | None,
        typer.Option(
            min=0,
            help="Report the share of trials within this: volumetric error after comp "
            "(calibration) or launch position error (identification), um.",
        ),
    ] = None,
    out: Annotated[Path, typer.Option(help="Directory for mc.json and the plots.")] = Path("mc"),
) -> None:
    """Plan a calibration by Monte Carlo: compare strategies on the same random setups."""
    # imported here: the simulator is loaded only by the commands that use it
    from sim.machine import ErrorAmplitudes
    from sim.mc import StudySettings, run_study, strategies
    from sim.mc_plots import plot_envelopes, plot_histograms, plot_volumetric_map

    check_seed(seed)
    if mode == "instruments":
        refuse_unused_options(
            {
                "--vary": vary is not None,
                "--scheduler": scheduler is not None,
                "--workers": workers is not None,
                "--batch": batch is not None,
                "--digits": digits is not None,
                "--method": method is not None,
                "--tolerance-um": tolerance_um is not None,
            },
            "with --mode instruments (each instrument is simulated here, one after the other)",
        )
        amplitudes = ErrorAmplitudes(scale=error_scale, squareness_urad=squareness_urad)
        compare_instruments_command(machine_or_default(machine), trials, seed, amplitudes, out)
        return
    written_names = ("mc.json", "histograms.png", "envelopes.png", "volumetric.png")
    check_output_folder(out, "--out")
    refuse_overwriting({"--machine": machine}, {"--out": [out / name for name in written_names]})
    settings = StudySettings(
        mode=mode,
        max_trials=trials,
        batch=20 if batch is None else batch,
        digits=1 if digits is None else digits,
        seed=seed,
        method=method or "joint",
        amplitudes=ErrorAmplitudes(scale=error_scale, squareness_urad=squareness_urad),
    )
    chosen_machine = machine_or_default(machine)
    chosen = strategies(chosen_machine, (vary or "").split(","))
    progress = Progress(
        TextColumn("trials"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
    )
    # the executor first: no dask, or no scheduler there, leaves no empty folder behind
    with _executor(scheduler, workers or os.cpu_count() or 1) as executor, progress:
        output_folder(out, "--out")
        task = progress.add_task("trials", total=trials * len(chosen))
        results = run_study(
            chosen_machine, chosen, settings, executor, lambda: progress.advance(task)
        )
        progress.update(task, total=sum(r.trials for r in results))
    _refuse_if_every_trial_failed(results)
    # the results first: nothing after this may lose minutes of trials
    output_folder(out, "--out")
    document = _results_json(results, settings, chosen_machine.name, sources(machine=machine))
    atomic_write_text(out / "mc.json", document)
    console.print(_table(results, tolerance_um, mode))
    written = [
        out / "mc.json",
        _plot(lambda: plot_histograms(results, out / "histograms.png"), "histograms.png"),
        _plot(lambda: plot_envelopes(results, out / "envelopes.png"), "envelopes.png"),
        _plot(lambda: plot_volumetric_map(results, out / "volumetric.png"), "volumetric.png"),
    ]
    for result in results:
        for warning in result.design_warnings:
            console.print(
                f"warning: {result.strategy.name}: identification design: {warning}",
                style="yellow",
                markup=False,
            )
        if result.failures:
            console.print(
                f"{result.strategy.name}: {len(result.failures)} failed trial(s), e.g. "
                f"{result.failures[0]}",
                highlight=False,
            )
    console.print("wrote " + ", ".join(str(p) for p in written if p is not None), highlight=False)


def register(app: typer.Typer) -> None:
    app.command(name="mc")(mc)
