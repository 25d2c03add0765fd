"""Six-line measurements of a virtual machine with known errors (tests and benchmarks).

Pure: a plan of the three axis lines and three face diagonals of a machine's
travel, and the channels the interferometer would read on them for any
:class:`~xmalign.rigid_body.ErrorModel`, with backlash, setup terms and noise.
The channel model is the one of docs/conventions.md; the deviation is
:func:`xmalign.rigid_body.deviation`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xmalign.formats.measurements import MeasurementRow
from xmalign.formats.plan import Plan, PlanLine
from xmalign.geometry import Vec, line_frame, rot_z
from xmalign.machine import Machine
from xmalign.rigid_body import AXIS_INDEX, Chain, ErrorModel, deviation

#: Corners of the six lines as fractions of the travel: (start, end).
_LINES = {
    "X": ((0, 0, 1), (1, 0, 1)),
    "Y": ((0, 0, 1), (0, 1, 1)),
    "Z": ((0, 0, 0), (0, 0, 1)),
    "XY": ((0, 0, 1), (1, 1, 1)),
    "YZ": ((0, 0, 0), (0, 1, 1)),
    "XZ": ((0, 0, 0), (1, 0, 1)),
}


def six_line_plan(
    machine: Machine, n_targets: int, runs: int = 2, bidirectional: bool = True
) -> Plan:
    """Axis lines and face diagonals along the edges of the travel, equally spaced targets."""
    low, high = machine.travel_min_mm, machine.travel_max_mm
    lines = []
    for line_id, (a, b) in _LINES.items():
        start = low + np.array(a) * (high - low)
        end = low + np.array(b) * (high - low)
        length = float(np.linalg.norm(end - start))
        lines.append(
            PlanLine(
                id=line_id,
                start_mm=start,
                end_mm=end,
                frame=line_frame(end - start),
                launch_rad=np.zeros(2),
                receiver_rad=np.zeros(3),
                targets_mm=np.linspace(0.0, length, n_targets),
                runs=runs,
                bidirectional=bidirectional,
            )
        )
    return Plan(
        machine=machine.name,
        receiver_offset_mm=machine.receiver_offset,
        spindle_angle_rad=machine.spindle_angle_rad,
        lines=lines,
    )


@dataclass(frozen=True)
class SetupDisturbance:
    """What the setup adds (docs/conventions.md), and the channel noise, in file units."""

    straightness_offset_um: float = 40.0
    straightness_slope_urad: float = 50.0
    angle_offset_urad: float = 100.0
    dead_path_um: float = 2.0
    noise: tuple[float, ...] = (0.2, 0.5, 0.5, 0.5, 0.5, 1.0)
    #: Zero the linear channel again at the start of every pass (a mistake: the
    #: interferometer should count on through the run).
    rezero_each_pass: bool = False
    #: The machine's positioning repeatability (standard deviation per moving axis and point),
    #: as :class:`sim.machine.ErrorAmplitudes` ``repeatability_um`` (0: a perfectly
    #: repeatable machine).
    repeatability_um: float = 0.0


class _Approached:
    """An ErrorModel whose positioning errors include backlash for given approach signs."""

    def __init__(self, model: ErrorModel, backlash_mm: Vec, signs: Vec) -> None:
        self._model, self._backlash, self._signs = model, backlash_mm, signs

    def motions(self, axis: str, position_mm: Vec) -> tuple[Vec, Vec]:
        delta, eps = self._model.motions(axis, position_mm)
        i = AXIS_INDEX[axis]
        delta = delta.copy()
        delta[:, i] -= 0.5 * self._signs[:, i] * self._backlash[i]
        return delta, eps

    def squareness_rad(self) -> Vec:
        return self._model.squareness_rad()


def measure(
    plan: Plan,
    chain: Chain,
    model: ErrorModel,
    rng: np.random.Generator,
    backlash_mm: Vec | None = None,
    setup: SetupDisturbance | None = None,
) -> list[MeasurementRow]:
    """The rows ``xmalign run`` would record for ``plan`` on a machine with ``model``.

    ``backlash_mm`` (3,) is the lost motion of X, Y, Z: a forward approach lands
    half of it short.

    A run is a forward pass and, if the line is bidirectional, the return pass;
    the linear channel is referred to the run's first point.
    """
    setup = setup or SetupDisturbance()
    backlash_mm = np.zeros(3) if backlash_mm is None else np.asarray(backlash_mm, dtype=float)
    t = rot_z(plan.spindle_angle_rad) @ plan.receiver_offset_mm
    rows: list[MeasurementRow] = []
    for line in plan.lines:
        straight_offset = rng.uniform(-1, 1, 2) * setup.straightness_offset_um * 1e-3
        straight_slope = rng.uniform(-1, 1, 2) * setup.straightness_slope_urad * 1e-6
        angle_offset = rng.uniform(-1, 1, 3) * setup.angle_offset_urad * 1e-6
        passes = [(1.0, np.arange(len(line.targets_mm)))]
        if line.bidirectional:
            passes.append((-1.0, np.arange(len(line.targets_mm))[::-1]))
        points = line.target_points_mm()
        for run in range(1, line.runs + 1):
            dead_path = rng.uniform(-1, 1) * setup.dead_path_um * 1e-3
            reference = None
            for sign, order in passes:
                signs = np.tile(np.sign(line.frame[0]) * sign, (len(order), 1))
                dp, rotation = deviation(
                    chain, points[order], t, _Approached(model, backlash_mm, signs)
                )
                # only the axes the line moves position anew (sim.machine.tool_pose)
                moving = np.abs(line.frame[0]) > 1e-9
                dp = dp + rng.normal(0.0, setup.repeatability_um * 1e-3, dp.shape) * moving
                local = dp @ line.frame.T
                if reference is None or setup.rezero_each_pass:
                    reference = local[0, 0]
                distance = line.targets_mm[order]
                channels = np.column_stack(
                    [
                        local[:, 0] - reference + dead_path,
                        local[:, 1:3] + straight_offset + np.outer(distance, straight_slope),
                        rotation @ line.frame.T + angle_offset,
                    ]
                ) * np.array([1e3, 1e3, 1e3, 1e6, 1e6, 1e6])
                channels += rng.normal(0.0, 1.0, channels.shape) * np.array(setup.noise)
                rows.extend(
                    MeasurementRow(
                        line=line.id,
                        run=run,
                        direction="+" if sign > 0 else "-",
                        index=int(i),
                        target_mm=float(line.targets_mm[i]),
                        machine_mm=points[i],
                        channels=values,
                    )
                    for i, values in zip(order, channels, strict=True)
                )
    return rows
