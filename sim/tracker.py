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
repeatability). On request the tracker has the systematic errors of
:mod:`sim.instrument_errors` (angle errors fixed per station, a scale per run),
the machine a drifting material temperature, and the SMR several positions.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from sim.instrument_errors import (
    MaterialDrift,
    actual_smr_points,
    angle_coefficients,
    scale_factor,
    smr_blocks,
    with_angle_errors,
)
from sim.machine import VirtualMachine
from xmalign.formats.instruments import TrackerPoint
from xmalign.geometry import Vec
from xmalign.machine import TrackerUncertainty


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
        self._angle_coefficients = angle_coefficients(self.seed)

    @property
    def rotation(self) -> Vec:
        """``R``: a vector in the MCS is ``R.T @ v`` in the tracker's frame, shape (3, 3)."""
        return Rotation.from_rotvec(np.radians(self.rotation_deg)).as_matrix()

    def observe(
        self,
        points_mcs_mm: Vec,
        run: int = 0,
        angle_systematic_urad: float = 0.0,
        scale_ppm: float = 0.0,
    ) -> Vec:
        """Noisy SMR centres in the tracker's frame for true points in the MCS, (N, 3).

        ``angle_systematic_urad`` and ``scale_ppm`` as the machine file's ``tracker``
        keys: the station's angle errors and the scale of its ``run``.
        """
        frame = (np.atleast_2d(points_mcs_mm) - self.position_mm) @ self.rotation
        frame = with_angle_errors(frame, self._angle_coefficients, angle_systematic_urad)
        frame = frame * scale_factor(self.seed, run, scale_ppm)
        distance = np.linalg.norm(frame, axis=1)
        beam = frame / distance[:, None]
        radial = self.uncertainty.radial_sigma_mm(distance)
        transverse = self.uncertainty.transverse_sigma_mm(distance)
        draw = self._rng.normal(size=frame.shape) * transverse[:, None]
        across = draw - np.sum(draw * beam, axis=1)[:, None] * beam
        along = self._rng.normal(size=len(frame)) * radial
        return frame + across + along[:, None] * beam


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
    smr_of_point: Sequence[str] | None = None,
    material: MaterialDrift | None = None,
) -> list[TrackerPoint]:
    """Tracker points at standstill: every commanded point, ``runs`` times.

    Parameters
    ----------
    smr_offset_mm : ndarray, shape (3,)
        The SMR from the tool point in the MCS.
    angle_systematic_urad, scale_ppm : float
        The tracker's systematic errors (:meth:`VirtualTracker.observe`).
    smr_offsets_mm : mapping of str to ndarray (3,), optional
        Several SMR positions instead of ``smr_offset_mm``: each is a run of its
        own (run ``repeat * len(smr_offsets_mm) + k``), its rows name it in ``smr``.
    smr_of_point : sequence of str, optional
        Which SMR position measures each point (default: every one every point).
    material : MaterialDrift, optional
        The machine's scale temperature through each run (rows get ``material_c``).
    """
    cnc = np.asarray(cnc_mm, dtype=float)
    blocks = smr_blocks(len(cnc), smr_offset_mm, smr_offsets_mm, smr_of_point)
    points = []
    for repeat in range(runs):
        for k, block in enumerate(blocks):
            run = repeat * len(blocks) + k
            commanded = cnc[block.indices]
            actual, temperatures = actual_smr_points(machine, commanded, block, material)
            seen = tracker.observe(actual, run, angle_systematic_urad, scale_ppm)
            points += [
                TrackerPoint(
                    station, run, int(i), commanded[j], seen[j],
                    smr=block.name, material_c=temperatures[j],
                )
                for j, i in enumerate(block.indices)
            ]  # fmt: skip
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
    *,
    angle_systematic_urad: float = 0.0,
    scale_ppm: float = 0.0,
) -> list[TrackerPoint]:
    """Tracker points taken while the machine moves along straight paths (seed 001).

    The tracker samples every ``spacing_mm`` of travel (its clock, not the
    CNC's: the rows say where each path starts and ends, not where along it the
    sample was taken). ``time_s`` counts from the run's start at ``feed_mm_min``.
    ``angle_systematic_urad`` and ``scale_ppm`` as for :func:`measure_tracker`.
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
        seen = tracker.observe(actual, run, angle_systematic_urad, scale_ppm)
        times = clock_s + fractions * length / (feed_mm_min / 60.0)
        rows += [
            TrackerPoint(station, run, None, start, seen[i], end, float(times[i]))
            for i in range(len(cnc))
        ]
        clock_s = float(times[-1])
    return rows
