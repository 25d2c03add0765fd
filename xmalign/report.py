"""The calibration report: one self-contained HTML page with matplotlib PNGs.

Shows each error table with its expanded uncertainty band (and the forward /
reverse tables with bidirectional data), the squareness, the ISO 230-2 figures
of the axis lines, the setup terms and residuals of the fit, and the
volumetric error map over the travel before and after the controller's
compensation tables. Figures are drawn with matplotlib's object interface
(no pyplot, no global backend), so the report works headless.
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from xmalign.comp import fit_for, remaining_errors
from xmalign.formats.common import atomic_write_text
from xmalign.formats.error_tables import ErrorTableSet, file_unit
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.post.evaluate import PostResult
from xmalign.rigid_body import (
    AXES,
    AXIS_INDEX,
    ROTATION_NAMES,
    TRANSLATION_NAMES,
    Chain,
    ErrorModel,
    deviation,
)

_MAP_POINTS = 41
_STYLE = (
    "body{font-family:sans-serif;max-width:1100px;margin:auto}"
    "table{border-collapse:collapse}td,th{border:1px solid #999;padding:2px 6px;text-align:right}"
)


def _png(figure: Figure) -> str:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90, bbox_inches="tight")
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img alt="plot" src="data:image/png;base64,{data}">'


def _scale(name: str) -> float:
    return 1e3 if file_unit(name) == "um" else 1e6


def error_curves_figure(tables: ErrorTableSet, axis: str) -> Figure:
    """Six panels: the error motions of one axis with their u95 bands."""
    figure = Figure(figsize=(13, 6))
    panels = figure.subplots(2, 3, sharex=True)
    for panel, name in zip(
        panels.ravel(), (*TRANSLATION_NAMES[axis], *ROTATION_NAMES[axis]), strict=True
    ):
        scale = _scale(name)
        for suffix, colour in (("", "k"), ("+", "tab:blue"), ("-", "tab:red")):
            table = tables.tables.get(name + suffix)
            if table is None:
                continue
            values, band = table.values * scale, np.nan_to_num(table.u95) * scale
            panel.plot(table.positions_mm, values, color=colour, label=name + suffix)
            panel.fill_between(
                table.positions_mm, values - band, values + band, color=colour, alpha=0.15
            )
        panel.set_title(f"{name} / {file_unit(name)}")
        panel.grid(True, alpha=0.3)
        panel.legend(fontsize=7)
    for panel in panels[1]:
        panel.set_xlabel(f"{axis} / mm")
    figure.suptitle(f"Error motions of {axis} (bands: expanded uncertainty, k = 2)")
    return figure


def _plane_points(machine: Machine, plane: tuple[str, str], at_mm: float) -> tuple[Vec, Vec, Vec]:
    a, b = (AXIS_INDEX[name] for name in plane)
    low, high = machine.travel_min_mm, machine.travel_max_mm
    ga, gb = np.meshgrid(
        np.linspace(low[a], high[a], _MAP_POINTS), np.linspace(low[b], high[b], _MAP_POINTS)
    )
    points = np.zeros((ga.size, 3))
    points[:, a], points[:, b] = ga.ravel(), gb.ravel()
    third = 3 - a - b
    points[:, third] = at_mm
    return ga, gb, points


def volumetric_map_figure(
    machine: Machine, before: ErrorModel, after: ErrorModel, controller: str
) -> Figure:
    """Length of the volumetric error (tool point) in the three faces, before and after."""
    chain = Chain.parse(machine.chain)
    figure = Figure(figsize=(14, 8))
    panels = figure.subplots(2, 3)
    planes = ((("X", "Y"), "Z"), (("X", "Z"), "Y"), (("Y", "Z"), "X"))
    for column, (plane, third) in enumerate(planes):
        at = machine.travel_max_mm[AXIS_INDEX[third]]
        ga, gb, points = _plane_points(machine, plane, at)
        for row, (model, label) in enumerate(
            ((before, "before"), (after, f"after {controller} tables"))
        ):
            dp, _ = deviation(chain, points, np.zeros(3), model)
            length_um = np.linalg.norm(dp, axis=1).reshape(ga.shape) * 1e3
            image = panels[row, column].contourf(ga, gb, length_um, levels=20, cmap="viridis")
            figure.colorbar(image, ax=panels[row, column], label="|error| / um")
            panels[row, column].set_title(f"{label}: {''.join(plane)} at {third} = {at:g} mm")
            panels[row, column].set_xlabel(f"{plane[0]} / mm")
            panels[row, column].set_ylabel(f"{plane[1]} / mm")
    figure.suptitle("Volumetric error of the tool point (from the error tables)")
    figure.tight_layout()
    return figure


def _html_table(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _number(value: float, digits: int = 2) -> str:
    return "–" if not math.isfinite(value) else f"{value:.{digits}f}"


def render_report(machine: Machine, result: PostResult, controller: str) -> str:
    """The HTML text of the report."""
    fit = result.fit
    tables = fit.tables
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>xmalign report</title>"
        f"<style>{_STYLE}</style></head><body>",
        f"<h1>Calibration of {html.escape(machine.name)}</h1>",
        f"<p>Chain {html.escape(machine.chain)}; {len(result.lines)} lines,"
        f" {fit.n_observations} observations, {fit.n_parameters} parameters;"
        f" a-posteriori sigma0 = {fit.sigma0:.2f} (uncertainties are scaled by it when"
        " above 1).</p>",
        "<h2>Squareness</h2>",
        _html_table(
            ["error", "value / urad", "U95 / urad"],
            [[n, _number(v * 1e6), _number(u * 1e6)] for n, (v, u) in tables.squareness.items()],
        ),
        "<h2>ISO 230-2 positioning figures (um)</h2>",
    ]
    if result.positioning:
        names = list(result.positioning[0].as_dict())
        parts.append(
            _html_table(
                ["line", "runs", *names],
                [
                    [f.line_id, str(f.runs), *(_number(v) for v in f.as_dict().values())]
                    for f in result.positioning
                ],
            )
        )
    parts.append("<h2>Error motions</h2>")
    parts.extend(_png(error_curves_figure(tables, axis)) for axis in AXES)
    parts.append("<h2>Volumetric error before and after compensation</h2>")
    comp_fit = fit_for(machine, tables, controller)
    parts.append(
        f"<p>Predicted over the whole travel at the tool point (RMS, mean offset removed):"
        f" {comp_fit.before_um:.2f} um before, {comp_fit.after_um:.2f} um after the"
        f" {controller} tables ({100 * comp_fit.removed_share:.0f} % removed).</p>"
    )
    parts.append(
        _png(
            volumetric_map_figure(
                machine, tables.model(""), remaining_errors(tables, controller, machine), controller
            )
        )
    )
    parts.append("<h2>Setup terms and residuals per line</h2>")
    parts.append(
        _html_table(
            [
                "line",
                "straightness offset v, w / um",
                "alignment slope v, w / urad",
                "angle offsets u, v, w / urad",
                "residual RMS lin, sv, sw / um",
                "residual RMS au, av, aw / urad",
            ],
            [
                [
                    s.line_id,
                    ", ".join(_number(v, 1) for v in s.straightness_offset_um),
                    ", ".join(_number(v, 1) for v in s.straightness_slope_urad),
                    ", ".join(_number(v, 1) for v in s.angle_offset_urad),
                    ", ".join(_number(v) for v in fit.residual_rms[s.line_id][:3]),
                    ", ".join(_number(v) for v in fit.residual_rms[s.line_id][3:]),
                ]
                for s in fit.setup
            ],
        )
    )
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(path: str | Path, machine: Machine, result: PostResult, controller: str) -> None:
    """Write the HTML report (PNGs embedded)."""
    atomic_write_text(path, render_report(machine, result, controller))
