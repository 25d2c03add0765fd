"""Positioning-unit kinematics of docs/conventions.md (pure numpy).

Launch unit (LU): beam direction ``d = Rz(gamma + phi1)·Ry(-phi2)·[1,0,0]``.
Receiver unit (RU): optical axis ``u = Rz(gamma_R + phi3)·Ry(-phi4)·[1,0,0]``,
pointing from the receiver towards the launch unit; the roll ``phi5`` turns the
receiver about ``u`` last and is zero when the receiver's "up" matches the
launch unit's (see docs/conventions-notes.md).

Encoder zero offsets: true angle = reported angle + ``c_k``; ``c1`` is 0 by
definition (it cannot be told apart from ``gamma``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from xmalign.geometry import Vec, azimuth_elevation, direction, rot_z, wrap_angle


@dataclass(frozen=True)
class EncoderOffsets:
    """Encoder zero offsets ``c2``, ``c3``, ``c4`` in rad (true = reported + c)."""

    c2: float = 0.0
    c3: float = 0.0
    c4: float = 0.0

    def as_array(self) -> Vec:
        """``[c2, c3, c4]``, shape (3,)."""
        return np.array([self.c2, self.c3, self.c4])


def launch_direction(gamma_rad: float, phi1_rad: ArrayLike, phi2_rad: ArrayLike) -> Vec:
    """Beam direction leaving the launch cp for true axis angles, shape (..., 3)."""
    return direction(gamma_rad + np.asarray(phi1_rad), phi2_rad)


def receiver_axis(gamma_r_rad: float, phi3_rad: ArrayLike, phi4_rad: ArrayLike) -> Vec:
    """Receiver optical axis (receiver towards launch) for true angles, shape (..., 3)."""
    return direction(gamma_r_rad + np.asarray(phi3_rad), phi4_rad)


def launch_angles(d: ArrayLike, gamma_rad: float) -> tuple[Vec, Vec]:
    """True launch angles ``(phi1, phi2)`` pointing the beam along ``d``, each shape (...).

    ``phi2`` lies in [-pi/2, pi/2] (the unit never looks over its top), ``phi1`` in [-pi, pi).
    """
    az, el = azimuth_elevation(d)
    return wrap_angle(az - gamma_rad), el


def receiver_angles(u: ArrayLike, gamma_r_rad: float) -> tuple[Vec, Vec]:
    """True receiver angles ``(phi3, phi4)`` turning the optical axis to ``u``, each shape (...)."""
    az, el = azimuth_elevation(u)
    return wrap_angle(az - gamma_r_rad), el


def receiver_cp(
    machine_mm: ArrayLike, receiver_offset_mm: ArrayLike, spindle_angle_rad: float
) -> Vec:
    """Receiver cp: CNC tool point plus the offset turned by the spindle angle, shape (..., 3)."""
    offset = rot_z(spindle_angle_rad) @ np.asarray(receiver_offset_mm, dtype=float)
    return np.asarray(machine_mm, dtype=float) + offset


@dataclass(frozen=True)
class AlignedAngles:
    """Reported angles (rad) that align the units; ``launch`` (2,), ``receiver`` (3,)."""

    launch_rad: Vec
    receiver_rad: Vec
    distance_mm: float


def aligned_angles(
    launch2mcs_mm: ArrayLike,
    gamma_rad: float,
    receiver_cp_mm: ArrayLike,
    spindle_angle_rad: float,
    offsets: EncoderOffsets | None = None,
) -> AlignedAngles:
    """Reported unit angles that point the beam from the launch cp to the receiver cp.

    Parameters
    ----------
    launch2mcs_mm : array_like, shape (3,)
        Launch cp in the MCS, mm.
    gamma_rad : float
        Launch-unit azimuth, rad.
    receiver_cp_mm : array_like, shape (3,)
        Receiver cp in the MCS, mm.
    spindle_angle_rad : float
        Spindle angle ``gamma_R``, rad.
    offsets : EncoderOffsets, optional
        Encoder zero offsets to subtract (reported = true - c).
    """
    c = offsets or EncoderOffsets()
    beam = np.asarray(receiver_cp_mm, dtype=float) - np.asarray(launch2mcs_mm, dtype=float)
    distance = float(np.linalg.norm(beam))
    phi1, phi2 = launch_angles(beam, gamma_rad)
    phi3, phi4 = receiver_angles(-beam, spindle_angle_rad)
    launch = np.array([float(phi1), float(phi2) - c.c2])
    receiver = np.array([float(wrap_angle(phi3 - c.c3)), float(phi4) - c.c4, 0.0])
    return AlignedAngles(launch_rad=launch, receiver_rad=receiver, distance_mm=distance)
