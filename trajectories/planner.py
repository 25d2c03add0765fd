"""From an identified launch pose to the measurement plan (docs/formats.md ``xmalign.plan/1``).

Each line is laid out by :mod:`trajectories.lines`, its unit angles come from
:func:`xmalign.kinematics.aligned_angles` with the pose's encoder offsets, and
its beam envelope from :mod:`trajectories.envelope`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trajectories.envelope import BeamEnvelope, predict_envelope
from trajectories.lines import (
    AXIS_LINES,
    LINE_IDS,
    LineLayout,
    plan_line,
    receiver_offset_mcs,
    shift_reason,
)
from xmalign.errors import GeometryError
from xmalign.formats.plan import Plan, PlanLine
from xmalign.formats.pose import OFFSET_NAMES, LaunchPose
from xmalign.geometry import Vec, line_frame
from xmalign.kinematics import aligned_angles
from xmalign.machine import Machine


@dataclass(frozen=True)
class PlannedLine:
    """A plan line with how it was laid out and its predicted beam envelope."""

    line: PlanLine
    layout: LineLayout
    envelope: BeamEnvelope

    @property
    def warning(self) -> str | None:
        """Why the 95 % envelope may lose the beam, with the margins; None if it fits."""
        if self.envelope.within:
            return None
        e = self.envelope
        return (
            f"line {self.line.id}: the 95 % beam envelope leaves the range"
            f" (straightness margin {e.straightness_margin_um:.0f} um,"
            f" angle margin {e.angle_margin_urad:.0f} urad); improve the pose"
            " (more alignments, estimate the encoder offsets) or shorten the line"
        )


@dataclass(frozen=True)
class MeasurementPlan:
    plan: Plan
    lines: list[PlannedLine]

    @property
    def warnings(self) -> list[str]:
        return [w for w in (line.warning for line in self.lines) if w is not None]


def parameter_covariance(pose: LaunchPose, machine: Machine) -> Vec:
    """Covariance of ``(x, y, z, gamma, c2, c3, c4)`` (mm, rad), shape (7, 7).

    The pose's 4x4 covariance; an encoder offset the pose estimated gets the
    variance of one encoder reading, one it did not estimate the a-priori
    ``uncertainty.encoder_zero_offset_urad``. Every commanded angle adds the
    encoder's positioning noise (``gamma`` stands in for axis a1).
    """
    u = machine.uncertainty
    encoder_var = (u.encoder_urad * 1e-6) ** 2
    covariance = np.zeros((7, 7))
    covariance[:4, :4] = pose.covariance
    covariance[3, 3] += encoder_var
    for k, name in enumerate(OFFSET_NAMES, start=4):
        offset_var = (
            encoder_var
            if name in pose.encoder_offsets_rad
            else (u.encoder_zero_offset_urad * 1e-6) ** 2
        )
        covariance[k, k] = offset_var + encoder_var
    return covariance


def _pose_vector(pose: LaunchPose) -> Vec:
    return np.concatenate([pose.position_mm, [pose.gamma_rad], pose.offsets.as_array()])


def plan_one_line(
    line_id: str, pose: LaunchPose, machine: Machine, max_length_mm: float | None = None
) -> PlannedLine:
    """Lay out one line (at most ``max_length_mm`` long), command its angles and predict
    its beam envelope.

    Raises
    ------
    GeometryError
        The line is too short, or it cannot pass through the launch cp and the
        closest parallel line is too far off for the beam even with a perfect pose.
    """
    layout = plan_line(line_id, pose.position_mm, machine, max_length_mm)
    frame = line_frame(layout.u)
    angles = aligned_angles(
        pose.position_mm,
        pose.gamma_rad,
        layout.aim_receiver_cp_mm,
        machine.spindle_angle_rad,
        pose.offsets,
    )
    measurement = machine.measurement
    ranges = machine.interferometer
    receiver_cps = layout.target_points_mm() + receiver_offset_mcs(machine)
    envelope = predict_envelope(
        _pose_vector(pose),
        parameter_covariance(pose, machine),
        receiver_cps,
        angles.launch_rad,
        angles.receiver_rad,
        machine.spindle_angle_rad,
        frame,
        ranges.straightness_range_um - measurement.straightness_allowance_um,
        ranges.angle_range_urad - measurement.angle_allowance_urad,
    )
    shifted = bool(np.any(layout.shift_mm != 0.0))
    if shifted and not envelope.nominal_fits:
        raise GeometryError(
            f"line {line_id} cannot run through the launch cp: "
            f"{shift_reason(layout, pose.position_mm, machine)} (the closest parallel line"
            f" puts the beam {np.max(envelope.lateral_nominal_um):.0f} um off the receiver,"
            f" more than the {envelope.straightness_limit_um:.0f} um range left after the"
            " allowance for the axis's own errors)"
        )
    extra = _line_extra(layout, envelope, machine)
    if shifted:
        extra["note"] = (
            "closest feasible line parallel to the axis through the launch cp: "
            + shift_reason(layout, pose.position_mm, machine)
        )
    line = PlanLine(
        id=line_id,
        start_mm=layout.start_mm,
        end_mm=layout.end_mm,
        frame=frame,
        launch_rad=angles.launch_rad,
        receiver_rad=angles.receiver_rad,
        targets_mm=layout.targets_mm,
        runs=measurement.runs if line_id in AXIS_LINES else measurement.diagonal_runs,
        bidirectional=measurement.bidirectional,
        dwell_s=measurement.dwell_s,
        extra=extra,
    )
    return PlannedLine(line=line, layout=layout, envelope=envelope)


def _line_extra(layout: LineLayout, envelope: BeamEnvelope, machine: Machine) -> dict:
    return {
        "length_mm": layout.length_mm,
        "coverage_percent": float(100.0 * layout.coverage),
        "beam_distance_mm": list(layout.beam_distance_mm),
        "shift_mm": [float(v) for v in layout.shift_mm],
        "feed_mm_min": machine.feed_mm_min.measure,
        "transit_feed_mm_min": machine.transit_feed_mm_min,
        "approach_mm": machine.measurement.approach_mm,
        "overrun_mm": machine.measurement.overrun_mm,
        "envelope": {
            "straightness_95_um": float(np.max(envelope.lateral_95_um)),
            "straightness_limit_um": envelope.straightness_limit_um,
            "straightness_margin_um": envelope.straightness_margin_um,
            "angle_95_urad": envelope.angle_95_urad,
            "angle_limit_urad": envelope.angle_limit_urad,
            "angle_margin_urad": envelope.angle_margin_urad,
            "within": envelope.within,
        },
    }


def plan_measurement(
    machine: Machine,
    pose: LaunchPose,
    line_ids: tuple[str, ...] = LINE_IDS,
    max_length_mm: float | None = None,
) -> MeasurementPlan:
    """Plan the measuring lines (default: X, Y, Z, XY, YZ, XZ) for an identified pose.

    ``max_length_mm`` cuts every line to at most that length (a try-out; the plan
    records it as ``max_length_mm``).
    """
    planned = [plan_one_line(line_id, pose, machine, max_length_mm) for line_id in line_ids]
    cut = {} if max_length_mm is None else {"max_length_mm": float(max_length_mm)}
    plan = Plan(
        machine=machine.name,
        receiver_offset_mm=machine.receiver_offset,
        spindle_angle_rad=machine.spindle_angle_rad,
        lines=[p.line for p in planned],
        extra={
            "machine_sha256": machine.geometry_sha256(),
            "launch_position_mm": [float(v) for v in pose.position_mm],
            "launch_gamma_deg": float(np.degrees(pose.gamma_rad)),
            "encoder_offsets_deg": {
                k: float(np.degrees(v)) for k, v in pose.encoder_offsets_rad.items()
            },
            **cut,
        },
    )
    return MeasurementPlan(plan=plan, lines=planned)
