"""``post`` without the files: plan + measurement rows -> error tables and figures."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from xmalign.environment import StationCompensation, compensate_station
from xmalign.errors import InputError
from xmalign.formats.instruments import TracerFile, TrackerFile
from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan
from xmalign.geometry import Vec, rot_z
from xmalign.machine import Machine
from xmalign.post.datum import datum_warnings
from xmalign.post.instruments import (
    JointFit,
    Progress,
    fit_joint,
    tracer_places,
    tracker_stations,
)
from xmalign.post.iso230_2 import PositioningFigures, positioning_figures
from xmalign.post.lines import (
    CHANNEL_TO_SI,
    UM_PER_MM,
    LineData,
    dead_row_warning,
    group_by_line,
    is_dead_row,
)
from xmalign.post.solve import Outlier, TableFit, fit_error_tables
from xmalign.rigid_body import Chain, ErrorModel, ErrorTables, RemainingErrors, deviation
from xmalign.roles import CHANNELS


@dataclass
class PostResult:
    """Everything ``xmalign post`` computes.

    Attributes
    ----------
    fit : TableFit
        Error tables (mm / rad, u95 k = 2), setup terms, residuals.
    positioning : list of PositioningFigures
        ISO 230-2 figures of every axis line (um).
    lines : list of LineData
        The measurement, grouped by line (mm / rad).
    warnings : list of str
        What the user should know about the data (e.g. a re-zeroed linear datum, a
        reading left out as a gross outlier: ``fit.outliers``).
    compensation : list of StationCompensation
        Per station, how its readings were compensated for the air, the dead
        path and the material, and the drift of each line.
    applied : ErrorTables, optional
        The compensation the controller applied during the measurement (a
        verification run): ``fit`` is then the machine's own geometry and
        :meth:`tool_point_errors` what remains with the compensation.
    instruments : JointFit, optional
        With tracker points or tracer lengths: the joint fit (its ``fit`` is ``fit``),
        with each station's and place's setup and residuals.
    """

    fit: TableFit
    positioning: list[PositioningFigures]
    lines: list[LineData]
    warnings: list[str] = field(default_factory=list)
    compensation: list[StationCompensation] = field(default_factory=list)
    applied: ErrorTables | None = None
    instruments: JointFit | None = None

    def tool_point_errors(self, direction: str = "") -> ErrorModel:
        """The errors the machine shows with its controller's compensation (if any) in."""
        model = self.fit.tables.model(direction)
        return model if self.applied is None else RemainingErrors(model, self.applied)

    @property
    def notes(self) -> list[str]:
        """One line per station on how its linear readings were treated."""
        return [c.note for c in self.compensation]

    def figure_lines(self) -> list[LineData]:
        """The axis lines the ISO 230-2 and VDI/DGQ 3441 figures are taken from: ``lines``
        without the linear readings the fit left out as gross outliers."""
        kept = without_linear_outliers(self.lines, self.fit.outliers)
        return [data for data in kept if data.axis() is not None]


def channel_sigma(machine: Machine) -> Vec:
    """Standard uncertainty of the six channels from the machine file, mm / rad, shape (6,)."""
    u = machine.uncertainty
    return np.array(
        [
            u.channel_linear_um * 1e-3,
            u.channel_straightness_um * 1e-3,
            u.channel_straightness_um * 1e-3,
            u.channel_roll_urad * 1e-6,
            u.channel_angle_urad * 1e-6,
            u.channel_angle_urad * 1e-6,
        ]
    )


@dataclass(frozen=True)
class Instruments:
    """Tracker-point and tracer-length files for the same fit as the lines.

    ``knot_spacing_mm``: the compensation points' spacing where no line sets them
    (None: chosen by cross-validation; :func:`xmalign.post.instruments.fit_joint`).
    """

    trackers: tuple[TrackerFile, ...] = ()
    tracers: tuple[TracerFile, ...] = ()
    knot_spacing_mm: float | None = None


@dataclass(frozen=True)
class Station:
    """The measurement from one launch-unit station: its plan, rows and file name."""

    plan: Plan
    rows: list[MeasurementRow]
    source: str


def post_stations(
    machine: Machine,
    stations: list[Station],
    applied: ErrorTables | None = None,
    instruments: Instruments | None = None,
    progress: Progress | None = None,
) -> PostResult:
    """Fit one set of error tables to the measurements of one or more stations.

    Every line keeps its own setup terms (the beam, the mountings and the
    interferometer's datum change with the station); the error tables and the
    squareness are shared. ``Station.source`` names the file in error messages.

    ``applied``: the compensation the controller applied while measuring (a
    verification run). Its shift of the tool point is added back to the
    readings before the fit: a volumetric compensation moves the tool point by
    tilts times lever arms, which leaves no rigid-body chain to fit; the ISO
    230-2 figures stay those of the readings (as left).

    ``instruments``: tracker points and tracer lengths fitted together with the
    lines (:func:`xmalign.post.instruments.fit_joint`); ``stations`` may then be empty.
    ``progress(done, total, what)`` is told how far that fit is.
    """
    for index, station in enumerate(stations):  # the rows as read: checked before any use
        for data in group_by_line(station.plan, station.rows, station.source, index):
            refuse_dead_channels(data, station.source)
    dead = [dead_row_warning(s.source, row) for s in stations for row in s.rows if is_dead_row(row)]
    stations = [
        replace(station, rows=[row for row in station.rows if not is_dead_row(row)])
        for station in stations
    ]
    compensation = [compensate(machine, station) for station in stations]
    lines = [
        data
        for index, (station, compensated) in enumerate(zip(stations, compensation, strict=True))
        for data in group_by_line(
            station.plan,
            compensated.rows,
            station.source,
            index,
        )
    ]
    sources = [station.source for station in stations]
    chain = Chain.parse(machine.chain)
    fitted = lines
    if applied is not None:
        fitted = [_without(data, chain, applied, machine.cnc.tool_offset) for data in lines]
    travel = (machine.travel_min_mm, machine.travel_max_mm)
    joint = None
    if instruments is not None and (instruments.trackers or instruments.tracers):
        if applied is not None:
            raise InputError(
                "--applied (a verification run) takes interferometer lines only, not tracker"
                " points or tracer lengths"
            )
        spindle = rot_z(machine.spindle_angle_rad)
        joint = fit_joint(
            fitted,
            tracker_stations(list(instruments.trackers)),
            tracer_places(list(instruments.tracers)),
            chain,
            channel_sigma(machine),
            spindle @ machine.smr_offset,
            machine.tracker,
            machine.tracer,
            travel,
            instruments.knot_spacing_mm,
            {name: spindle @ offset for name, offset in machine.smr_offsets().items()},
            machine.thermal.expansion_ppm_per_k,
            progress,
        )
        fit = joint.fit
    else:
        fit = fit_error_tables(fitted, chain, channel_sigma(machine), travel)
    drift = [check.message() for c in compensation for check in c.drift if check.exceeded]
    result = PostResult(
        fit=fit,
        positioning=[],
        lines=lines,
        warnings=dead
        + datum_warnings(lines)
        + drift
        + outlier_warnings(fit, lines, sources)
        + instrument_outlier_warnings(joint),
        compensation=compensation,
        applied=applied,
        instruments=joint,
    )
    result.positioning = [
        positioning_figures(
            data.label, data.index, data.sign, data.run, data.channels[:, 0] * UM_PER_MM
        )
        for data in result.figure_lines()
    ]
    return result


def without_linear_outliers(lines: list[LineData], outliers: list[Outlier]) -> list[LineData]:
    """``lines`` without their linear readings that the fit left out as gross outliers."""
    return [
        data.without([o.point for o in outliers if o.line == k and o.channel == 0])
        for k, data in enumerate(lines)
    ]


def refuse_dead_channels(data: LineData, source: str) -> None:
    """Refuse a line whose channel reads exactly zero at every point.

    No working channel does (its noise alone moves the last digit): a dead or
    unplugged instrument, or a channel its software left out. Its zeros would
    enter the fit as a perfect machine; measure the line again.

    Raises
    ------
    InputError
        Naming the file, the line and the dead channels.
    """
    dead = [
        name for name, column in zip(CHANNELS, data.channels.T, strict=True) if not column.any()
    ]
    if dead and len(data.run) > 1:
        raise InputError(
            f"{source}: line {data.line.id}: {', '.join(dead)} read exactly 0 at all"
            f" {len(data.run)} points (a dead or unplugged instrument channel); measure the line"
            " again"
        )


def outlier_warnings(fit: TableFit, lines: list[LineData], sources: list[str]) -> list[str]:
    """One warning per reading the fit left out as a gross outlier, naming the point."""
    warnings = []
    for outlier in fit.outliers:
        data = lines[outlier.line]
        k = outlier.point
        reading = data.channels[k, outlier.channel] / CHANNEL_TO_SI[outlier.channel]
        warnings.append(
            f"{sources[data.station]}: line {data.line.id} run {data.run[k]} direction"
            f" {'+' if data.sign[k] > 0 else '-'} index {data.index[k]}:"
            f" {CHANNELS[outlier.channel]} {reading:g} is {outlier.sigmas:.0f} standard"
            " deviations off the fit, a gross outlier: left out of the fit"
        )
    return warnings


def instrument_outlier_warnings(joint: JointFit | None) -> list[str]:
    """One warning per tracker point or tracer length the joint fit left out."""
    return [
        f"{outlier.name}: {outlier.sigmas:.0f} standard deviations off the fit, a gross"
        " outlier: left out of the fit"
        for outlier in (joint.outliers if joint is not None else [])
    ]


def _without(data: LineData, chain: Chain, applied: ErrorModel, tool_offset_mm: Vec) -> LineData:
    """A line's readings as the machine would give them without the applied compensation.

    The controller moved the tool by minus the deviation ``applied`` predicts
    at its tool point (``tool_offset_mm`` from the CNC point); seen from the
    line frame, that adds to the three translation channels and leaves the
    angles alone.
    """
    shift_mm, _ = deviation(chain, data.machine_mm, tool_offset_mm, applied)
    channels = data.channels.copy()
    channels[:, :3] += shift_mm @ data.frame.T
    return replace(data, channels=channels)


def compensate(machine: Machine, station: Station) -> StationCompensation:
    """The station's readings compensated for air, dead path and material (docs/formats.md).

    A file without environment columns is taken as already compensated, at
    20 °C. Drift-check rows are taken out of the rows and checked.
    """
    return compensate_station(
        station.plan,
        station.rows,
        [row.environment for row in station.rows],
        machine.thermal.expansion_ppm_per_k,
        machine.thermal.drift_limit_um,
    )


def post_process(
    machine: Machine, plan: Plan, rows: list[MeasurementRow], source: str
) -> PostResult:
    """Fit the error tables to the rows of a measurement of ``plan`` (one station).

    ``source`` names the measurement file in error messages.
    """
    return post_stations(machine, [Station(plan, rows, source)])
