"""``post`` without the files: plan + measurement rows -> error tables and figures."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan
from xmalign.geometry import Vec
from xmalign.machine import Machine
from xmalign.post.datum import datum_warnings
from xmalign.post.iso230_2 import PositioningFigures, positioning_figures
from xmalign.post.lines import UM_PER_MM, LineData, group_by_line
from xmalign.post.solve import TableFit, fit_error_tables
from xmalign.rigid_body import Chain


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
        What the user should know about the data (e.g. a re-zeroed linear datum).
    """

    fit: TableFit
    positioning: list[PositioningFigures]
    lines: list[LineData]
    warnings: list[str] = field(default_factory=list)


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
class Station:
    """The measurement from one launch-unit station: its plan, rows and file name."""

    plan: Plan
    rows: list[MeasurementRow]
    source: str


def post_stations(machine: Machine, stations: list[Station]) -> PostResult:
    """Fit one set of error tables to the measurements of one or more stations.

    Every line keeps its own setup terms (the beam, the mountings and the
    interferometer's datum change with the station); the error tables and the
    squareness are shared. ``Station.source`` names the file in error messages.
    """
    lines = [
        data
        for index, station in enumerate(stations)
        for data in group_by_line(station.plan, station.rows, station.source, index)
    ]
    fit = fit_error_tables(
        lines,
        Chain.parse(machine.chain),
        channel_sigma(machine),
        (machine.travel_min_mm, machine.travel_max_mm),
    )
    positioning = [
        positioning_figures(
            data.label, data.index, data.sign, data.run, data.channels[:, 0] * UM_PER_MM
        )
        for data in lines
        if data.axis() is not None
    ]
    return PostResult(fit=fit, positioning=positioning, lines=lines, warnings=datum_warnings(lines))


def post_process(
    machine: Machine, plan: Plan, rows: list[MeasurementRow], source: str
) -> PostResult:
    """Fit the error tables to the rows of a measurement of ``plan`` (one station).

    ``source`` names the measurement file in error messages.
    """
    return post_stations(machine, [Station(plan, rows, source)])
