"""Simulated identification sessions: aligned units with realistic imperfections.

A closed-form model, fast enough for Monte Carlo: the machine puts the
receiver cp near the commanded point (positioning error), the units point the
beam between their real optical centres (axis offsets), and the encoders
report the true angles minus their zero offsets plus noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim.imperfections import UnitImperfections
from xmalign.formats.session import Alignment, Session
from xmalign.geometry import Vec, rot_y, rot_z, unit
from xmalign.kinematics import EncoderOffsets, launch_angles, receiver_angles, receiver_cp
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

    @classmethod
    def realistic(
        cls, rng: np.random.Generator, with_distance: bool = True
    ) -> SessionImperfections:
        """Encoder noise 10 urad, zero offsets 60 urad, axis offsets 10 um, machine 20 um."""
        return cls(
            launch=UnitImperfections.random(rng, 2),
            receiver=UnitImperfections.random(rng, 3),
            machine_position_mm=0.020,
            distance_noise_mm=0.020 if with_distance else None,
        )

    def truth(self, launch2mcs_mm: Vec, gamma_rad: float) -> LaunchTruth:
        """The truth an identification should find (c1 is part of gamma)."""
        offsets = EncoderOffsets(
            c2=float(self.launch.zero_offsets_rad[1]),
            c3=float(self.receiver.zero_offsets_rad[0]),
            c4=float(self.receiver.zero_offsets_rad[1]),
        )
        return LaunchTruth(np.asarray(launch2mcs_mm, dtype=float), gamma_rad, offsets)


def _head_offset(azimuth: float, elevation: float, offset_mm: Vec) -> Vec:
    return rot_z(azimuth) @ rot_y(-elevation) @ offset_mm


def simulate_alignment(
    machine_mm: Vec,
    truth: LaunchTruth,
    receiver_offset_mm: Vec,
    spindle_angle_rad: float,
    imperfections: SessionImperfections,
    rng: np.random.Generator,
) -> Alignment:
    """One alignment at a commanded CNC point, as the encoders report it."""
    cp_actual = receiver_cp(machine_mm, receiver_offset_mm, spindle_angle_rad)
    cp_actual = cp_actual + rng.normal(0.0, imperfections.machine_position_mm, 3)
    launch_origin, receiver_centre = truth.launch2mcs_mm, cp_actual
    for _ in range(4):  # the optical centres move with the angles they set
        beam = unit(receiver_centre - launch_origin)
        phi1, phi2 = launch_angles(beam, truth.gamma_rad)
        phi3, phi4 = receiver_angles(-beam, spindle_angle_rad)
        launch_origin = truth.launch2mcs_mm + _head_offset(
            truth.gamma_rad + phi1, phi2, imperfections.launch.axis_offset_mm
        )
        receiver_centre = cp_actual + _head_offset(
            spindle_angle_rad + phi3, phi4, imperfections.receiver.axis_offset_mm
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
    alignments = [
        simulate_alignment(p, truth, receiver_offset_mm, spindle_angle_rad, imperfections, rng)
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
