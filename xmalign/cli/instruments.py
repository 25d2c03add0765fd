"""``xmalign post --tracker/--tracer``: reading the files and printing each instrument's setup."""

from __future__ import annotations

from pathlib import Path

from rich.table import Table as RichTable

from xmalign.errors import InputError
from xmalign.formats.instruments import read_tracer_lengths, read_tracker_points
from xmalign.post.evaluate import Instruments
from xmalign.post.instruments import JointFit, describe_undetermined


def read_instruments(tracker: list[Path], tracer: list[Path]) -> Instruments:
    """The tracker-point and tracer-length files given (each option repeatable)."""
    return Instruments(
        trackers=tuple(read_tracker_points(path) for path in tracker),
        tracers=tuple(read_tracer_lengths(path) for path in tracer),
    )


def count_readings(instruments: Instruments) -> str:
    """``"500 tracker points, 1760 tracer lengths"`` (what is being fitted besides the lines)."""
    points = sum(len(file.points) for file in instruments.trackers)
    lengths = sum(len(file.lengths) for file in instruments.tracers)
    parts = [f"{points} tracker points"] if points else []
    return ", ".join(parts + ([f"{lengths} tracer lengths"] if lengths else []))


def check_inputs(
    plans: list[Path], tracker: list[Path], tracer: list[Path], verify_needs_plan: bool
) -> None:
    """Refuse a ``post`` with nothing to fit, or a verification without a plan (one line)."""
    if not plans and not tracker and not tracer:
        raise InputError(
            "post: nothing to fit; give --plan/--data pairs, --tracker FILE or --tracer FILE"
        )
    if not plans and verify_needs_plan:
        raise InputError("post: --verify-data needs --verify-plan when no --plan is given")


def _triple(values, digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def instruments_table(joint: JointFit) -> RichTable:
    """Each tracker station's pose and each tracer place's pivot and constants, with u95."""
    table = RichTable(title="Instruments (setup with U95, k = 2; residual RMS)")
    table.add_column("instrument")
    table.add_column("setup")
    table.add_column("U95", justify="right")
    table.add_column("residual um (scatter / model)", justify="right")
    table.add_column("covered X/Y/Z mm")
    for s in joint.trackers:
        covered = " / ".join(f"{lo:.0f}..{hi:.0f}" for lo, hi in zip(*s.covered_mm, strict=True))
        table.add_row(
            f"tracker {s.label} ({s.n_points} points)",
            f"origin {_triple(s.position_mm)} mm\nrotation {_triple(s.rotation_urad, 0)} urad",
            f"{_triple(s.position_u95_mm)}\n{_triple(s.rotation_u95_urad, 1)}",
            f"{s.residual_rms_um:.2f} ({s.scatter_factor:.2f})",
            covered,
        )
    for p in joint.tracers:
        covered = " / ".join(f"{lo:.0f}..{hi:.0f}" for lo, hi in zip(*p.covered_mm, strict=True))
        constants = ", ".join(f"run {r}: {k:.4f}" for r, k in p.constant_mm.items())
        u95 = ", ".join(f"{u:.4f}" for u in p.constant_u95_mm.values())
        table.add_row(
            f"tracer {p.label} ({p.n_lengths} lengths)",
            f"pivot {_triple(p.pivot_mm, 4)} mm\nconstant {constants} mm",
            f"{_triple(p.pivot_u95_mm, 4)}\n{u95}",
            f"{p.residual_rms_um:.3f} ({p.scatter_factor:.2f})",
            covered,
        )
    return table


def instrument_notes(joint: JointFit) -> list[str]:
    """What the user should know about the joint fit (one line each)."""
    notes = []
    if joint.undetermined:
        notes.append(describe_undetermined(joint.undetermined))
    if not joint.converged:
        notes.append(
            f"the fit did not settle in {joint.iterations} iterations; check the instruments'"
            " setups and the points"
        )
    return notes
