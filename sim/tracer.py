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

from collections.abc import Mapping
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

    def observe(self, points_mcs_mm: Vec, constant_mm: float, scale_ppm: float = 0.0) -> Vec:
        """Noisy lengths to true SMR points in the MCS, plus the run's constant, (N,).

        ``scale_ppm``: the run's scale error (air compensation), on the distance.
        """
        distance = np.linalg.norm(np.atleast_2d(points_mcs_mm) - self.pivot_mm, axis=1)
        noise = self._rng.normal(size=len(distance)) * self.uncertainty.length_sigma_mm(distance)
        return distance * (1.0 + scale_ppm * 1e-6) + constant_mm + noise

    def run_scale(self, scale_ppm: float) -> float:
        """One run's scale error, ppm, drawn with standard deviation ``scale_ppm`` (0: none)."""
        return float(self._rng.normal() * scale_ppm) if scale_ppm > 0 else 0.0

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
) -> list[TracerLength]:
    """Tracer lengths at standstill: every commanded point, ``runs`` runs (new constant each).

    With ``smr_offsets_mm`` (name to offset, MCS) every point is measured with each
    SMR position in turn within a run (rows named in ``smr``); ``scale_ppm``: the
    standard deviation of a scale error drawn per run (0: none).
    """
    lengths = []
    named: list[tuple[str | None, Vec]] = list((smr_offsets_mm or {}).items())
    positions = named or [(None, np.asarray(smr_offset_mm, float))]
    for run in range(runs):
        constant, scale = tracer.new_constant(), tracer.run_scale(scale_ppm)
        for name, offset in positions:
            ones = np.ones_like(cnc_mm)
            actual, _ = machine.actual_functional_point(cnc_mm, ones, offset)
            seen = tracer.observe(actual, constant, scale)
            lengths += [
                TracerLength(
                    station, run, i, np.asarray(cnc_mm[i], float), float(seen[i]), smr=name
                )
                for i in range(len(cnc_mm))
            ]
    return lengths
