"""``xmalign post --tracker/--tracer``: reading the files and printing each instrument's setup."""

from __future__ import annotations

from pathlib import Path

from xmalign.errors import InputError
from xmalign.formats.instruments import read_tracer_lengths, read_tracker_points
from xmalign.geometry import Vec
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


def _triple(values: Vec, digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def _covered(covered_mm: tuple[Vec, Vec]) -> str:
    spans = (f"{a} {lo:.0f}..{hi:.0f}" for a, lo, hi in zip("XYZ", *covered_mm, strict=True))
    return "covered " + ", ".join(spans) + " mm"


def instrument_lines(joint: JointFit) -> list[str]:
    """One line per tracker station (pose) and tracer place (pivot, constants), with U95."""
    lines = []
    for s in joint.trackers:
        lines.append(
            f"tracker {s.label} ({s.n_points} points, {s.source}): origin"
            f" {_triple(s.position_mm)} mm (U95 {_triple(s.position_u95_mm)}), rotation"
            f" {_triple(s.rotation_urad, 0)} urad (U95 {_triple(s.rotation_u95_urad, 1)});"
            f" residual {s.residual_rms_um:.2f} um RMS (scatter / model {s.scatter_factor:.2f});"
            f" {_covered(s.covered_mm)}"
        )
    for p in joint.tracers:
        constants = ", ".join(
            f"run {run} {k:.4f} (U95 {p.constant_u95_mm[run]:.4f})"
            for run, k in p.constant_mm.items()
        )
        lines.append(
            f"tracer {p.label} ({p.n_lengths} lengths, {p.source}): pivot"
            f" {_triple(p.pivot_mm, 4)} mm (U95 {_triple(p.pivot_u95_mm, 4)}), constant"
            f" {constants} mm; residual {p.residual_rms_um:.3f} um RMS (scatter / model"
            f" {p.scatter_factor:.2f}); {_covered(p.covered_mm)}"
        )
    return lines


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
