"""Where to align the units for identification: a D-optimal design with casadi.

Identification without a measured distance (seed paper 002, 2.3.2) observes at
each machine position the four reported angles that align the units:

    phi1 = az(b) - gamma       phi2 = el(b) - c2
    phi3 = az(-b) - gamma_R - c3   phi4 = el(-b) - c4

with ``b`` the vector from the launch cp to the receiver cp. Each angle has
the encoder's noise plus the machine's and the units' position noise seen
over the beam length (over the horizontal length for the azimuths). The
encoder offsets are nuisance parameters with their a-priori uncertainty. The
design maximises the determinant of the information about
``(x, y, z, gamma)`` (their Schur complement), i.e. minimises the volume of the
predicted pose-uncertainty ellipsoid, for the coarse launch position of the
machine file, inside the travel, the stand-off and the beam range.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import casadi as ca
import numpy as np

from trajectories.lines import receiver_offset_mcs
from xmalign.errors import GeometryError, InputError
from xmalign.geometry import Vec
from xmalign.machine import Machine

#: Smallest number of alignments that determines the pose (4 unknowns, 4 angles each).
MIN_POSITIONS = 2
_HALTON_BASES = (2, 3, 5)
# Exact Hessians of the log-determinant through atan2 are ill-conditioned; L-BFGS is robust.
_IPOPT_OPTIONS = {
    "print_level": 0,
    "sb": "yes",
    "hessian_approximation": "limited-memory",
    "max_iter": 400,
    "tol": 1e-6,
    "acceptable_tol": 1e-4,
    "acceptable_iter": 10,
}


@dataclass(frozen=True)
class IdentificationDesign:
    """Proposed machine positions and the pose uncertainty they predict.

    Attributes
    ----------
    machine_mm : ndarray, shape (N, 3)
        CNC tool points at which to align the units.
    pose_covariance : ndarray, shape (4, 4)
        Predicted covariance of ``(x mm, y mm, z mm, gamma rad)``.
    """

    machine_mm: Vec
    pose_covariance: Vec

    @property
    def std(self) -> Vec:
        """Standard uncertainties ``(x mm, y mm, z mm, gamma rad)``, shape (4,)."""
        return np.sqrt(np.diag(self.pose_covariance))


def _halton(index: int, base: int) -> float:
    result, fraction = 0.0, 1.0
    while index > 0:
        fraction /= base
        result += fraction * (index % base)
        index //= base
    return result


def _start_points(machine: Machine, count: int) -> Vec:
    low, high = machine.travel_min_mm, machine.travel_max_mm
    fractions = np.array([[_halton(i + 1, base) for base in _HALTON_BASES] for i in range(count)])
    return low + fractions * (high - low)


def _information(tool_mm: ca.MX, launch_cp_mm: Vec, offset_mm: Vec, machine: Machine) -> ca.MX:
    """Fisher information (7x7) of ``(x, y, z, gamma, c2, c3, c4)`` for tool points (N, 3)."""
    u = machine.uncertainty
    encoder_var = (u.encoder_urad * 1e-6) ** 2
    lateral_var = (u.machine_position_um * 1e-3) ** 2 + (u.unit_kinematics_um * 1e-3) ** 2
    q = ca.MX.sym("q", 7)
    receiver_cp = ca.MX.sym("r", 3)
    b = receiver_cp - q[:3]
    horizontal = ca.sqrt(b[0] ** 2 + b[1] ** 2)
    az, el = ca.atan2(b[1], b[0]), ca.atan2(b[2], horizontal)
    observed = ca.vertcat(az - q[3], el - q[4], az - q[5], -el - q[6])
    jacobian = ca.Function("J", [q, receiver_cp], [ca.jacobian(observed, q)])
    q0 = np.concatenate([launch_cp_mm, np.zeros(4)])
    information = ca.MX(np.diag([0, 0, 0, 0] + [(u.encoder_zero_offset_urad * 1e-6) ** -2] * 3))
    for i in range(tool_mm.shape[0]):
        r = tool_mm[i, :].T + offset_mm
        j = jacobian(q0, r)
        d = r - launch_cp_mm
        length2 = ca.sumsqr(d)
        horizontal2 = d[0] ** 2 + d[1] ** 2
        weights = ca.vertcat(
            1.0 / (encoder_var + lateral_var / horizontal2),
            1.0 / (encoder_var + lateral_var / length2),
            1.0 / (encoder_var + lateral_var / horizontal2),
            1.0 / (encoder_var + lateral_var / length2),
        )
        information += j.T @ ca.diag(weights) @ j
    return information


def _pose_information(information: ca.MX) -> ca.MX:
    """Information about the pose with the offsets marginalised (Schur complement), 4x4."""
    f_pp, f_pc, f_cc = information[:4, :4], information[:4, 4:], information[4:, 4:]
    return f_pp - f_pc @ ca.solve(f_cc, f_pc.T)


def predicted_pose_covariance(machine: Machine, machine_mm: Vec) -> Vec:
    """Predicted covariance of ``(x mm, y mm, z mm, gamma rad)`` for alignments at tool
    points ``machine_mm`` (N, 3), around the machine file's coarse launch position, (4, 4)."""
    if machine.launch_unit is None:
        raise InputError(
            "machine file has no launch_unit.position_mm; add the coarse launch position"
        )
    points = np.atleast_2d(np.asarray(machine_mm, dtype=float))
    tool = ca.MX.sym("tool", *points.shape)
    launch_cp = np.asarray(machine.launch_unit.position_mm, dtype=float)
    information = _information(tool, launch_cp, receiver_offset_mcs(machine), machine)
    evaluate = ca.Function("pose_information", [tool], [_pose_information(information)])
    return np.linalg.inv(np.array(evaluate(points)))


def design_identification(machine: Machine, count: int = 6) -> IdentificationDesign:
    """Machine positions for identification that minimise the predicted pose uncertainty.

    Parameters
    ----------
    machine : Machine
        Travel, receiver offset, stand-off, beam range, uncertainties and the coarse
        launch position ``launch_unit.position_mm``.
    count : int
        Number of alignments (at least 2).

    Raises
    ------
    InputError
        No coarse launch position in the machine file, or ``count`` too small.
    GeometryError
        No feasible design (the solver found none inside the travel and ranges).
    """
    if machine.launch_unit is None:
        raise InputError(
            "machine file has no launch_unit.position_mm; add the coarse launch position"
        )
    if count < MIN_POSITIONS:
        raise InputError(f"--count {count}: at least {MIN_POSITIONS} positions are needed")
    launch_cp = np.asarray(machine.launch_unit.position_mm, dtype=float)
    offset = receiver_offset_mcs(machine)
    opti = ca.Opti()
    tool = opti.variable(count, 3)
    pose_info = _pose_information(_information(tool, launch_cp, offset, machine))
    u = machine.uncertainty
    # Scale to the size of one observation's noise so the determinant is of order 1.
    reference = np.diag([u.machine_position_um * 1e-3] * 3 + [u.encoder_urad * 1e-6])
    opti.minimize(-ca.log(ca.det(reference @ pose_info @ reference)))
    standoff2 = machine.measurement.standoff_mm**2
    range2 = machine.interferometer.max_range_mm**2
    for i in range(count):
        for k in range(3):
            opti.subject_to(
                opti.bounded(machine.travel_min_mm[k], tool[i, k], machine.travel_max_mm[k])
            )
        beam2 = ca.sumsqr(tool[i, :].T + offset - launch_cp)
        opti.subject_to(opti.bounded(standoff2, beam2, range2))
    opti.set_initial(tool, _start_points(machine, count))
    opti.solver("ipopt", {"print_time": False}, _IPOPT_OPTIONS)
    # Out of iterations still leaves a usable design if it is feasible; checked below.
    with contextlib.suppress(RuntimeError):
        opti.solve()
    machine_mm = np.atleast_2d(opti.debug.value(tool))
    beam_mm = np.linalg.norm(machine_mm + offset - launch_cp, axis=1)
    tolerance_mm = 1e-3
    feasible = np.all(machine.within_travel(machine_mm, tolerance_mm)) and np.all(
        (beam_mm >= machine.measurement.standoff_mm - tolerance_mm)
        & (beam_mm <= machine.interferometer.max_range_mm + tolerance_mm)
    )
    # ipopt honours bounds only to its tolerance: put the points exactly inside the travel.
    machine_mm = np.clip(machine_mm, machine.travel_min_mm, machine.travel_max_mm)
    covariance = predicted_pose_covariance(machine, machine_mm)
    if not (feasible and np.all(np.isfinite(covariance))):
        raise GeometryError(
            "no identification design found inside the travel, the stand-off and the beam"
            " range; check launch_unit.position_mm and measurement.standoff_mm"
        )
    return IdentificationDesign(machine_mm=machine_mm, pose_covariance=covariance)
