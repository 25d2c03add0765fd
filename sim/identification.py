"""Simulated identification sessions: aligned units with realistic imperfections.

A closed-form model, fast enough for Monte Carlo: the machine puts the
receiver cp near the commanded point (a positioning error common to the
session plus one per alignment) and turns the tool that carries the receiver
(likewise), the units point the beam between their real optical centres (axis
offsets) with their heads' collimation errors, and the encoders report the
true angles minus their zero offsets plus noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from sim.imperfections import UnitImperfections
from xmalign.formats.session import Alignment, Session
from xmalign.geometry import Vec, azimuth_elevation, rot_y, rot_z, unit, wrap_angle
from xmalign.kinematics import EncoderOffsets, receiver_cp
from xmalign.machine import Machine


@dataclass(frozen=True)
class LaunchTruth:
    """The true launch pose and encoder offsets behind a simulated session."""

    launch2mcs_mm: Vec
    gamma_rad: float
    offsets: EncoderOffsets


@dataclass(frozen=True)
class SessionImperfections:
    """Everything that makes a simulated session differ from the nominal model."""

    launch: UnitImperfections = field(default_factory=UnitImperfections)
    receiver: UnitImperfections = field(default_factory=UnitImperfections)
    machine_position_mm: float = 0.0
    distance_noise_mm: float | None = None
    machine_common_mm: float = 0.0
    tool_rotation_rad: float = 0.0
    tool_rotation_common_rad: float = 0.0

    @classmethod
    def realistic(
        cls, rng: np.random.Generator, with_distance: bool = True
    ) -> SessionImperfections:
        """Unit imperfections of :meth:`UnitImperfections.random` (encoder noise 10 urad,
        zero offsets 60 urad, axis offsets 10 um, collimation 20 urad) and the machine's
        errors at the alignment positions as the virtual machine shows them (seed 003
        Table 1): position 15 um common and 20 um per alignment, tool rotation 17 urad
        common and 13 urad per alignment (each axis)."""
        return cls(
            launch=UnitImperfections.random(rng, 2),
            receiver=UnitImperfections.random(rng, 3),
            machine_position_mm=0.020,
            distance_noise_mm=0.020 if with_distance else None,
            machine_common_mm=0.015,
            tool_rotation_rad=13e-6,
            tool_rotation_common_rad=17e-6,
        )

    def truth(self, launch2mcs_mm: Vec, gamma_rad: float) -> LaunchTruth:
        """The truth an identification should find (c1 is part of gamma)."""
        offsets = EncoderOffsets(
            c2=float(self.launch.zero_offsets_rad[1]),
            c3=float(self.receiver.zero_offsets_rad[0]),
            c4=float(self.receiver.zero_offsets_rad[1]),
        )
        return LaunchTruth(np.asarray(launch2mcs_mm, dtype=float), gamma_rad, offsets)


@dataclass(frozen=True)
class MachineState:
    """The machine's error shared by all alignments of a session: shift (mm), turn (rad)."""

    shift_mm: Vec = field(default_factory=lambda: np.zeros(3))
    rotation_rad: Vec = field(default_factory=lambda: np.zeros(3))


def _head_offset(azimuth: float, elevation: float, offset_mm: Vec) -> Vec:
    return rot_z(azimuth) @ rot_y(-elevation) @ offset_mm


def _head_angles(target: Vec, tilt_rad: Vec) -> tuple[float, float]:
    """Head azimuth and elevation whose (tilted) optical axis points along ``target`` (3,).

    The optical axis is ``Rz(az)·Ry(-el)·Ry(tilt_y)·Rz(tilt_z)·x`` (the units' beam
    misalignment); solved by fixed-point iteration, which gains a factor of the tilt
    (~1e-5) per step, so two steps reach rounding.
    """
    axis_in_head = rot_y(tilt_rad[0]) @ rot_z(tilt_rad[1]) @ np.array([1.0, 0.0, 0.0])
    want_az, want_el = azimuth_elevation(target)
    azimuth, elevation = float(want_az), float(want_el)
    for _ in range(2):
        got_az, got_el = azimuth_elevation(rot_z(azimuth) @ rot_y(-elevation) @ axis_in_head)
        azimuth += float(wrap_angle(want_az - got_az))
        elevation += float(want_el - got_el)
    return azimuth, elevation


def simulate_alignment(
    machine_mm: Vec,
    truth: LaunchTruth,
    receiver_offset_mm: Vec,
    spindle_angle_rad: float,
    imperfections: SessionImperfections,
    rng: np.random.Generator,
    common: MachineState | None = None,
) -> Alignment:
    """One alignment at a commanded CNC point, as the encoders report it."""
    common = common or MachineState()
    cp_actual = receiver_cp(machine_mm, receiver_offset_mm, spindle_angle_rad) + common.shift_mm
    cp_actual = cp_actual + rng.normal(0.0, imperfections.machine_position_mm, 3)
    tool_rotation = common.rotation_rad + rng.normal(0.0, imperfections.tool_rotation_rad, 3)
    tool = Rotation.from_rotvec(tool_rotation).as_matrix()
    launch_origin, receiver_centre = truth.launch2mcs_mm, cp_actual
    for _ in range(3):  # the optical centres move with the angles they set (~1e-5 per step)
        beam = unit(receiver_centre - launch_origin)
        launch_az, phi2 = _head_angles(beam, imperfections.launch.beam_misalignment_rad)
        receiver_az, phi4 = _head_angles(
            tool.T @ -beam, imperfections.receiver.beam_misalignment_rad
        )
        phi1 = float(wrap_angle(launch_az - truth.gamma_rad))
        phi3 = float(wrap_angle(receiver_az - spindle_angle_rad))
        launch_origin = truth.launch2mcs_mm + _head_offset(
            launch_az, phi2, imperfections.launch.axis_offset_mm
        )
        receiver_centre = cp_actual + tool @ _head_offset(
            receiver_az, phi4, imperfections.receiver.axis_offset_mm
        )
    c = truth.offsets
    noise_l = rng.normal(0.0, imperfections.launch.encoder_noise_rad, 2)
    noise_r = rng.normal(0.0, imperfections.receiver.encoder_noise_rad, 3)
    distance = None
    if imperfections.distance_noise_mm is not None:
        exact = float(np.linalg.norm(receiver_centre - launch_origin))
        distance = exact + float(rng.normal(0.0, imperfections.distance_noise_mm))
    return Alignment(
        machine_mm=np.asarray(machine_mm, dtype=float),
        launch_rad=np.array([phi1, phi2 - c.c2]) + noise_l,
        receiver_rad=np.array([phi3 - c.c3, phi4 - c.c4, 0.0]) + noise_r,
        distance_mm=distance,
    )


def simulate_session(
    positions_mm: Vec,
    truth: LaunchTruth,
    receiver_offset_mm: Vec,
    spindle_angle_rad: float = 0.0,
    imperfections: SessionImperfections | None = None,
    rng: np.random.Generator | None = None,
) -> Session:
    """A session of alignments at CNC points ``positions_mm`` (n, 3)."""
    imperfections = imperfections or SessionImperfections()
    rng = rng or np.random.default_rng(0)
    common = MachineState(
        rng.normal(0.0, imperfections.machine_common_mm, 3),
        rng.normal(0.0, imperfections.tool_rotation_common_rad, 3),
    )
    alignments = [
        simulate_alignment(
            p, truth, receiver_offset_mm, spindle_angle_rad, imperfections, rng, common
        )
        for p in np.atleast_2d(positions_mm)
    ]
    return Session(
        receiver_offset_mm=np.asarray(receiver_offset_mm, dtype=float),
        spindle_angle_rad=spindle_angle_rad,
        alignments=alignments,
    )


def spread_positions(machine: Machine, n: int = 8, inset: float = 0.1) -> Vec:
    """CNC points for identification that view the launch unit from many sides.

    The corners of the travel (inset by ``inset`` of each stroke), alternating
    between the top and the bottom of Z, then the edge midpoints: beams that
    cross at wide angles and at different distances and heights, so that
    position, gamma and the encoder offsets separate.
    """
    low, high = machine.travel_min_mm, machine.travel_max_mm
    span = high - low
    lo, hi = low + inset * span, high - inset * span
    mid = (low + high) / 2
    corners = [
        (lo[0], lo[1], hi[2]),
        (hi[0], hi[1], hi[2]),
        (hi[0], lo[1], lo[2]),
        (lo[0], hi[1], lo[2]),
        (hi[0], lo[1], hi[2]),
        (lo[0], hi[1], hi[2]),
        (lo[0], lo[1], lo[2]),
        (hi[0], hi[1], lo[2]),
        (mid[0], lo[1], mid[2]),
        (mid[0], hi[1], mid[2]),
        (lo[0], mid[1], mid[2]),
        (hi[0], mid[1], mid[2]),
    ]
    reps = -(-n // len(corners))
    return np.array((corners * reps)[:n], dtype=float)
