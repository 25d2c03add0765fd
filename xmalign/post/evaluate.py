"""``post`` without the files: plan + measurement rows -> error tables and figures."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan
from xmalign.geometry import Vec, rot_z
from xmalign.machine import Machine
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
    """

    fit: TableFit
    positioning: list[PositioningFigures]
    lines: list[LineData]


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


def tool_offset_mm(plan: Plan) -> Vec:
    """Receiver cp from the CNC tool point in the MCS during the measurement, mm (3,)."""
    return rot_z(plan.spindle_angle_rad) @ plan.receiver_offset_mm


def post_process(
    machine: Machine, plan: Plan, rows: list[MeasurementRow], source: str
) -> PostResult:
    """Fit the error tables to the rows of a measurement of ``plan``.

    ``source`` names the measurement file in error messages.
    """
    lines = group_by_line(plan, rows, source)
    fit = fit_error_tables(
        lines, Chain.parse(machine.chain), tool_offset_mm(plan), channel_sigma(machine)
    )
    positioning = [
        positioning_figures(
            data.line.id, data.index, data.sign, data.run, data.channels[:, 0] * UM_PER_MM
        )
        for data in lines
        if data.axis() is not None
    ]
    return PostResult(fit=fit, positioning=positioning, lines=lines)
