"""A complete virtual setup: machine, both units placed on it, and the interferometer."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from sim.clock import SimClock
from sim.imperfections import UnitImperfections
from sim.interferometer import SimInterferometer
from sim.machine import ErrorAmplitudes, VirtualMachine
from sim.units import SimUnit
from xmalign.errors import InputError
from xmalign.geometry import Vec
from xmalign.kinematics import EncoderOffsets
from xmalign.machine import Machine
from xmalign.roles import Clock, MachinePositionSource


class FixedPosition:
    """A ``MachinePositionSource`` whose CNC stands still at a settable tool point."""

    def __init__(self, position_mm: ArrayLike) -> None:
        self.position = np.asarray(position_mm, dtype=float)

    def position_mm(self) -> Vec:
        return self.position.copy()

    def is_standstill(self) -> bool:
        return True


@dataclass
class World:
    """Everything the simulator serves; ``launch2mcs_mm``/``gamma_rad`` are the true pose."""

    clock: Clock
    machine: VirtualMachine
    launch: SimUnit
    receiver: SimUnit
    interferometer: SimInterferometer
    launch2mcs_mm: Vec
    gamma_rad: float

    @property
    def offsets(self) -> EncoderOffsets:
        """The true encoder zero offsets c2, c3, c4 (what identification should find)."""
        launch = np.resize(self.launch.imperfections.zero_offsets_rad, 2)
        receiver = np.resize(self.receiver.imperfections.zero_offsets_rad, 2)
        return EncoderOffsets(c2=float(launch[1]), c3=float(receiver[0]), c4=float(receiver[1]))


def build_world(
    machine: Machine,
    position: MachinePositionSource | None = None,
    seed: int | None = None,
    real_time: bool = False,
    gamma_rad: float = 0.0,
    amplitudes: ErrorAmplitudes | None = None,
    clock: SimClock | None = None,
) -> World:
    """A seeded virtual setup on ``machine``.

    The launch unit stands at the machine file's ``launch_unit.position_mm``
    (else below the travel's lower corner) with azimuth ``gamma_rad``; both
    units get random imperfections of :meth:`UnitImperfections.random`.
    ``position`` is the ``MachinePositionSource`` (default: a CNC standing at
    the centre of the travel). ``clock`` (default: a new one, following the
    wall clock with ``real_time``) is the time of every device.
    """
    if not math.isfinite(gamma_rad):
        raise InputError(f"launch-unit azimuth {gamma_rad}: not a finite number")
    rng = np.random.default_rng(seed)
    clock = clock or SimClock(real_time=real_time)
    vm = VirtualMachine(machine, amplitudes, seed=int(rng.integers(2**31)))
    launch = SimUnit(
        "launch", clock, UnitImperfections.random(rng, 2), seed=int(rng.integers(2**31))
    )
    receiver = SimUnit(
        "receiver", clock, UnitImperfections.random(rng, 3), seed=int(rng.integers(2**31))
    )
    if machine.launch_unit is not None:
        launch2mcs = np.asarray(machine.launch_unit.position_mm, dtype=float)
    else:
        launch2mcs = machine.travel_min_mm - np.array([0.0, 0.0, 200.0])
    if position is None:
        position = FixedPosition(0.5 * (machine.travel_min_mm + machine.travel_max_mm))
    interferometer = SimInterferometer(
        launch,
        receiver,
        vm,
        position,
        launch2mcs,
        gamma_rad,
        clock=clock,
        seed=int(rng.integers(2**31)),
    )
    return World(clock, vm, launch, receiver, interferometer, launch2mcs, gamma_rad)
