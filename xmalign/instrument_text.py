"""What the joint fit of tracker points and tracer lengths tells a person (one line each).

The console (``xmalign post``, the instruments' dry run) and the record
(:mod:`xmalign.report`) print these; the fit itself (:mod:`xmalign.post.instruments`)
writes no text.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from xmalign.geometry import Vec
from xmalign.post.instruments import FACTOR_TOLERANCE, JointFit


def describe_undetermined(names: Iterable[str]) -> str:
    """One line for the report: which rotations the points could not see."""
    listed = ", ".join(names)
    return (
        f"{listed}: a point cannot see these rotations (no lever arm changes); written as 0"
        " without u95, the tables are those of the SMR as the functional point (measure with"
        " two or more SMR positions, smr_offsets_mm, to see them)"
    )


def _triple(values: Vec, digits: int = 3) -> str:
    return ", ".join(f"{v:.{digits}f}" for v in values)


def _covered_text(covered_mm: tuple[Vec, Vec]) -> str:
    spans = (f"{a} {lo:.0f}..{hi:.0f}" for a, lo, hi in zip("XYZ", *covered_mm, strict=True))
    return "covered " + ", ".join(spans) + " mm"


def _scale_text(scale_ppm: dict[int, float], u95_ppm: dict[int, float]) -> str:
    runs = ", ".join(f"run {r} {s:+.2f} (U95 {u95_ppm[r]:.2f})" for r, s in scale_ppm.items())
    return f"; scale {runs} ppm" if runs else ""


def _correlation_text(samples: float) -> str:
    if samples <= 1.0 + FACTOR_TOLERANCE:
        return ""
    return (
        f"; noise correlated over {samples:.1f} points on the fly (U95 widened"
        f" {np.sqrt(samples):.2f}x)"
    )


def instrument_lines(joint: JointFit) -> list[str]:
    """One line per tracker station (pose) and tracer place (pivot, constants), with U95."""
    lines = []
    for s in joint.trackers:
        angles = ""
        if len(s.angle_coefficients_urad):
            rms = float(np.sqrt(np.sum(s.angle_coefficients_urad**2) / 4))
            angles = f"; systematic angle errors {rms:.1f} urad RMS"
        lines.append(
            f"tracker {s.label} ({s.n_points} points, {s.source}): origin"
            f" {_triple(s.position_mm)} mm (U95 {_triple(s.position_u95_mm)}), rotation"
            f" {_triple(s.rotation_urad, 0)} urad (U95 {_triple(s.rotation_u95_urad, 1)});"
            f" residual {s.residual_rms_um:.2f} um RMS (scatter / model {s.scatter_factor:.2f})"
            f"{_correlation_text(s.correlation_samples)}{angles}"
            f"{_scale_text(s.scale_ppm, s.scale_u95_ppm)}; {_covered_text(s.covered_mm)}"
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
            f" {p.scatter_factor:.2f}){_scale_text(p.scale_ppm, p.scale_u95_ppm)};"
            f" {_covered_text(p.covered_mm)}"
        )
    return lines


def instrument_notes(joint: JointFit) -> list[str]:
    """What the user should know about the joint fit (one line each)."""
    notes = []
    if joint.undetermined:
        notes.append(describe_undetermined(joint.undetermined))
    if joint.spacing_scores:
        tried = ", ".join(f"{s:.0f}" for s, _ in joint.spacing_scores)
        notes.append(
            f"compensation points {joint.knot_spacing_mm:.0f} mm apart: the least generalised"
            f" cross-validation score of {tried} mm (post --knot-spacing-mm sets it)"
        )
    return notes
