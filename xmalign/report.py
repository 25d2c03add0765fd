"""The calibration report as a calibration record: HTML (A4 printable) and PDF.

The record names when, with what and on what the calibration was made (date
and time, xmalign version, machine name and serial, operator, instrument and
sensor serials), the environment of every line (min / mean / max), how the
readings were compensated, the drift of every line, the standard applied with
its conditions (ISO 230-2 figures, a note below five runs; VDI/DGQ 3441 as an
option), the uncertainty budget of every error, and, when a verification
measurement exists, the as-found / as-left comparison. It then shows each
error table with its expanded uncertainty band, the squareness, the
volumetric error maps before and after compensation on one colour scale, and
the setup terms and residuals of the fit.

Figures are drawn with matplotlib's object interface (no pyplot, no global
backend), so the report works headless. The PDF is laid out by matplotlib on
A4 pages (text and tables as monospaced lines that always fit the page).
"""

from __future__ import annotations

import base64
import html
import io
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure

import xmalign
from xmalign.comp import fit_for, remaining_errors
from xmalign.environment import (
    ENVIRONMENT_COLUMNS,
    DriftCheck,
    Range,
    SensorUncertainty,
    StationCompensation,
    linear_budget_um,
)
from xmalign.errors import InputError
from xmalign.formats.common import atomic_write_bytes
from xmalign.formats.error_tables import ErrorTableSet, file_unit
from xmalign.formats.error_tables import Table as ErrorTable
from xmalign.geometry import Vec
from xmalign.instrument_text import instrument_lines, instrument_notes
from xmalign.machine import Machine
from xmalign.post.compare import grid_points, measured_box_mm, tool_point_squareness_rad
from xmalign.post.evaluate import PostResult
from xmalign.post.iso230_2 import ISO_230_2_RUNS, VdiFigures, runs_note, vdi3441_figures
from xmalign.post.lines import UM_PER_MM
from xmalign.post.ranges import RANGES_HEADER, extrapolated_spans_mm, range_rows
from xmalign.rigid_body import (
    AXES,
    AXIS_INDEX,
    ROTATION_NAMES,
    SQUARENESS_NAMES,
    TRANSLATION_NAMES,
    Chain,
    ErrorModel,
    deviation,
)

_MAP_POINTS = 41
#: A4 portrait, inches.
A4_IN = (8.27, 11.69)
_MARGIN_IN = 0.6
_STYLE = (
    "@page{size:A4;margin:15mm}"
    "body{font-family:sans-serif;max-width:180mm;margin:auto;font-size:10pt}"
    "img{max-width:100%;height:auto}"
    "table{border-collapse:collapse;font-size:8pt;margin-bottom:6pt;page-break-inside:avoid}"
    "td,th{border:1px solid #999;padding:1px 4px;text-align:right}"
    "td:first-child{text-align:left}"
    "h2{page-break-after:avoid}"
)
#: The positioning errors that the air and the material affect.
_LINEAR_ERRORS = {"X": "EXX", "Y": "EYY", "Z": "EZZ"}
_COLUMN_LABEL = {
    "air_temp_c": "air °C",
    "air_pressure_hpa": "air hPa",
    "air_humidity_percent": "humidity %",
    "material_temp_c": "material °C",
}


@dataclass
class RecordInfo:
    """What the record says beyond the fit.

    Attributes
    ----------
    operator : str
    created : datetime
        When the record was made (UTC).
    instruments : dict of str to str
        Instrument or sensor name -> serial number (``units.yaml``).
    environment : dict of str to dict of str to Range
        Per line id, the measured environment (empty: none measured).
    compensation : str
        How the readings were compensated (one sentence).
    drift : list of DriftCheck
    vdi3441 : bool
        Also give the VDI/DGQ 3441 figures.
    verification : PostResult, optional
        A measurement after compensation (as left).
    sensors : SensorUncertainty
    """

    operator: str = ""
    created: datetime = field(default_factory=lambda: datetime.now(UTC))
    instruments: dict[str, str] = field(default_factory=dict)
    environment: dict[str, dict[str, Range]] = field(default_factory=dict)
    compensation: str = (
        "no environment columns: readings taken as already compensated for the air and at 20 °C"
    )
    drift: list[DriftCheck] = field(default_factory=list)
    vdi3441: bool = False
    verification: PostResult | None = None
    sensors: SensorUncertainty = field(default_factory=SensorUncertainty)

    @classmethod
    def of_compensation(
        cls,
        compensation: StationCompensation | Sequence[StationCompensation] | None,
        **keys: object,
    ) -> RecordInfo:
        """The record of compensated measurements, one per station (``keys``: the rest)."""
        if isinstance(compensation, StationCompensation):
            compensation = [compensation]
        stations = [c for c in compensation or () if c.lines]
        if not stations:
            return cls(**keys)  # type: ignore[arg-type]
        return cls(
            environment={k: v for c in stations for k, v in c.environment.items()},
            compensation=stations[0].note,
            drift=[check for c in stations for check in c.drift],
            **keys,  # type: ignore[arg-type]
        )


# ---------------------------------------------------------------- content


@dataclass(frozen=True)
class Table:
    """A titled table of text cells."""

    title: str
    header: list[str]
    rows: list[list[str]]
    note: str = ""


def _number(value: float, digits: int = 2) -> str:
    return "–" if not math.isfinite(value) else f"{value:.{digits}f}"


def _scale(name: str) -> float:
    return 1e3 if file_unit(name) == "um" else 1e6


def record_table(machine: Machine, info: RecordInfo) -> Table:
    rows = [
        ["date and time (UTC)", info.created.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S")],
        ["software", f"xmalign {xmalign.__version__}"],
        ["machine", machine.name],
        ["machine serial", machine.serial or "not given"],
        ["kinematic chain", machine.chain],
        ["operator", info.operator or "not given"],
        *([name, serial] for name, serial in sorted(info.instruments.items())),
        ["compensation", info.compensation],
    ]
    return Table("Calibration record", ["item", "value"], rows)


def environment_table(info: RecordInfo) -> Table:
    header = ["line", *(f"{_COLUMN_LABEL[c]} min/mean/max" for c in ENVIRONMENT_COLUMNS)]
    rows = [
        [
            line,
            *(
                "/".join(_number(v, 2) for v in (r.min, r.mean, r.max))
                if (r := ranges.get(column)) is not None and math.isfinite(r.mean)
                else "not measured"
                for column in ENVIRONMENT_COLUMNS
            ),
        ]
        for line, ranges in info.environment.items()
    ]
    note = "" if rows else "No environment was recorded with the measurement."
    return Table("Environment per line", header, rows, note)


def drift_table(info: RecordInfo) -> Table:
    rows = [
        [
            d.line_id,
            _number(d.drift_um),
            "–" if d.limit_um is None else f"{d.limit_um:g}",
            "EXCEEDED" if d.exceeded else "ok",
        ]
        for d in info.drift
    ]
    note = "" if rows else "No re-measurement of the first targets was recorded."
    return Table(
        "Drift at the first target of each line (um)", ["line", "drift", "limit", ""], rows, note
    )


def iso_table(result: PostResult) -> Table:
    if not result.positioning:
        return Table("ISO 230-2 positioning figures (um)", ["line"], [], "No axis line.")
    names = list(result.positioning[0].as_dict())
    rows = [
        [f.line_id, str(f.runs), *(_number(v) for v in f.as_dict().values())]
        for f in result.positioning
    ]
    notes = [n for f in result.positioning if (n := runs_note(f)) is not None]
    conditions = (
        f"ISO 230-2: bidirectional approach, {ISO_230_2_RUNS} runs per direction asked for;"
        " deviations after the compensation stated in the record."
    )
    return Table(
        "ISO 230-2 positioning figures (um)",
        ["line", "runs", *names],
        rows,
        " ".join([conditions, *notes]),
    )


def vdi_figures(result: PostResult) -> list[VdiFigures]:
    return [
        vdi3441_figures(data.line.id, data.index, data.sign, data.channels[:, 0] * UM_PER_MM)
        for data in result.figure_lines()
    ]


def vdi_table(result: PostResult) -> Table:
    rows = [[v.line_id, *(_number(x) for x in v.as_dict().values())] for v in vdi_figures(result)]
    return Table(
        "VDI/DGQ 3441 figures (um)",
        ["line", "P", "Ps", "U", "Pa"],
        rows,
        "P position uncertainty, Ps position scatter (6 s), U reversal span, Pa positional"
        " deviation.",
    )


def _axis_length_mm(tables: ErrorTableSet, name: str) -> float:
    table = tables.tables.get(name)
    if table is None or len(table.positions_mm) == 0:
        return 0.0
    return float(np.ptp(table.positions_mm))


def _line_environment(info: RecordInfo, axis: str) -> dict[str, Range]:
    return info.environment.get(axis, {})


def budget_table(machine: Machine, result: PostResult, info: RecordInfo) -> Table:
    """What each source contributes to U95 (k = 2) of every error, at the end of its table."""
    tables = result.fit.tables
    sources = ("air refractive index", "material temperature", "expansion coefficient")
    rows = []
    for name in sorted(tables.tables):
        if name[-1] in "+-":
            continue
        table = tables.tables[name]
        scale = _scale(name)
        fit_u95 = float(np.nanmax(np.nan_to_num(table.u95, nan=0.0))) * scale
        extra: dict[str, float] = {}
        axis = name[-1]
        if _LINEAR_ERRORS.get(axis) == name:
            extra = linear_budget_um(
                _axis_length_mm(tables, name),
                _line_environment(info, axis),
                machine.thermal.expansion_ppm_per_k,
                info.sensors,
            )
        parts = [fit_u95, *(2 * extra.get(s, 0.0) for s in sources)]
        total = math.sqrt(sum(p * p for p in parts))
        rows.append([name, file_unit(name), *(_number(p) for p in parts), _number(total)])
    for name, (_, u95) in tables.squareness.items():
        rows.append([name, "urad", _number(u95 * 1e6), "0.00", "0.00", "0.00", _number(u95 * 1e6)])
    return Table(
        "Uncertainty budget (U95, k = 2, largest along each table)",
        ["error", "unit", "fit (channels)", "air index", "material T", "expansion α", "combined"],
        rows,
        "fit: the interferometer channels propagated through the fit (GUM), scaled by sigma0"
        " above 1; air, material and α only enter the positioning errors, with the sensor"
        " uncertainties of the environment section, over the whole stroke.",
    )


def squareness_table(result: PostResult) -> Table:
    return Table(
        "Squareness",
        ["error", "value / urad", "U95 / urad"],
        [
            [n, _number(v * 1e6), _number(u * 1e6)]
            for n, (v, u) in result.fit.tables.squareness.items()
        ],
    )


def as_left_table(machine: Machine, result: PostResult, verification: PostResult) -> Table:
    """ISO 230-2 figures of each axis line and the squareness the tool point shows, as
    found and as left (over the as-found measured strokes, for both)."""
    before = {f.line_id: f for f in result.positioning}
    rows = []
    for after in verification.positioning:
        found = before.get(after.line_id)
        for figure in ("A", "E", "R", "B"):
            old = getattr(found, figure) if found else math.nan
            rows.append([after.line_id, figure, _number(old), _number(getattr(after, figure))])
    chain = Chain.parse(machine.chain)
    points = grid_points(*measured_box_mm(result.fit.tables))
    found_rad = tool_point_squareness_rad(chain, points, result.tool_point_errors())
    left_rad = tool_point_squareness_rad(chain, points, verification.tool_point_errors())
    for name, found_value, left_value in zip(SQUARENESS_NAMES, found_rad, left_rad, strict=True):
        rows.append([name, "urad", _number(found_value * 1e6), _number(left_value * 1e6)])
    return Table(
        "As found / as left (ISO 230-2 figures in um; squareness at the tool point in urad)",
        ["line / error", "figure", "as found", "as left"],
        rows,
        "Squareness here is what the tool point shows over the measured strokes: the"
        " machine's own plus the Abbe terms of the angular errors and what the tables take out.",
    )


def setup_table(result: PostResult) -> Table:
    fit = result.fit
    return Table(
        "Setup terms and residuals per line",
        [
            "line",
            "str. offset v,w um",
            "slope v,w urad",
            "angle offsets u,v,w urad",
            "RMS lin,sv,sw um",
            "RMS au,av,aw urad",
        ],
        [
            [
                s.line_id + (f" (setup segment {s.segment})" if s.segment else ""),
                ", ".join(_number(v, 1) for v in s.straightness_offset_um),
                ", ".join(_number(v, 1) for v in s.straightness_slope_urad),
                ", ".join(_number(v, 1) for v in s.angle_offset_urad),
                ", ".join(_number(v) for v in fit.residual_rms[s.line_id][:3]),
                ", ".join(_number(v) for v in fit.residual_rms[s.line_id][3:]),
            ]
            for s in fit.setup
        ],
        f"{len(result.lines)} lines, {fit.n_observations} observations, {fit.n_parameters}"
        f" parameters; a-posteriori sigma0 = {fit.sigma0:.2f} (uncertainties are scaled by it"
        " when above 1).",
    )


def ranges_table(result: PostResult) -> Table:
    return Table(
        "Measured and extrapolated ranges",
        list(RANGES_HEADER),
        range_rows(result.fit.tables),
        "The tables cover the whole travel; beyond the range the lines measured they are the"
        " linear continuation of the end segment, with a U95 that grows with the distance"
        " (shaded grey in the plots, range = extrapolated in the error-table file).",
    )


def compensation_table(machine: Machine, result: PostResult, controller: str) -> Table:
    """What the controller's own tables are predicted to leave over the whole travel."""
    fit = fit_for(machine, result.fit.tables, controller)
    rows = [
        ["before compensation", _number(fit.before_um)],
        [f"after the {controller} tables", _number(fit.after_um)],
        ["share removed", f"{100 * fit.removed_share:.0f} %"],
    ]
    note = (
        "Predicted over the whole travel at the tool point (RMS, um, mean offset removed), from"
        f" the 21 errors and the {controller} compensation model fitted to them."
    )
    if not fit.removes_enough:
        note += " Warning: these tables remove less than half of the error."
    return Table("Compensation predicted", ["", "um"], rows, note)


def instruments_table(result: PostResult) -> list[Table]:
    """Each tracker station's and tracer place's setup with U95 and residual (if any)."""
    joint = result.instruments
    if joint is None:
        return []
    rows = [[line] for line in instrument_lines(joint) + instrument_notes(joint)]
    return [
        Table("Laser tracker and tracer: setup (U95, k = 2) and residuals", ["instrument"], rows)
    ]


def report_tables(
    machine: Machine, result: PostResult, info: RecordInfo, controller: str | None = None
) -> list[Table]:
    """Every table of the record, in order (with ``controller``, the predicted compensation)."""
    tables = [
        record_table(machine, info),
        environment_table(info),
        drift_table(info),
        iso_table(result),
    ]
    if info.vdi3441:
        tables.append(vdi_table(result))
    tables += [squareness_table(result), *instruments_table(result)]
    tables += [
        ranges_table(result),
        budget_table(machine, result, info),
    ]
    if controller is not None:
        tables.append(compensation_table(machine, result, controller))
    if result.warnings:
        tables.append(Table("Warnings", ["warning"], [[w] for w in result.warnings]))
    if info.verification is not None:
        tables.append(as_left_table(machine, result, info.verification))
    return tables


# ---------------------------------------------------------------- figures


def _shade_extrapolated(panel: Axes, table: ErrorTable | None) -> None:
    for a, b in extrapolated_spans_mm(table) if table is not None else []:
        panel.axvspan(a, b, color="0.5", alpha=0.2, linewidth=0)


def error_curves_figure(tables: ErrorTableSet, axis: str) -> Figure:
    """Six panels (3 x 2, fits A4 portrait): the error motions of one axis with u95 bands."""
    figure = Figure(figsize=(7.0, 8.0), layout="constrained")
    panels = figure.subplots(3, 2, sharex=True)
    names = (*TRANSLATION_NAMES[axis], *ROTATION_NAMES[axis])
    for panel, name in zip(panels.T.ravel(), names, strict=True):
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
        _shade_extrapolated(panel, tables.tables.get(name))
        panel.set_title(f"{name} / {file_unit(name)}", fontsize=9)
        panel.tick_params(labelsize=7)
        panel.grid(True, alpha=0.3)
        panel.legend(fontsize=6)
    for panel in panels[-1]:
        panel.set_xlabel(f"{axis} / mm", fontsize=8)
    figure.suptitle(
        f"Error motions of {axis} (bands: U95, k = 2; grey: extrapolated beyond the measured"
        " range)",
        fontsize=10,
    )
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


_PLANES = ((("X", "Y"), "Z"), (("X", "Z"), "Y"), (("Y", "Z"), "X"))


def volumetric_map_figure(machine: Machine, maps: list[tuple[str, ErrorModel]]) -> Figure:
    """Length of the volumetric error in the three faces, one column per model, one colour scale.

    ``maps`` are (label, model) pairs, e.g. before and after the controller's tables.
    """
    chain = Chain.parse(machine.chain)
    lengths = []
    for plane, third in _PLANES:
        at = machine.travel_max_mm[AXIS_INDEX[third]]
        ga, gb, points = _plane_points(machine, plane, at)
        for _, model in maps:
            dp, _ = deviation(chain, points, np.zeros(3), model)
            lengths.append((plane, third, at, ga, gb, np.linalg.norm(dp, axis=1) * 1e3))
    top = max(float(np.max(item[-1])) for item in lengths) or 1.0
    levels = np.linspace(0.0, top, 21)
    figure = Figure(figsize=(7.0, 9.0), layout="constrained")
    panels = figure.subplots(3, len(maps), squeeze=False)
    for k, (plane, third, at, ga, gb, length) in enumerate(lengths):
        row, column = divmod(k, len(maps))
        panel = panels[row, column]
        panel.contourf(ga, gb, length.reshape(ga.shape), levels=levels, cmap="viridis")
        panel.set_title(f"{maps[column][0]}: {''.join(plane)} at {third} = {at:g} mm", fontsize=8)
        panel.set_xlabel(f"{plane[0]} / mm", fontsize=7)
        panel.set_ylabel(f"{plane[1]} / mm", fontsize=7)
        panel.tick_params(labelsize=6)
    scale = ScalarMappable(Normalize(0.0, top), cmap="viridis")
    figure.colorbar(scale, ax=panels, label="|error| / um", shrink=0.6, boundaries=levels)
    figure.suptitle("Volumetric error of the tool point (one colour scale)", fontsize=10)
    return figure


def _maps(machine: Machine, result: PostResult, info: RecordInfo, controller: str) -> list:
    tables = result.fit.tables
    if info.verification is not None:
        return [
            ("as found", tables.model("")),
            ("as left", info.verification.tool_point_errors()),
        ]
    return [
        ("before", tables.model("")),
        (f"after {controller} tables", remaining_errors(tables, controller, machine)),
    ]


def report_figures(
    machine: Machine, result: PostResult, info: RecordInfo, controller: str
) -> list[tuple[str, Figure]]:
    """Every figure of the report with its heading."""
    figures = [
        (f"Error motions of {axis}", error_curves_figure(result.fit.tables, axis)) for axis in AXES
    ]
    figures.append(
        (
            "Volumetric error before and after compensation",
            volumetric_map_figure(machine, _maps(machine, result, info, controller)),
        )
    )
    return figures


# ---------------------------------------------------------------- HTML


def _png(figure: Figure) -> str:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img alt="plot" src="data:image/png;base64,{data}">'


def _html_table(table: Table) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in table.header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in table.rows
    )
    note = f"<p><small>{html.escape(table.note)}</small></p>" if table.note else ""
    grid = f"<table><tr>{head}</tr>{body}</table>" if table.rows else ""
    return f"<h2>{html.escape(table.title)}</h2>{grid}{note}"


def render_report(
    machine: Machine, result: PostResult, controller: str, info: RecordInfo | None = None
) -> str:
    """The HTML text of the report (PNGs embedded, A4 printable)."""
    info = info or RecordInfo()
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>"
        f"<title>Calibration record: {html.escape(machine.name)}</title>"
        f"<style>{_STYLE}</style></head><body>",
        f"<h1>Calibration of {html.escape(machine.name)}</h1>",
    ]
    parts.extend(_html_table(table) for table in report_tables(machine, result, info, controller))
    for title, figure in report_figures(machine, result, info, controller):
        parts.append(f"<h2>{html.escape(title)}</h2>{_png(figure)}")
    parts.append(_html_table(setup_table(result)))
    parts.append("</body></html>")
    return "\n".join(parts)


# ---------------------------------------------------------------- PDF


def _text_lines(table: Table, width: int) -> list[str]:
    """A table as monospaced lines no wider than ``width`` (cells wrapped when needed)."""
    cells = [table.header, *table.rows]
    count = len(table.header)
    widths = [max(len(row[k]) for row in cells) for k in range(count)]
    while sum(widths) + 2 * (count - 1) > width and max(widths) > 8:
        widths[int(np.argmax(widths))] -= 1
    lines = []
    for n, row in enumerate(cells):
        wrapped = [_wrap(cell, w) for cell, w in zip(row, widths, strict=True)]
        for k in range(max(len(w) for w in wrapped)):
            parts = [(w[k] if k < len(w) else "").ljust(widths[i]) for i, w in enumerate(wrapped)]
            lines.append("  ".join(parts).rstrip())
        if n == 0:
            lines.append("-" * min(width, sum(widths) + 2 * (count - 1)))
    return lines


def _wrap(text: str, width: int) -> list[str]:
    words, lines, line = text.split(), [], ""
    for word in words:
        while len(word) > width:
            if line:
                lines.append(line)
                line = ""
            lines.append(word[:width])
            word = word[width:]
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    lines.append(line)
    return lines


@dataclass
class _Page:
    """Monospaced text laid out top to bottom on A4 pages."""

    pdf: PdfPages
    font_pt: float = 7.0
    figure: Figure | None = None
    y_in: float = 0.0

    @property
    def width_chars(self) -> int:
        return int((A4_IN[0] - 2 * _MARGIN_IN) * 72 / (0.6 * self.font_pt))

    def _new(self) -> None:
        self.finish()
        self.figure = Figure(figsize=A4_IN)
        self.y_in = A4_IN[1] - _MARGIN_IN

    def finish(self) -> None:
        if self.figure is not None:
            self.pdf.savefig(self.figure)
            self.figure = None

    def write(self, text: str, size: float | None = None, weight: str = "normal") -> None:
        size = size or self.font_pt
        step = 1.35 * size / 72
        if self.figure is None or self.y_in - step < _MARGIN_IN:
            self._new()
        assert self.figure is not None
        self.figure.text(
            _MARGIN_IN / A4_IN[0],
            self.y_in / A4_IN[1],
            text,
            family="monospace" if weight == "normal" else "sans-serif",
            fontsize=size,
            weight=weight,
            va="top",
        )
        self.y_in -= step

    def table(self, table: Table) -> None:
        self.write("")
        self.write(table.title, 10, "bold")
        for line in _text_lines(table, self.width_chars) if table.rows else []:
            self.write(line)
        for line in _wrap(table.note, self.width_chars) if table.note else []:
            self.write(line)


def _pages(items: list[tuple[str, Figure]]) -> Iterator[Figure]:
    """The figures on A4 pages within the margins (their suptitle is the heading)."""
    for _, figure in items:
        figure.set_size_inches(*A4_IN)
        margin_x, margin_y = _MARGIN_IN / A4_IN[0], _MARGIN_IN / A4_IN[1]
        rect = (margin_x, margin_y, 1 - 2 * margin_x, 1 - 2 * margin_y)
        figure.set_layout_engine("constrained", rect=rect)
        yield figure


def pdf_bytes(
    machine: Machine,
    result: PostResult,
    controller: str,
    info: RecordInfo | None = None,
) -> bytes:
    """The report as an A4 PDF (tables first, then one figure per page)."""
    info = info or RecordInfo()
    buffer = io.BytesIO()
    with PdfPages(buffer) as pdf:
        page = _Page(pdf)
        page.write(f"Calibration of {machine.name}", 14, "bold")
        for table in report_tables(machine, result, info, controller):
            page.table(table)
        page.table(setup_table(result))
        page.finish()
        for figure in _pages(report_figures(machine, result, info, controller)):
            pdf.savefig(figure)
    return buffer.getvalue()


def report_bytes(
    path: str | Path,
    machine: Machine,
    result: PostResult,
    controller: str,
    info: RecordInfo | None = None,
) -> bytes:
    """The report for ``path``: a PDF when it ends in ``.pdf``, else HTML (PNGs embedded)."""
    if Path(path).suffix.lower() == ".pdf":
        return pdf_bytes(machine, result, controller, info)
    return render_report(machine, result, controller, info).encode("utf-8")


def write_report(
    path: str | Path,
    machine: Machine,
    result: PostResult,
    controller: str,
    info: RecordInfo | None = None,
) -> None:
    """Write the report (:func:`report_bytes`) atomically; a name that does not end in
    ``.html``, ``.htm`` or ``.pdf`` is refused (:func:`check_report_name`)."""
    check_report_name(path)
    atomic_write_bytes(path, report_bytes(path, machine, result, controller, info))


#: The report's file name endings and what each writes.
REPORT_KINDS = {".html": "HTML", ".htm": "HTML", ".pdf": "PDF"}


def check_report_name(path: str | Path) -> None:
    """Refuse a report name whose ending is not one of :data:`REPORT_KINDS` (a ``.docx``
    would get HTML under a name that promises another format)."""
    suffix = Path(path).suffix
    if suffix.lower() not in REPORT_KINDS:
        found = f"'{suffix}'" if suffix else "no file name ending"
        raise InputError(f"{path}: {found}: a report is written as .html or .pdf")
