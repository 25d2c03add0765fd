"""Rotations, directions and line frames (pure numpy).

Angles are radians, lengths mm. A direction is given by its azimuth (about
+Z from +X) and its elevation (from the XY plane towards +Z).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from xmalign.errors import GeometryError

Vec = NDArray[np.float64]

#: Vectors shorter than this (mm or unit-free) count as zero.
_TINY = 1e-12


def rot_z(angle_rad: float) -> Vec:
    """Right-handed rotation about +Z, shape (3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(angle_rad: float) -> Vec:
    """Right-handed rotation about +Y, shape (3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(angle_rad: float) -> Vec:
    """Right-handed rotation about +X, shape (3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def skew(v: ArrayLike) -> Vec:
    """Cross-product matrix ``[v]x`` with ``skew(a) @ b == cross(a, b)``, shape (3, 3)."""
    x, y, z = np.asarray(v, dtype=float)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def unit(v: ArrayLike) -> Vec:
    """``v`` normalised along its last axis; raises GeometryError for a zero vector."""
    a = np.asarray(v, dtype=float)
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    if np.any(n < _TINY):
        raise GeometryError("cannot normalise a zero-length vector")
    return a / n


def direction(azimuth_rad: ArrayLike, elevation_rad: ArrayLike) -> Vec:
    """Unit vector ``Rz(az)·Ry(-el)·[1, 0, 0]``; broadcasts, shape (..., 3)."""
    az = np.asarray(azimuth_rad, dtype=float)
    el = np.asarray(elevation_rad, dtype=float)
    return np.stack([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)], axis=-1)


def azimuth_elevation(d: ArrayLike) -> tuple[Vec, Vec]:
    """Inverse of :func:`direction` for vectors of any length, shape (..., 3) -> (...), (...).

    The elevation lies in [-pi/2, pi/2] and the azimuth in (-pi, pi].
    """
    a = np.asarray(d, dtype=float)
    horizontal = np.hypot(a[..., 0], a[..., 1])
    return np.arctan2(a[..., 1], a[..., 0]), np.arctan2(a[..., 2], horizontal)


def wrap_angle(angle_rad: ArrayLike) -> Vec:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(angle_rad, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi


def circular_mean(angles_rad: ArrayLike) -> float:
    """Mean direction of angles (rad), right across the ±pi seam."""
    return float(np.angle(np.mean(np.exp(1j * np.asarray(angles_rad, dtype=float)))))


def line_frame(u: ArrayLike) -> Vec:
    """Line frame of docs/conventions.md for a line direction ``u``.

    ``w`` is the part of +Z perpendicular to ``u`` (normalised), ``v = w x u``;
    for a vertical line ``v = +X`` and ``w = u x v``.

    Returns
    -------
    ndarray, shape (3, 3)
        Rows ``u``, ``v``, ``w`` (unit vectors, right-handed).
    """
    u_ = unit(u)
    z = np.array([0.0, 0.0, 1.0])
    w_raw = z - np.dot(z, u_) * u_
    if np.linalg.norm(w_raw) < 1e-9:
        v = np.array([1.0, 0.0, 0.0])
        w = np.cross(u_, v)
    else:
        w = unit(w_raw)
        v = np.cross(w, u_)
    return np.vstack([u_, v, w])
