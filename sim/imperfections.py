"""Imperfections of the simulated positioning units (shared by every unit model in sim/)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from xmalign.geometry import Vec


@dataclass(frozen=True)
class UnitImperfections:
    """How one positioning unit differs from its nominal kinematics.

    Attributes
    ----------
    encoder_noise_rad : float
        Standard deviation of each encoder reading.
    zero_offsets_rad : ndarray, shape (n_axes,)
        True angle minus reported angle of each axis (``c_k`` of docs/conventions.md;
        for the launch unit the first one is absorbed in gamma).
    axis_offset_mm : ndarray, shape (3,)
        Where the optical centre really is relative to the cp, in the head frame
        (axes that do not intersect): the beam leaves / enters there.
    backlash_rad : float
        Belt backlash: lost motion on a reversal of each axis.
    beam_misalignment_rad : ndarray, shape (2,)
        Launch: the beam's tilt about the head's y and z axes relative to the head's
        x axis. Receiver: the same tilt of its optical axis (seen as angle constants).
    """

    encoder_noise_rad: float = 0.0
    zero_offsets_rad: Vec = field(default_factory=lambda: np.zeros(3))
    axis_offset_mm: Vec = field(default_factory=lambda: np.zeros(3))
    backlash_rad: float = 0.0
    beam_misalignment_rad: Vec = field(default_factory=lambda: np.zeros(2))

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        n_axes: int,
        encoder_noise_rad: float = 10e-6,
        zero_offset_rad: float = 60e-6,
        axis_offset_mm: float = 0.010,
        backlash_rad: float = 0.0,
        beam_misalignment_rad: float = 20e-6,
    ) -> UnitImperfections:
        """Imperfections drawn with the given standard deviations."""
        return cls(
            encoder_noise_rad=encoder_noise_rad,
            zero_offsets_rad=rng.normal(0.0, zero_offset_rad, n_axes),
            axis_offset_mm=rng.normal(0.0, axis_offset_mm, 3),
            backlash_rad=backlash_rad,
            beam_misalignment_rad=rng.normal(0.0, beam_misalignment_rad, 2),
        )
