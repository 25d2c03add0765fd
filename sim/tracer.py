"""A virtual laser tracer measuring the SMR on the virtual machine (seed 004).

The tracer's pivot (the centre of its reference sphere) stands at a place on
the table; it counts the interferometric distance to the SMR from an unknown
start, so every reading is the pivot-to-SMR distance plus a constant of the
(place, run). Noise: the length uncertainty published for the Etalon
LaserTRACER-NG, U = 0.2 um + 0.3 um/m (k = 2), taken as a standard deviation
of half of it (:class:`xmalign.machine.TracerUncertainty` defaults). The SMR
is where the virtual machine really puts it, as for the tracker. On request the
tracer has a scale error per run (:mod:`sim.instrument_errors`), the machine a
drifting material temperature, and the SMR several positions; several tracers
may follow the SMR in the same run (:func:`measure_tracers_at_once`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from sim.instrument_errors import MaterialDrift, actual_smr_points, scale_factor, smr_blocks
from sim.machine import VirtualMachine
from xmalign.formats.instruments import TracerLength
from xmalign.geometry import Vec
from xmalign.machine import TracerUncertainty

#: The unknown constant of a run is drawn in +-this, mm (where the count started).
CONSTANT_RANGE_MM = 100.0


@dataclass
class VirtualTracer:
    """A tracer with its pivot at ``pivot_mm`` (MCS)."""

    pivot_mm: Vec
    uncertainty: TracerUncertainty = field(default_factory=TracerUncertainty)
    seed: int = 0

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def observe(
        self, points_mcs_mm: Vec, constant_mm: float, run: int = 0, scale_ppm: float = 0.0
    ) -> Vec:
        """Noisy lengths to true SMR points in the MCS, plus the run's constant, (N,).

        ``scale_ppm`` as the machine file's ``tracer`` key: the scale of this ``run``.
        """
        distance = np.linalg.norm(np.atleast_2d(points_mcs_mm) - self.pivot_mm, axis=1)
        distance = distance * scale_factor(self.seed, run, scale_ppm)
        noise = self._rng.normal(size=len(distance)) * self.uncertainty.length_sigma_mm(distance)
        return distance + constant_mm + noise

    def new_constant(self) -> float:
        return float(self._rng.uniform(-CONSTANT_RANGE_MM, CONSTANT_RANGE_MM))


def measure_tracer(
    machine: VirtualMachine,
    tracer: VirtualTracer,
    cnc_mm: Vec,
    runs: int,
    smr_offset_mm: Vec,
    station: str = "P1",
    *,
    scale_ppm: float = 0.0,
    smr_offsets_mm: Mapping[str, Vec] | None = None,
    smr_of_point: Sequence[str] | None = None,
    material: MaterialDrift | None = None,
) -> list[TracerLength]:
    """Tracer lengths at standstill: every commanded point, ``runs`` runs (new constant each).

    The keywords as for :func:`sim.tracker.measure_tracker` (each SMR position a
    run of its own: the tracer's count restarts when the SMR is changed).
    """
    return measure_tracers_at_once(
        machine,
        {station: tracer},
        cnc_mm,
        runs,
        smr_offset_mm,
        scale_ppm=scale_ppm,
        smr_offsets_mm=smr_offsets_mm,
        smr_of_point=smr_of_point,
        material=material,
    )


def measure_tracers_at_once(
    machine: VirtualMachine,
    tracers: Mapping[str, VirtualTracer],
    cnc_mm: Vec,
    runs: int,
    smr_offset_mm: Vec,
    *,
    scale_ppm: float = 0.0,
    smr_offsets_mm: Mapping[str, Vec] | None = None,
    smr_of_point: Sequence[str] | None = None,
    material: MaterialDrift | None = None,
) -> list[TracerLength]:
    """Several tracers (by station name) following the SMR in the same runs (seed 004).

    Each tracer reads the same actual SMR positions (one draw of the machine's
    repeatability and temperature per point), with its own noise, constant and
    scale. Rows per run, then per tracer; keywords as for :func:`measure_tracer`.
    """
    cnc = np.asarray(cnc_mm, dtype=float)
    blocks = smr_blocks(len(cnc), smr_offset_mm, smr_offsets_mm, smr_of_point)
    lengths = []
    for repeat in range(runs):
        for k, block in enumerate(blocks):
            run = repeat * len(blocks) + k
            commanded = cnc[block.indices]
            actual, temperatures = actual_smr_points(machine, commanded, block, material)
            for station, tracer in tracers.items():
                seen = tracer.observe(actual, tracer.new_constant(), run, scale_ppm)
                lengths += [
                    TracerLength(
                        station, run, int(i), commanded[j], float(seen[j]),
                        smr=block.name, material_c=temperatures[j],
                    )
                    for j, i in enumerate(block.indices)
                ]  # fmt: skip
    return lengths
