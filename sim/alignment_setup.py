"""A virtual alignment setup: the units off alignment by a chosen amount, in simulated time.

``xmalign align --sim`` and the alignment tests and benchmarks start from it;
:func:`point_by_truth` stands in for the operator's manual alignment.
"""

from __future__ import annotations

import math

import numpy as np

from sim.units import SimPositioningUnit
from sim.world import FixedPosition, World, build_world
from xmalign.alignment import AlignmentDevices, FineAlignmentSettings, fine_align, sensitivity
from xmalign.kinematics import aligned_angles, receiver_cp
from xmalign.machine import Machine
from xmalign.roles import PositioningUnit


def point_by_truth(
    world: World, machine: Machine, launch: PositioningUnit, receiver: PositioningUnit
) -> float:
    """What the operator's manual alignment achieves in a simulated setup.

    Moves the units to the nominal aligned angles of the true pose (true
    encoder offsets, ignoring the optical-centre offsets and the beam
    misalignment), which brings every beam into range but leaves work for
    fine alignment. Returns the nominal cp-to-cp distance, mm.
    """
    cnc_mm = world.interferometer.position.position_mm()
    cp = receiver_cp(cnc_mm, machine.receiver_offset, machine.spindle_angle_rad)
    nominal = aligned_angles(
        world.launch2mcs_mm, world.gamma_rad, cp, machine.spindle_angle_rad, world.offsets
    )
    roll = -world.receiver.axes[2].zero_offset_rad
    launch.move_to(nominal.launch_rad, timeout_s=60.0)
    receiver.move_to(np.array([*nominal.receiver_rad[:2], roll]), timeout_s=60.0)
    return nominal.distance_mm


def simulated_setup(
    machine: Machine,
    position_mm: np.ndarray,
    seed: int,
    start_um: float,
    start_urad: float,
    gamma_rad: float = 0.3,
) -> tuple[World, AlignmentDevices]:
    """A virtual setup with the units ``start_um`` / ``start_urad`` off alignment.

    The units are first aligned on the (simulated) beam, then moved so that
    the straightness channels read ``start_um`` in total (equal in v and w)
    and each angle channel ``start_urad``; they then stand still, unlocked.
    Returns the world and the in-process devices (virtual time);
    ``distance_mm`` is the true cp-to-cp distance.
    """
    world = build_world(machine, FixedPosition(position_mm), seed=seed, gamma_rad=gamma_rad)
    launch, receiver = SimPositioningUnit(world.launch), SimPositioningUnit(world.receiver)
    distance_mm = point_by_truth(world, machine, launch, receiver)
    fine_align(
        launch,
        receiver,
        world.interferometer,
        world.clock,
        distance_mm,
        FineAlignmentSettings(timeout_s=60.0),
    )
    aligned_rad = np.array([axis.target_rad for axis in (*world.launch.axes, *world.receiver.axes)])
    wanted = np.array([start_um / math.sqrt(2.0)] * 2 + [start_urad] * 3)
    offset_urad = np.linalg.solve(sensitivity(aligned_rad[1], distance_mm), wanted)
    start = aligned_rad + offset_urad * 1e-6
    launch.move_to(start[:2], timeout_s=60.0)
    receiver.move_to(start[2:], timeout_s=60.0)
    devices = AlignmentDevices(launch, receiver, world.interferometer, world.clock, distance_mm)
    return world, devices
