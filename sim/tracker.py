"""A virtual laser tracker measuring the SMR on the virtual machine (seed 000).

The tracker stands on the table at a pose that nobody knows exactly; it reports
the SMR centre in its own frame. Its noise is drawn from its uncertainty model
(:class:`xmalign.machine.TrackerUncertainty`): along the beam
``a_r + b_r * d``, across it ``a_t + b_t * d`` per axis, with ``d`` the distance.
The defaults are half the maximum permissible errors published for absolute
laser trackers of the Leica AT960 class (distance 10 um + 0.3 um/m, transverse
15 um + 6 um/m, figures quoted in issue 24), the noise level of the project's
benchmarks.

The SMR is where the virtual machine really puts it
(:meth:`sim.machine.VirtualMachine.actual_functional_point`: the same truth model
of the errors the interferometer simulation measures, with the machine's
repeatability).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from sim.machine import VirtualMachine
from xmalign.formats.instruments import TrackerPoint
from xmalign.geometry import Vec
from xmalign.machine import TrackerUncertainty
from xmalign.post.instruments import beam_angles, systematic_angle_basis


@dataclass
class VirtualTracker:
    """A tracker at ``position_mm`` (its origin in the MCS), turned by ``rotation_deg``.

    ``rotation_deg`` is the rotation vector of the tracker's frame in the MCS, degrees.
    """

    position_mm: Vec
    rotation_deg: Vec = field(default_factory=lambda: np.zeros(3))
    uncertainty: TrackerUncertainty = field(default_factory=TrackerUncertainty)
    seed: int = 0

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    @property
    def rotation(self) -> Vec:
        """``R``: a vector in the MCS is ``R.T @ v`` in the tracker's frame, shape (3, 3)."""
        return Rotation.from_rotvec(np.radians(self.rotation_deg)).as_matrix()

    def systematic_angles(self, angle_systematic_urad: float) -> Vec:
        """A station's systematic angle errors: 8 coefficients for the azimuth, then 8 for
        the elevation, each with standard deviation ``s / 2``, rad, shape (16,) (none at 0)."""
        if angle_systematic_urad <= 0:
            return np.zeros(16)
        return self._rng.normal(size=16) * angle_systematic_urad * 1e-6 / 2

    def run_scale(self, scale_ppm: float) -> float:
        """One run's scale error, ppm, drawn with standard deviation ``scale_ppm`` (0: none)."""
        return float(self._rng.normal() * scale_ppm) if scale_ppm > 0 else 0.0

    def observe(
        self, points_mcs_mm: Vec, angles_rad: Vec | None = None, scale_ppm: float = 0.0
    ) -> Vec:
        """Noisy SMR centres in the tracker's frame for true points in the MCS, (N, 3).

        ``angles_rad`` (16,): the station's systematic angle errors
        (:meth:`systematic_angles`); ``scale_ppm``: the run's scale error.
        """
        frame = (np.atleast_2d(points_mcs_mm) - self.position_mm) @ self.rotation
        if (angles_rad is not None and np.any(angles_rad)) or scale_ppm:
            frame = _systematic(
                frame, np.zeros(16) if angles_rad is None else angles_rad, scale_ppm
            )
        distance = np.linalg.norm(frame, axis=1)
        beam = frame / distance[:, None]
        radial = self.uncertainty.radial_sigma_mm(distance)
        transverse = self.uncertainty.transverse_sigma_mm(distance)
        draw = self._rng.normal(size=frame.shape) * transverse[:, None]
        across = draw - np.sum(draw * beam, axis=1)[:, None] * beam
        along = self._rng.normal(size=len(frame)) * radial
        return frame + across + along[:, None] * beam


def _systematic(frame_mm: Vec, angles_rad: Vec, scale_ppm: float) -> Vec:
    """Points in the tracker's frame as its systematic errors report them, (N, 3)."""
    azimuth, elevation = beam_angles(frame_mm)
    basis = systematic_angle_basis(azimuth, elevation)
    azimuth = azimuth + basis @ angles_rad[:8]
    elevation = elevation + basis @ angles_rad[8:]
    distance = np.linalg.norm(frame_mm, axis=1) * (1.0 + scale_ppm * 1e-6)
    return distance[:, None] * np.stack(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ],
        axis=1,
    )


def measure_tracker(
    machine: VirtualMachine,
    tracker: VirtualTracker,
    cnc_mm: Vec,
    runs: int,
    smr_offset_mm: Vec,
    station: str = "T1",
    *,
    angle_systematic_urad: float = 0.0,
    scale_ppm: float = 0.0,
    smr_offsets_mm: Mapping[str, Vec] | None = None,
) -> list[TrackerPoint]:
    """Tracker points at standstill: every commanded point, ``runs`` times.

    ``smr_offset_mm`` is the SMR from the tool point in the MCS. With
    ``smr_offsets_mm`` (name to offset, MCS) every point is measured with each of
    these SMR positions in turn instead (rows named in ``smr``). The tracker's
    systematic errors (docs/formats.md): angle errors drawn once for the station
    (``angle_systematic_urad``, RMS over all directions), a scale per run
    (``scale_ppm``, standard deviation); 0: none.
    """
    points = []
    angles = tracker.systematic_angles(angle_systematic_urad)
    named: list[tuple[str | None, Vec]] = list((smr_offsets_mm or {}).items())
    positions = named or [(None, np.asarray(smr_offset_mm, float))]
    for run in range(runs):
        scale = tracker.run_scale(scale_ppm)
        for name, offset in positions:
            ones = np.ones_like(cnc_mm)
            actual, _ = machine.actual_functional_point(cnc_mm, ones, offset)
            seen = tracker.observe(actual, angles, scale)
            points += [
                TrackerPoint(station, run, i, np.asarray(cnc_mm[i], float), seen[i], smr=name)
                for i in range(len(cnc_mm))
            ]
    return points


def measure_tracker_on_the_fly(
    machine: VirtualMachine,
    tracker: VirtualTracker,
    paths_mm: list[tuple[Vec, Vec]],
    spacing_mm: float,
    smr_offset_mm: Vec,
    station: str = "T1",
    run: int = 0,
    feed_mm_min: float = 2000.0,
) -> list[TrackerPoint]:
    """Tracker points taken while the machine moves along straight paths (seed 001).

    The tracker samples every ``spacing_mm`` of travel (its clock, not the
    CNC's: the rows say where each path starts and ends, not where along it the
    sample was taken). ``time_s`` counts from the run's start at ``feed_mm_min``.
    """
    rows = []
    clock_s = 0.0
    for start, end in paths_mm:
        start, end = np.asarray(start, float), np.asarray(end, float)
        length = float(np.linalg.norm(end - start))
        fractions = np.linspace(0.0, 1.0, max(2, int(length / spacing_mm) + 1))
        cnc = start + np.outer(fractions, end - start)
        approach = np.tile(np.sign(end - start) + (end == start), (len(cnc), 1))
        actual, _ = machine.actual_functional_point(cnc, approach, smr_offset_mm)
        seen = tracker.observe(actual)
        times = clock_s + fractions * length / (feed_mm_min / 60.0)
        rows += [
            TrackerPoint(station, run, None, start, seen[i], end, float(times[i]))
            for i in range(len(cnc))
        ]
        clock_s = float(times[-1])
    return rows
