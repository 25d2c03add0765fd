"""A virtual laser tracer measuring the SMR on the virtual machine (seed 004).

The tracer's pivot (the centre of its reference sphere) stands at a place on
the table; it counts the interferometric distance to the SMR from an unknown
start, so every reading is the pivot-to-SMR distance plus a constant of the
(place, run). Noise: the length uncertainty published for the Etalon
LaserTRACER-NG, U = 0.2 um + 0.3 um/m (k = 2), taken as a standard deviation
of half of it (:class:`xmalign.machine.TracerUncertainty` defaults). The SMR
is where the virtual machine really puts it, as for the tracker.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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

    def observe(self, points_mcs_mm: Vec, constant_mm: float) -> Vec:
        """Noisy lengths to true SMR points in the MCS, plus the run's constant, (N,)."""
        distance = np.linalg.norm(np.atleast_2d(points_mcs_mm) - self.pivot_mm, axis=1)
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
) -> list[TracerLength]:
    """Tracer lengths at standstill: every commanded point, ``runs`` runs (new constant each)."""
    lengths = []
    for run in range(runs):
        actual, _ = machine.actual_functional_point(cnc_mm, np.ones_like(cnc_mm), smr_offset_mm)
        seen = tracer.observe(actual, tracer.new_constant())
        lengths += [
            TracerLength(station, run, i, np.asarray(cnc_mm[i], float), float(seen[i]))
            for i in range(len(cnc_mm))
        ]
    return lengths
