"""Where to align the units for identification: a D-optimal design with casadi.

Each alignment observes the four reported angles that align the units and
carries the joint model's input noise (:func:`xmalign.identify.joint_model`,
the same model ``identify`` fits, with its exact casadi derivatives): encoder
noise, the machine's position error seen over the beam, and the tool's
rotation that turns the receiver; machine errors correlate the launch and
receiver angles. The encoder offsets are nuisance parameters with their
a-priori uncertainty. The design maximises the determinant of the information
about ``(x, y, z, gamma)`` (their Schur complement), i.e. minimises the volume
of the predicted pose-uncertainty ellipsoid, for the coarse launch position of
the machine file, inside the travel, the stand-off and the beam range, with

* no beam steeper than :data:`MAX_ELEVATION_DEG` (a near-vertical beam turns
  about itself when the launch azimuth moves: fine alignment loses control
  and the azimuths carry no information), and
* every two positions at least :data:`MIN_SEPARATION_FRACTION` of the travel's
  diagonal apart: a repeated point adds no geometry, only weight on one spot
  of the machine's own errors, which vary over the travel.

The predicted covariance adds what the alignments cannot reduce (optical-centre
offsets, the machine's common-mode error, beam collimation) as ``identify``
does.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from trajectories.lines import receiver_offset_mcs
from xmalign.errors import GeometryError, InputError
from xmalign.geometry import Vec
from xmalign.identify import (
    OFFSET_NAMES,
    IdentificationUncertainty,
    input_sigmas,
    joint_model,
    systematic_sigmas,
)
from xmalign.machine import Machine

logger = logging.getLogger(__name__)

#: Smallest number of alignments that determines the pose (4 unknowns, 4 angles each).
MIN_POSITIONS = 2
#: Most alignments a design is made for: beyond about 24 the predicted pose uncertainty
#: improves by less than 1 um (the errors common to all alignments dominate), while the
#: design time grows with the cube of the count (48 positions: about 15 s).
MAX_POSITIONS = 50


def count_problem(count: int) -> str | None:
    """What is wrong with a number of identification positions, or None."""
    if count < MIN_POSITIONS:
        return f"{count}: at least {MIN_POSITIONS} positions are needed"
    if count > MAX_POSITIONS:
        return (
            f"{count} positions: at most {MAX_POSITIONS} (beyond about 24 the pose"
            " uncertainty hardly improves, the errors common to all alignments dominate,"
            " while the design time grows with the cube of the count)"
        )
    return None


#: Steepest beam a design may use, degrees above (or below) the horizontal.
MAX_ELEVATION_DEG = 60.0
#: Smallest distance between two positions, as a fraction of the travel's diagonal.
MIN_SEPARATION_FRACTION = 0.1
_HALTON_BASES = (2, 3, 5)
#: casadi expressions: symbolic (MX) while designing, numeric (DM) when evaluating.
Symbolic = ca.MX | ca.DM
# Exact Hessians of the log-determinant through atan2 are ill-conditioned; L-BFGS is robust.
_IPOPT_OPTIONS: dict[str, str | int | float] = {
    "print_level": 0,
    "sb": "yes",
    "hessian_approximation": "limited-memory",
    "max_iter": 400,
    "tol": 1e-6,
    "acceptable_tol": 1e-4,
    "acceptable_iter": 10,
}
#: Start points tried (different Halton stretches); the best converged design wins.
_STARTS = 2
_FEASIBILITY_TOL_MM = 1e-3


@dataclass(frozen=True)
class IdentificationDesign:
    """Proposed machine positions and the pose uncertainty they predict.

    Attributes
    ----------
    machine_mm : ndarray, shape (N, 3)
        CNC tool points at which to align the units.
    pose_covariance : ndarray, shape (4, 4)
        Predicted covariance of ``(x mm, y mm, z mm, gamma rad)``.
    converged : bool
        The optimiser converged (else the design is feasible but maybe not optimal).
    solver_status : str
        ipopt's return status.
    warnings : list of str
    """

    machine_mm: Vec
    pose_covariance: Vec
    converged: bool = True
    solver_status: str = ""
    warnings: list[str] = field(default_factory=list)

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


def _start_points(machine: Machine, count: int, skip: int = 0) -> Vec:
    low, high = machine.travel_min_mm, machine.travel_max_mm
    fractions = np.array(
        [[_halton(i + 1 + skip, base) for base in _HALTON_BASES] for i in range(count)]
    )
    return low + fractions * (high - low)


@dataclass(frozen=True)
class _Setting:
    """What the design is computed around: the coarse launch cp and the machine."""

    launch_cp_mm: Vec
    offset_mm: Vec
    spindle_angle_rad: float
    uncertainty: IdentificationUncertainty

    @classmethod
    def of(cls, machine: Machine) -> _Setting:
        if machine.launch_unit is None:
            raise InputError(
                "machine file has no launch_unit.position_mm; add the coarse launch position"
            )
        return cls(
            np.asarray(machine.launch_unit.position_mm, dtype=float),
            receiver_offset_mcs(machine),
            machine.spindle_angle_rad,
            IdentificationUncertainty.from_machine(machine.uncertainty),
        )


def _nominal_inputs(cp_mm: Symbolic, setting: _Setting) -> Symbolic:
    """The joint model's inputs (11,) of an exact alignment at receiver cp (3,), gamma 0."""
    b = cp_mm - setting.launch_cp_mm
    azimuth = ca.atan2(b[1], b[0])
    elevation = ca.atan2(b[2], ca.sqrt(b[0] ** 2 + b[1] ** 2))
    phi3 = azimuth + math.pi - setting.spindle_angle_rad
    return ca.vertcat(azimuth, elevation, phi3, -elevation, cp_mm, 0, 0, 0, 0)


def _alignment_terms(tool_mm: Symbolic, setting: _Setting) -> tuple[Symbolic, Symbolic]:
    """Information (7, 7) and systematic cross term (7, 19) of one alignment at a tool point."""
    theta = np.concatenate([setting.launch_cp_mm, np.zeros(4)])
    z = _nominal_inputs(tool_mm + setting.offset_mm, setting)
    _, d_theta, d_inputs, d_systematics = joint_model()(
        theta,
        z,
        np.zeros(len(systematic_sigmas(setting.uncertainty))),
        setting.spindle_angle_rad,
        0,
    )
    # the four angles (no distance is measured when planning)
    j, jz, jc = d_theta[:4, :], d_inputs[:4, :], d_systematics[:4, :]
    noise = jz @ ca.diag(input_sigmas(setting.uncertainty) ** 2) @ jz.T
    return j.T @ ca.solve(noise, j), j.T @ ca.solve(noise, jc)


def _offset_prior(setting: _Setting) -> Vec:
    prior = (1.0 / setting.uncertainty.zero_offset_rad) ** 2
    return np.diag([0.0] * 4 + [prior] * len(OFFSET_NAMES))


def _information(tool_mm: Symbolic, setting: _Setting) -> Symbolic:
    """Fisher information (7x7) of ``(x, y, z, gamma, c2, c3, c4)`` for tool points (N, 3)."""
    information = (
        ca.DM(_offset_prior(setting))
        if isinstance(tool_mm, ca.DM)
        else ca.MX(_offset_prior(setting))
    )
    for i in range(tool_mm.shape[0]):
        information += _alignment_terms(tool_mm[i, :].T, setting)[0]
    return information


def _pose_information(information: Symbolic) -> Symbolic:
    """Information about the pose with the offsets marginalised (Schur complement), 4x4."""
    f_pp, f_pc, f_cc = information[:4, :4], information[:4, 4:], information[4:, 4:]
    return f_pp - f_pc @ ca.solve(f_cc, f_pc.T)


def predicted_pose_covariance(machine: Machine, machine_mm: Vec) -> Vec:
    """Predicted covariance of ``(x mm, y mm, z mm, gamma rad)`` for alignments at tool
    points ``machine_mm`` (N, 3), around the machine file's coarse launch position, (4, 4).

    The random part (the inverse information) plus the systematics the alignments
    cannot estimate, propagated as ``identify`` does.
    """
    setting = _Setting.of(machine)
    points = ca.DM(np.atleast_2d(np.asarray(machine_mm, dtype=float)))
    information = np.array(_information(points, setting))
    cross = sum(
        np.array(_alignment_terms(points[i, :].T, setting)[1]) for i in range(points.shape[0])
    )
    covariance = np.linalg.inv(information)
    sigma_c = systematic_sigmas(setting.uncertainty)
    sigma_c[: len(OFFSET_NAMES)] = 0.0  # the offsets are estimated (with their prior)
    gain = covariance @ cross
    total = covariance + gain @ np.diag(sigma_c**2) @ gain.T
    return total[:4, :4]


def _min_separation_mm(machine: Machine) -> float:
    return MIN_SEPARATION_FRACTION * float(
        np.linalg.norm(machine.travel_max_mm - machine.travel_min_mm)
    )


def design_violations(machine: Machine, machine_mm: Vec, tolerance_mm: float = 0.0) -> list[str]:
    """What makes a set of identification positions (N, 3) unusable; empty if none."""
    setting = _Setting.of(machine)
    points = np.atleast_2d(np.asarray(machine_mm, dtype=float))
    beams = points + setting.offset_mm - setting.launch_cp_mm
    length = np.linalg.norm(beams, axis=1)
    elevation = np.degrees(np.arctan2(np.abs(beams[:, 2]), np.hypot(beams[:, 0], beams[:, 1])))
    problems = []
    if not np.all(machine.within_travel(points, tolerance_mm)):
        problems.append("a position lies outside the travel")
    if np.any(length < machine.measurement.standoff_mm - tolerance_mm) or np.any(
        length > machine.interferometer.max_range_mm + tolerance_mm
    ):
        problems.append("a beam is shorter than the stand-off or longer than the range")
    if np.any(elevation > MAX_ELEVATION_DEG + 1e-3):
        problems.append(f"a beam is steeper than {MAX_ELEVATION_DEG:g}°")
    gaps = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=-1)
    gaps[np.diag_indices(len(points))] = np.inf
    if np.any(gaps < _min_separation_mm(machine) - tolerance_mm):
        problems.append(
            f"two positions are closer than {_min_separation_mm(machine):.0f} mm"
            f" ({MIN_SEPARATION_FRACTION:g} of the travel's diagonal)"
        )
    return problems


@dataclass(frozen=True)
class _Attempt:
    machine_mm: Vec
    objective: float
    converged: bool
    status: str


def _solve_from(machine: Machine, setting: _Setting, start_mm: Vec) -> _Attempt:
    count = len(start_mm)
    opti = ca.Opti()
    tool = opti.variable(count, 3)
    pose_info = _pose_information(_information(tool, setting))
    u = setting.uncertainty
    # Scale to the size of one observation's noise so the determinant is of order 1.
    reference = np.diag([u.machine_position_mm] * 3 + [u.encoder_rad])
    objective = -ca.log(ca.det(reference @ pose_info @ reference))
    opti.minimize(objective)
    standoff2 = machine.measurement.standoff_mm**2
    range2 = machine.interferometer.max_range_mm**2
    steep2 = math.tan(math.radians(MAX_ELEVATION_DEG)) ** 2
    separation2 = _min_separation_mm(machine) ** 2
    for i in range(count):
        for k in range(3):
            opti.subject_to(
                opti.bounded(machine.travel_min_mm[k], tool[i, k], machine.travel_max_mm[k])
            )
        beam = tool[i, :].T + setting.offset_mm - setting.launch_cp_mm
        opti.subject_to(opti.bounded(standoff2, ca.sumsqr(beam), range2))
        opti.subject_to(beam[2] ** 2 <= steep2 * (beam[0] ** 2 + beam[1] ** 2))
        for j in range(i):
            opti.subject_to(ca.sumsqr(tool[i, :] - tool[j, :]) >= separation2)
    opti.set_initial(tool, start_mm)
    opti.solver("ipopt", {"print_time": False}, _IPOPT_OPTIONS)
    failure = ""
    try:
        opti.solve()
    except RuntimeError as error:  # the status below says what happened; the caller decides
        failure = str(error).strip().splitlines()[-1].strip()
        logger.info("ipopt stopped early: %s", failure)
    try:
        stats = opti.stats()
    except RuntimeError:  # refused before it ran (e.g. contradictory bounds)
        return _Attempt(start_mm, math.inf, False, failure or "not solved")
    return _Attempt(
        np.atleast_2d(opti.debug.value(tool)),
        float(opti.debug.value(objective)),
        bool(stats.get("success", False)),
        str(stats.get("return_status", "unknown")),
    )


def design_identification(machine: Machine, count: int = 6) -> IdentificationDesign:
    """Machine positions for identification that minimise the predicted pose uncertainty.

    Parameters
    ----------
    machine : Machine
        Travel, receiver offset, stand-off, beam range, uncertainties and the coarse
        launch position ``launch_unit.position_mm``.
    count : int
        Number of alignments (at least 2).

    Returns
    -------
    IdentificationDesign
        ``converged`` is False (and ``warnings`` says why) when the solver stopped
        early on a design that is feasible but may not be optimal.

    Raises
    ------
    InputError
        No coarse launch position in the machine file, or ``count`` outside
        :data:`MIN_POSITIONS` .. :data:`MAX_POSITIONS`.
    GeometryError
        No feasible design (the solver found none inside the travel and ranges, with
        distinct positions and no steep beam); the message gives the solver's status.
    """
    setting = _Setting.of(machine)
    problem = count_problem(count)
    if problem is not None:
        raise InputError(f"identification design: {problem}")
    attempts = [
        _solve_from(machine, setting, _start_points(machine, count, skip=k * count))
        for k in range(_STARTS)
    ]
    feasible = [
        a for a in attempts if not design_violations(machine, a.machine_mm, _FEASIBILITY_TOL_MM)
    ]
    if not feasible:
        problems = design_violations(machine, attempts[0].machine_mm, _FEASIBILITY_TOL_MM)
        raise GeometryError(
            f"no identification design of {count} positions found ({'; '.join(problems)};"
            f" solver: {', '.join(a.status for a in attempts)}); check launch_unit.position_mm"
            " and measurement.standoff_mm, or ask for fewer positions"
        )
    best = min(feasible, key=lambda a: (not a.converged, a.objective))
    # ipopt honours bounds only to its tolerance: put the points exactly inside the travel.
    machine_mm = np.clip(best.machine_mm, machine.travel_min_mm, machine.travel_max_mm) + 0.0
    covariance = predicted_pose_covariance(machine, machine_mm)
    if not np.all(np.isfinite(covariance)):
        raise GeometryError(
            f"the identification design of {count} positions does not determine the pose"
        )
    warnings = []
    if not best.converged:
        warnings.append(
            f"the design optimiser stopped before converging ({best.status}): the positions are"
            " usable but may not be the best ones"
        )
    return IdentificationDesign(machine_mm, covariance, best.converged, best.status, warnings)
