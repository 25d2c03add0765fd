"""Rigid-body error model of docs/conventions.md (ISO 230-1 names, first order).

The kinematic chain is written workpiece side to tool side with ``F`` for the
frame (``FYXZ``, ``XFYZ``, ...). Every axis's error motions are stated as the
motion of the tool relative to the workpiece that the axis causes. With CNC
coordinates ``k``, ``delta_K = (EXK, EYK, EZK)`` and ``eps_K = (EAK, EBK, ECK)``::

    dp = sum_K [delta_K(k_K) + eps_K(k_K) x r_K] + squareness terms
    rotation of the tool relative to the workpiece = sum_K eps_K(k_K)

Inside this module lengths are mm and angles rad; files use um and urad.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from xmalign.errors import InputError
from xmalign.geometry import Vec

AXES = ("X", "Y", "Z")
AXIS_INDEX = {"X": 0, "Y": 1, "Z": 2}
TRANSLATION_NAMES = {axis: (f"EX{axis}", f"EY{axis}", f"EZ{axis}") for axis in AXES}
ROTATION_NAMES = {axis: (f"EA{axis}", f"EB{axis}", f"EC{axis}") for axis in AXES}
SQUARENESS_NAMES = ("EC0Y", "EA0Z", "EB0Z")
#: Straightness errors whose end-point slope the table convention moves into squareness,
#: with the squareness it goes to and the sign (docs/conventions-notes.md).
SLOPE_TO_SQUARENESS = {
    "EYX": ("EC0Y", -1.0),
    "EXY": ("EC0Y", -1.0),
    "EZY": ("EA0Z", -1.0),
    "EYZ": ("EA0Z", -1.0),
    "EZX": ("EB0Z", +1.0),
    "EXZ": ("EB0Z", +1.0),
}
#: The 18 position-dependent error names, axis by axis.
MOTION_NAMES = tuple(
    name for axis in AXES for name in (*TRANSLATION_NAMES[axis], *ROTATION_NAMES[axis])
)


def error_axis(name: str) -> str:
    """The axis an ISO 230-1 motion name belongs to (``EXY`` -> ``Y``)."""
    if name not in MOTION_NAMES:
        raise InputError(f"'{name}' is not an ISO 230-1 error motion name (e.g. EXX, EBY)")
    return name[2]


@dataclass(frozen=True)
class Chain:
    """A kinematic chain: ``workpiece`` axes (workpiece to F), ``tool`` axes (F to tool)."""

    workpiece: tuple[str, ...]
    tool: tuple[str, ...]

    @classmethod
    def parse(cls, text: str) -> Chain:
        letters = text.strip().upper()
        if sorted(letters) != sorted("FXYZ"):
            raise InputError(f"chain '{text}' must name F, X, Y and Z once each (e.g. FYXZ)")
        frame = letters.index("F")
        return cls(workpiece=tuple(letters[:frame]), tool=tuple(letters[frame + 1 :]))

    def __str__(self) -> str:
        return "".join(self.workpiece) + "F" + "".join(self.tool)

    def lever_arm_axes(self, axis: str) -> tuple[str, ...]:
        """Axes whose CNC coordinate enters the lever arm of ``axis``."""
        if axis in self.tool:
            return self.tool[self.tool.index(axis) + 1 :]
        return self.tool + self.workpiece[self.workpiece.index(axis) :]

    def lever_arms(self, machine_mm: ArrayLike, tool_offset_mm: ArrayLike) -> dict[str, Vec]:
        """Lever arm ``r_K`` of every axis at CNC points.

        Parameters
        ----------
        machine_mm : array_like, shape (N, 3)
            CNC coordinates X, Y, Z, mm.
        tool_offset_mm : array_like, shape (3,)
            Functional point offset ``t`` in the MCS, mm.

        Returns
        -------
        dict of str to ndarray, shape (N, 3)
        """
        k = np.atleast_2d(np.asarray(machine_mm, dtype=float))
        t = np.asarray(tool_offset_mm, dtype=float)
        arms = {}
        for axis in AXES:
            r = np.tile(t, (len(k), 1))
            for other in self.lever_arm_axes(axis):
                r[:, AXIS_INDEX[other]] += k[:, AXIS_INDEX[other]]
            arms[axis] = r
        return arms


class ErrorModel(Protocol):
    """Anything that gives the 18 error motions and the 3 squareness errors."""

    def motions(self, axis: str, position_mm: Vec) -> tuple[Vec, Vec]:
        """``(delta mm (N, 3), eps rad (N, 3))`` of ``axis`` at its coordinates (N,)."""
        ...

    def squareness_rad(self) -> Vec:
        """``[EC0Y, EA0Z, EB0Z]`` in rad, shape (3,)."""
        ...


def squareness_deviation(machine_mm: ArrayLike, squareness_rad: ArrayLike) -> Vec:
    """Deviation caused by ``[EC0Y, EA0Z, EB0Z]`` at CNC points, mm, shape (N, 3)."""
    k = np.atleast_2d(np.asarray(machine_mm, dtype=float))
    ec0y, ea0z, eb0z = np.asarray(squareness_rad, dtype=float)
    dp = np.zeros_like(k)
    dp[:, 0] = -k[:, 1] * ec0y + k[:, 2] * eb0z
    dp[:, 1] = -k[:, 2] * ea0z
    return dp


def deviation(
    chain: Chain, machine_mm: ArrayLike, tool_offset_mm: ArrayLike, model: ErrorModel
) -> tuple[Vec, Vec]:
    """Deviation of the functional point and tool rotation at CNC points.

    Returns
    -------
    dp_mm : ndarray, shape (N, 3)
        Actual minus nominal functional point, tool relative to workpiece.
    rotation_rad : ndarray, shape (N, 3)
        Rotation vector of the tool relative to the workpiece.
    """
    k = np.atleast_2d(np.asarray(machine_mm, dtype=float))
    arms = chain.lever_arms(k, tool_offset_mm)
    dp = squareness_deviation(k, model.squareness_rad())
    rotation = np.zeros_like(k)
    for axis in AXES:
        delta, eps = model.motions(axis, k[:, AXIS_INDEX[axis]])
        dp += delta + np.cross(eps, arms[axis])
        rotation += eps
    return dp, rotation


@dataclass
class ErrorTables:
    """Tabulated error motions, linearly interpolated between compensation points.

    ``tables`` maps an ISO 230-1 name to ``(positions_mm (M,), values (M,))`` in
    mm (translations) or rad (rotations); a missing name is zero. Outside a
    table the end values are held.
    """

    tables: dict[str, tuple[Vec, Vec]] = field(default_factory=dict)
    squareness: dict[str, float] = field(default_factory=dict)

    def value(self, name: str, position_mm: ArrayLike) -> Vec:
        """Interpolated value of one error at positions (N,)."""
        k = np.asarray(position_mm, dtype=float)
        if name not in self.tables:
            return np.zeros_like(k)
        positions, values = self.tables[name]
        return np.interp(k, positions, values)

    def motions(self, axis: str, position_mm: Vec) -> tuple[Vec, Vec]:
        delta = np.stack([self.value(n, position_mm) for n in TRANSLATION_NAMES[axis]], axis=-1)
        eps = np.stack([self.value(n, position_mm) for n in ROTATION_NAMES[axis]], axis=-1)
        return delta, eps

    def squareness_rad(self) -> Vec:
        return np.array([self.squareness.get(name, 0.0) for name in SQUARENESS_NAMES])


@dataclass(frozen=True)
class RemainingErrors:
    """An error model minus the translation tables a controller applies (an ErrorModel)."""

    model: ErrorModel
    applied: ErrorTables

    def motions(self, axis: str, position_mm: Vec) -> tuple[Vec, Vec]:
        delta, eps = self.model.motions(axis, position_mm)
        applied, applied_eps = self.applied.motions(axis, position_mm)
        return delta - applied, eps - applied_eps

    def squareness_rad(self) -> Vec:
        return self.model.squareness_rad() - self.applied.squareness_rad()
