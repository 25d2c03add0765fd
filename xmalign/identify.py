"""Launch-unit pose identification from aligned units (pure numpy / scipy).

Three estimators of the launch cp ``p_L`` and azimuth ``gamma``:

``intersection``
    The seed paper's method (002, section 2.3.2): the point nearest to all
    receiver beam lines, ``gamma`` as the circular mean of beam azimuth minus
    ``phi1``. Kept as the baseline.
``distance``
    The closed kinematic loop with known cp-to-cp distances (002, 2.3.1),
    both chains: ``p_R + l·u = p_L`` and ``p_L + l·d = p_R``.
``joint``
    Weighted nonlinear least squares over every angle, distance and residual
    straightness, also estimating the encoder zero offsets ``c2``, ``c3``,
    ``c4`` that the alignments can separate; robust to one bad alignment.

Every estimator reports a covariance built from the stated uncertainties
(encoder noise, machine positioning, the tool's rotation that turns the
receiver, unit kinematics, zero offsets, the machine's common-mode error and
the beams' collimation), not only from the fit's scatter, and which alignment
contributes what. The models are written in casadi: their derivatives are exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import casadi as ca
import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtrc

from xmalign.errors import GeometryError, InputError
from xmalign.formats.pose import LaunchPose
from xmalign.formats.session import Session
from xmalign.geometry import Vec, azimuth_elevation, circular_mean, line_frame, wrap_angle
from xmalign.kinematics import launch_direction, receiver_axis, receiver_cp
from xmalign.machine import Uncertainty

METHODS = ("joint", "intersection", "distance")
OFFSET_NAMES = ("c2", "c3", "c4")
#: An offset is estimated only if the data pin it down to this fraction of its prior.
_OFFSET_INFORMATION_RATIO = 0.7
#: Global chi-square p-value below which the fit is suspect (outlier search, scaling).
_SUSPECT_P = 1e-3
_NEAR_PARALLEL_DEG = 20.0
_WEAK_POSITION_MM = 0.05


@dataclass(frozen=True)
class IdentificationUncertainty:
    """Standard uncertainties (k = 1) of the inputs, in mm and rad.

    ``machine_position_mm`` and ``tool_rotation_rad`` vary from one alignment to
    the next; ``machine_common_mm`` and ``tool_rotation_common_rad`` are the
    machine's error shared by all alignment positions (a common shift or turn
    of the tool that the field cannot separate from the pose);
    ``collimation_rad`` is each unit's beam tilt in its head (two components).
    """

    encoder_rad: float = 10e-6
    machine_position_mm: float = 0.020
    unit_kinematics_mm: float = 0.010
    zero_offset_rad: float = 100e-6
    distance_mm: float = 0.020
    straightness_mm: float = 0.002
    tool_rotation_rad: float = 15e-6
    tool_rotation_common_rad: float = 18e-6
    machine_common_mm: float = 0.015
    collimation_rad: float = 20e-6

    @classmethod
    def from_machine(cls, u: Uncertainty) -> IdentificationUncertainty:
        """From the machine file's ``uncertainty`` section (um, urad)."""
        return cls(
            encoder_rad=u.encoder_urad * 1e-6,
            machine_position_mm=u.machine_position_um * 1e-3,
            unit_kinematics_mm=u.unit_kinematics_um * 1e-3,
            zero_offset_rad=u.encoder_zero_offset_urad * 1e-6,
            distance_mm=u.distance_um * 1e-3,
            straightness_mm=u.straightness_um * 1e-3,
            tool_rotation_rad=u.tool_rotation_urad * 1e-6,
            tool_rotation_common_rad=u.tool_rotation_common_urad * 1e-6,
            machine_common_mm=u.machine_common_um * 1e-3,
            collimation_rad=u.beam_collimation_urad * 1e-6,
        )

    @property
    def position_mm(self) -> float:
        """Per-axis uncertainty of where the receiver cp really is at one alignment."""
        return float(np.hypot(self.machine_position_mm, self.straightness_mm))


# Columns of the per-alignment input array: reported angles (rad), beam point (mm),
# distance (mm), the tool's rotation (rad, MCS rotation vector; unknown, nominally 0).
PHI1, PHI2, PHI3, PHI4, BX, BY, BZ, DIST, RX, RY, RZ = range(11)
N_INPUTS = 11


@dataclass(frozen=True)
class Observations:
    """A session as arrays.

    Attributes
    ----------
    inputs : ndarray, shape (n, 11)
        Per alignment: reported ``phi1..phi4`` (rad), the beam point (mm) where
        the beam crosses the receiver (its cp minus the residual straightness),
        the cp-to-cp distance (mm, 0 where unknown) and the tool rotation (rad,
        0: not measured, its uncertainty enters the covariance).
    has_distance : ndarray of bool, shape (n,)
    spindle_angle_rad : float
    """

    inputs: Vec
    has_distance: Vec
    spindle_angle_rad: float

    @property
    def n(self) -> int:
        return len(self.inputs)

    def subset(self, keep: Vec) -> Observations:
        """The observations of the alignments where ``keep`` (n,) is True."""
        return replace(self, inputs=self.inputs[keep], has_distance=self.has_distance[keep])


def observations_from_session(session: Session) -> Observations:
    """Arrays of a session, with the residual straightness moved onto the beam point."""
    rows = []
    for a in session.alignments:
        cp = receiver_cp(a.machine_mm, session.receiver_offset_mm, session.spindle_angle_rad)
        if a.straightness_um is not None:
            beam = -receiver_axis(session.spindle_angle_rad, a.receiver_rad[0], a.receiver_rad[1])
            _, v, w = line_frame(beam)
            cp = cp - (a.straightness_um[0] * v + a.straightness_um[1] * w) * 1e-3
        distance = 0.0 if a.distance_mm is None else a.distance_mm
        rows.append([*a.launch_rad[:2], *a.receiver_rad[:2], *cp, distance, 0.0, 0.0, 0.0])
    has_distance = np.array([a.distance_mm is not None for a in session.alignments], dtype=bool)
    inputs = np.array(rows, dtype=float).reshape(-1, N_INPUTS)
    return Observations(inputs, has_distance, session.spindle_angle_rad)


def input_sigmas(u: IdentificationUncertainty) -> Vec:
    """Standard uncertainty of each input column, shape (11,)."""
    p = u.position_mm
    return np.array([u.encoder_rad] * 4 + [p, p, p, u.distance_mm] + [u.tool_rotation_rad] * 3)


def systematic_sigmas(u: IdentificationUncertainty) -> Vec:
    """Standard uncertainty of each systematic (see ``N_SYSTEMATICS``), shape (19,)."""
    return np.array(
        [u.zero_offset_rad] * 3
        + [u.unit_kinematics_mm] * 6
        + [u.machine_common_mm] * 3
        + [u.tool_rotation_common_rad] * 3
        + [u.collimation_rad] * 4
    )


@dataclass
class AlignmentReport:
    """What one alignment brings to the result.

    ``share_position`` and ``share_gamma`` are the fractions of the position
    (trace) and gamma variance that stem from this alignment's inputs;
    ``normalized_residual`` is its RMS whitened residual (about 1 when it agrees
    with the stated uncertainties).
    """

    index: int
    share_position: float
    share_gamma: float
    normalized_residual: float
    excluded: bool = False


@dataclass
class IdentificationResult:
    """Result of an identification (cf. scipy's OptimizeResult).

    Attributes
    ----------
    position_mm : (3,)
    gamma_rad : float
    covariance : (4, 4)
        Of ``(x mm, y mm, z mm, gamma rad)``, including the uncertainty of
        offsets that were not estimated.
    offsets_rad : dict
        The estimated encoder zero offsets.
    offsets_covariance : (k, k)
        Of the estimated offsets, rad^2.
    converged, iterations
        Whether the solver converged (the closed-form intersection always does)
        and in how many iterations; a warning says so when it did not.
    """

    method: str
    position_mm: Vec
    gamma_rad: float
    covariance: Vec
    offsets_rad: dict[str, float] = field(default_factory=dict)
    offsets_covariance: Vec = field(default_factory=lambda: np.zeros((0, 0)))
    offsets_not_estimated: dict[str, str] = field(default_factory=dict)
    residual_rms_um: float = 0.0
    chi2: float = 0.0
    dof: int = 0
    covariance_scale: float = 1.0
    alignments: list[AlignmentReport] = field(default_factory=list)
    outlier: int | None = None
    warnings: list[str] = field(default_factory=list)
    converged: bool = True
    iterations: int = 0

    @property
    def n_used(self) -> int:
        return sum(not a.excluded for a in self.alignments)

    def to_pose(self) -> LaunchPose:
        return LaunchPose(
            position_mm=self.position_mm,
            gamma_rad=self.gamma_rad,
            covariance=self.covariance,
            encoder_offsets_rad=dict(self.offsets_rad),
            method=self.method,
            residual_rms_um=self.residual_rms_um,
            n_alignments=self.n_used,
        )


# ------------------------------------------------------------------ residual models
#
# Every method is a residual model r(theta, z_i, c) -> (k,) per alignment i, written in
# casadi so that its derivatives are exact: theta the parameters, z_i the alignment's
# inputs (the columns above; the tool rotation is nominally zero) and c (N_SYSTEMATICS,)
# what is common to all alignments and not estimated, nominally zero: the encoder zero
# offsets c2, c3, c4 beyond those estimated, the optical centres' offsets from the cps in
# the launch and receiver head frames (axes that do not intersect), the machine's
# common-mode position error and tool rotation at the alignment positions, and both
# units' beam collimation. The estimate minimises the (whitened) residuals; its
# covariance follows from the implicit-function theorem,
# d theta / d z = -(J^T J)^-1 J^T dr/dz, with the stated uncertainties of every z and c.

C2, C3, C4 = 0, 1, 2
LAUNCH_CENTRE = slice(3, 6)
RECEIVER_CENTRE = slice(6, 9)
COMMON_POSITION = slice(9, 12)
COMMON_ROTATION = slice(12, 15)
LAUNCH_COLLIMATION = slice(15, 17)
RECEIVER_COLLIMATION = slice(17, 19)
N_SYSTEMATICS = 19
_NO_SYSTEMATICS = np.zeros(N_SYSTEMATICS)


def _sx_direction(azimuth: ca.SX, elevation: ca.SX) -> ca.SX:
    return ca.vertcat(
        ca.cos(azimuth) * ca.cos(elevation), ca.sin(azimuth) * ca.cos(elevation), ca.sin(elevation)
    )


def _sx_azimuth_elevation(e: ca.SX) -> tuple[ca.SX, ca.SX]:
    return ca.atan2(e[1], e[0]), ca.atan2(e[2], ca.sqrt(e[0] ** 2 + e[1] ** 2))


def _sx_wrap(angle: ca.SX) -> ca.SX:
    return ca.atan2(ca.sin(angle), ca.cos(angle))


def _sx_head_to_mcs(azimuth: ca.SX, elevation: ca.SX, vector_head: ca.SX) -> ca.SX:
    """``Rz(az)·Ry(-el)·vector``."""
    ca_, sa, ce, se = ca.cos(azimuth), ca.sin(azimuth), ca.cos(elevation), ca.sin(elevation)
    x_axis = ca.vertcat(ca_ * ce, sa * ce, se)
    y_axis = ca.vertcat(-sa, ca_, 0)
    z_axis = ca.vertcat(-ca_ * se, -sa * se, ce)
    return vector_head[0] * x_axis + vector_head[1] * y_axis + vector_head[2] * z_axis


@dataclass(frozen=True)
class _Symbols:
    """One alignment's model inputs as casadi symbols, and the geometry they imply."""

    theta: ca.SX
    z: ca.SX
    c: ca.SX
    spindle: ca.SX
    has_distance: ca.SX
    offsets: ca.SX  # true minus reported c2, c3, c4 (estimated plus systematic)

    @property
    def tool_rotation(self) -> ca.SX:
        return self.z[RX : RZ + 1] + self.c[COMMON_ROTATION]

    def launch_centre(self) -> ca.SX:
        return self.theta[:3] + _sx_head_to_mcs(
            self.theta[3] + self.z[PHI1], self.z[PHI2], self.c[LAUNCH_CENTRE]
        )

    def receiver_centre(self) -> ca.SX:
        beam_point = self.z[BX:DIST] + self.c[COMMON_POSITION]
        return beam_point + _sx_head_to_mcs(
            self.spindle + self.z[PHI3], self.z[PHI4], self.c[RECEIVER_CENTRE]
        )

    def launch_angles(self) -> tuple[ca.SX, ca.SX]:
        """Azimuth and elevation of the launch beam from the launch encoders (true angles)."""
        elevation = self.z[PHI2] + self.offsets[0] - self.c[LAUNCH_COLLIMATION][0]
        # A beam tilted sideways in the head turns its azimuth by tilt / cos(elevation).
        azimuth = self.theta[3] + self.z[PHI1] + self.c[LAUNCH_COLLIMATION][1] / ca.cos(elevation)
        return azimuth, elevation

    def receiver_angles(self) -> tuple[ca.SX, ca.SX]:
        """Azimuth and elevation of the receiver axis in its mount (the tool) frame."""
        elevation = self.z[PHI4] + self.offsets[2] - self.c[RECEIVER_COLLIMATION][0]
        azimuth = (
            self.spindle
            + self.z[PHI3]
            + self.offsets[1]
            + self.c[RECEIVER_COLLIMATION][1] / ca.cos(elevation)
        )
        return azimuth, elevation

    def beam_from_receiver(self) -> ca.SX:
        """Beam direction launch -> receiver from the receiver encoders, MCS (the tool turns)."""
        axis = _sx_direction(*self.receiver_angles())
        return -(axis + ca.cross(self.tool_rotation, axis))


def _symbols(n_params: int, estimated: tuple[str, ...] = ()) -> _Symbols:
    theta = ca.SX.sym("theta", n_params)
    c = ca.SX.sym("c", N_SYSTEMATICS)
    offsets = [c[C2], c[C3], c[C4]]
    for k, name in enumerate(estimated):
        offsets[OFFSET_NAMES.index(name)] += theta[4 + k]
    return _Symbols(
        theta,
        ca.SX.sym("z", N_INPUTS),
        c,
        ca.SX.sym("spindle"),
        ca.SX.sym("has_distance"),
        ca.vertcat(*offsets),
    )


def _joint_residuals(s: _Symbols) -> ca.SX:
    """Angle and distance residuals of the joint model, (5,)."""
    e = s.receiver_centre() - s.launch_centre()
    azimuth, elevation = _sx_azimuth_elevation(e)
    # The receiver's encoders see the beam in the frame of the tool, which is turned.
    seen = e - ca.cross(s.tool_rotation, e)
    seen_azimuth, seen_elevation = _sx_azimuth_elevation(-seen)
    launch_azimuth, launch_elevation = s.launch_angles()
    receiver_azimuth, receiver_elevation = s.receiver_angles()
    return ca.vertcat(
        _sx_wrap(launch_azimuth - azimuth),
        launch_elevation - elevation,
        _sx_wrap(receiver_azimuth - seen_azimuth),
        receiver_elevation - seen_elevation,
        s.has_distance * (s.z[DIST] - ca.norm_2(e)),
    )


def _intersection_residuals(s: _Symbols) -> ca.SX:
    """Perpendicular miss of the launch cp from the receiver beam line, and gamma, (4,)."""
    d = s.beam_from_receiver()
    miss = s.launch_centre() - s.receiver_centre()
    perpendicular = miss - ca.dot(miss, d) * d
    azimuth, _ = _sx_azimuth_elevation(d)
    launch_azimuth, _ = s.launch_angles()
    return ca.vertcat(perpendicular, _sx_wrap(azimuth - launch_azimuth))


def _distance_residuals(s: _Symbols) -> ca.SX:
    """Both chains of the closed loop with a known distance, mm, (6,)."""
    length = s.z[DIST]
    launch, receiver = s.launch_centre(), s.receiver_centre()
    d_launch = _sx_direction(*s.launch_angles())
    receiver_chain = receiver - length * s.beam_from_receiver() - launch
    launch_chain = launch + length * d_launch - receiver
    return ca.vertcat(receiver_chain, launch_chain)


_MODELS = {
    "joint": _joint_residuals,
    "intersection": _intersection_residuals,
    "distance": _distance_residuals,
}


@dataclass(frozen=True)
class _Evaluation:
    """Residuals and their exact derivatives for every alignment."""

    residuals: Vec  # (n, k)
    d_theta: Vec  # (n, k, p)
    d_inputs: Vec  # (n, k, N_INPUTS)
    d_systematics: Vec  # (n, k, N_SYSTEMATICS)


@lru_cache(maxsize=32)
def _compiled(method: str, estimated: tuple[str, ...]) -> ca.Function:
    s = _symbols(4 + len(estimated), estimated)
    r = _MODELS[method](s)
    arguments = [s.theta, s.z, s.c, s.spindle, s.has_distance]
    outputs = [r, ca.jacobian(r, s.theta), ca.jacobian(r, s.z), ca.jacobian(r, s.c)]
    return ca.Function(f"identify_{method}", arguments, outputs, {"cse": True})


def joint_model() -> ca.Function:
    """The joint model of one alignment with every offset estimated, for planning.

    A casadi function ``(theta (7,), z (11,), c (19,), spindle_angle_rad,
    has_distance) -> (r (5,), dr/dtheta (5, 7), dr/dz (5, 11), dr/dc (5, 19))``
    with ``theta = (x, y, z, gamma, c2, c3, c4)`` and the input and systematic
    columns of this module; the derivatives are exact.
    """
    return _compiled("joint", OFFSET_NAMES)


@lru_cache(maxsize=256)
def _mapped(method: str, estimated: tuple[str, ...], n: int) -> ca.Function:
    return _compiled(method, estimated).map(n)


@dataclass(frozen=True)
class _Model:
    """A residual model over the alignments of one set of observations."""

    method: str
    estimated: tuple[str, ...]
    obs: Observations

    @property
    def n_params(self) -> int:
        return 4 + len(self.estimated)

    def evaluate(self, theta: Vec, systematics: Vec = _NO_SYSTEMATICS) -> _Evaluation:
        n = self.obs.n
        out = _mapped(self.method, self.estimated, n)(
            theta,
            self.obs.inputs.T,
            systematics,
            self.obs.spindle_angle_rad,
            self.obs.has_distance.astype(float)[None, :],
        )
        r = np.array(out[0]).T
        k = r.shape[1]

        def blocks(matrix: ca.DM) -> Vec:
            return np.array(matrix).reshape(k, n, -1).transpose(1, 0, 2)

        return _Evaluation(r, blocks(out[1]), blocks(out[2]), blocks(out[3]))

    def residuals(self, theta: Vec) -> Vec:
        return self.evaluate(theta).residuals


def _beam_from_receiver(obs: Observations) -> Vec:
    """Beam directions launch -> receiver from the reported receiver angles, (n, 3)."""
    return -receiver_axis(obs.spindle_angle_rad, obs.inputs[:, PHI3], obs.inputs[:, PHI4])


# ------------------------------------------------------------------ numerical machinery


def _residual_covariances(jz: Vec, sigma_inputs: Vec) -> Vec:
    """Covariance of each alignment's residuals caused by its input noise, (n, k, k)."""
    return np.einsum("nij,j,nkj->nik", jz, sigma_inputs**2, jz)


def _whitening(cov: Vec) -> Vec:
    """Matrices W with W cov W^T = I on the informative subspace, (n, k, k)."""
    values, vectors = np.linalg.eigh(cov)
    floor = values.max(axis=1, keepdims=True) * 1e-12
    inv_sqrt = np.where(values > floor, 1.0 / np.sqrt(np.maximum(values, floor)), 0.0)
    return np.einsum("nij,nj->nji", vectors, inv_sqrt)


@dataclass
class FitResult:
    """Outcome of the Gauss-Newton solver.

    Attributes
    ----------
    theta : (p,)
    jacobian : (n, k, p)
        Whitened, at ``theta``.
    residuals : (n, k)
        Whitened, at ``theta``.
    converged : bool
        The predicted decrease of the cost fell below the tolerance.
    iterations : int
    decrement : float
        Last predicted decrease of the whitened cost (chi-square units).
    """

    theta: Vec
    jacobian: Vec
    residuals: Vec
    converged: bool = True
    iterations: int = 0
    decrement: float = 0.0


#: Gauss-Newton stops when a step would lower chi-square by less than this fraction of it
#: (or of 1 when it is smaller): far below any statistical meaning. The last step is
#: still taken, so a noise-free fit ends at rounding level (quadratic convergence).
_DECREMENT_TOL = 1e-10


def _gauss_newton(model: _Model, theta0: Vec, weights: Vec, max_iterations: int = 60) -> FitResult:
    """Minimise sum |W_i r_i|^2 by Gauss-Newton with step halving."""

    def whitened(theta: Vec) -> tuple[Vec, Vec]:
        e = model.evaluate(theta)
        r = np.einsum("nij,nj->ni", weights, e.residuals)
        return r, np.einsum("nij,njp->nip", weights, e.d_theta)

    theta = np.asarray(theta0, dtype=float).copy()
    r, j = whitened(theta)
    cost = float(np.sum(r**2))
    decrement = float("inf")
    for iteration in range(1, max_iterations + 1):
        jf = j.reshape(-1, len(theta))
        step, *_ = np.linalg.lstsq(jf, -r.ravel(), rcond=None)
        decrement = float(np.sum((jf @ step) ** 2))
        if decrement <= _DECREMENT_TOL * max(cost, 1.0):
            r_new, j_new = whitened(theta + step)
            if float(np.sum(r_new**2)) <= cost:
                theta, r, j = theta + step, r_new, j_new
            return FitResult(theta, j, r, True, iteration, decrement)
        for _ in range(30):
            r_new, j_new = whitened(theta + step)
            cost_new = float(np.sum(r_new**2))
            if cost_new <= cost:
                break
            step = step / 2
        else:
            # No step lowers the cost: a minimum as far as rounding lets us see.
            return FitResult(theta, j, r, decrement <= 1e-6 * max(cost, 1.0), iteration, decrement)
        theta, r, j, cost = theta + step, r_new, j_new, cost_new
    return FitResult(theta, j, r, False, max_iterations, decrement)


@dataclass
class _Propagation:
    covariance: Vec  # (p, p), all inputs and systematics
    per_alignment: Vec  # (n, p, p)
    from_systematics: Vec  # (p, p)


def _propagate(
    model: _Model, fit: FitResult, e: _Evaluation, weights: Vec, u: IdentificationUncertainty
) -> _Propagation:
    """Covariance of theta from the input and systematic uncertainties (implicit function).

    ``e`` is the model evaluated at the fit. Offsets the model estimates are
    parameters, not systematics, and carry no prior.
    """
    jf = fit.jacobian.reshape(-1, len(fit.theta))
    hessian_inv = np.linalg.pinv(jf.T @ jf)
    # G_i = -H^-1 J_i^T W_i dr_i/dz_i, per alignment (p, N_INPUTS)
    g_inputs = -np.einsum("pq,nkq,nkl,nlj->npj", hessian_inv, fit.jacobian, weights, e.d_inputs)
    sigma = input_sigmas(u)
    per_alignment = np.einsum("npj,j,nqj->npq", g_inputs, sigma**2, g_inputs)
    g_systematic = -hessian_inv @ np.einsum(
        "nkq,nkl,nlj->qj", fit.jacobian, weights, e.d_systematics
    )
    sigma_systematic = systematic_sigmas(u)
    sigma_systematic[[OFFSET_NAMES.index(name) for name in model.estimated]] = 0.0
    from_systematics = g_systematic @ np.diag(sigma_systematic**2) @ g_systematic.T
    return _Propagation(
        per_alignment.sum(axis=0) + from_systematics, per_alignment, from_systematics
    )


# ------------------------------------------------------------------------ estimators


def _nearest_point_to_lines(points: Vec, directions: Vec) -> Vec:
    """Least-squares point nearest to lines ``points + t·directions``, (3,)."""
    projectors = np.eye(3) - np.einsum("ni,nj->nij", directions, directions)
    a = projectors.sum(axis=0)
    if np.linalg.cond(a) > 1e10:
        raise GeometryError(
            "degenerate geometry: the beam lines are (nearly) parallel and do not cross; "
            "align at machine positions that view the launch unit from different sides"
        )
    return np.linalg.solve(a, np.einsum("nij,nj->i", projectors, points))


def _intersection_estimate(obs: Observations) -> Vec:
    """The seed paper's estimate: nearest point to the beam lines, mean azimuth offset."""
    d = _beam_from_receiver(obs)
    position = _nearest_point_to_lines(obs.inputs[:, BX:DIST], d)
    azimuth, _ = azimuth_elevation(d)
    return np.append(position, circular_mean(azimuth - obs.inputs[:, PHI1]))


def _unit_weights(n: int, k: int) -> Vec:
    return np.broadcast_to(np.eye(k), (n, k, k)).copy()


def _distance_start(obs: Observations) -> Vec:
    d = _beam_from_receiver(obs)
    launch_cps = obs.inputs[:, BX:DIST] - obs.inputs[:, DIST, None] * d
    position = launch_cps.mean(axis=0)
    azimuth, _ = azimuth_elevation(obs.inputs[:, BX:DIST] - position)
    return np.append(position, circular_mean(azimuth - obs.inputs[:, PHI1]))


def _weights(model: _Model, theta: Vec, u: IdentificationUncertainty) -> Vec:
    """Whitening of each alignment's residuals by the covariance its inputs give them."""
    return _whitening(_residual_covariances(model.evaluate(theta).d_inputs, input_sigmas(u)))


def _information(model: _Model, theta: Vec, weights: Vec) -> Vec:
    """Whitened normal matrix J^T J, (p, p)."""
    j = np.einsum("nij,njp->nip", weights, model.evaluate(theta).d_theta)
    jf = j.reshape(-1, len(theta))
    return jf.T @ jf


def _relative_conditioning(information: Vec) -> tuple[Vec, Vec]:
    """Eigen-decomposition of the information matrix scaled to unit diagonal."""
    scale = 1.0 / np.sqrt(np.maximum(np.diag(information), 1e-300))
    return np.linalg.eigh(information * np.outer(scale, scale))


def _select_offsets(
    obs: Observations, start: Vec, u: IdentificationUncertainty
) -> tuple[tuple[str, ...], dict[str, str]]:
    """The encoder offsets the alignments can separate from the pose (rank and information test)."""
    # With every offset a parameter (all zero here) the information of any subset is a
    # sub-matrix, and the weights are those of any subset: one evaluation serves all.
    every = _Model("joint", OFFSET_NAMES, obs)
    theta_every = np.concatenate([start, np.zeros(len(OFFSET_NAMES))])
    full_information = _information(every, theta_every, _weights(every, theta_every, u))

    def information_of(names: list[str]) -> Vec:
        keep = [0, 1, 2, 3] + [4 + OFFSET_NAMES.index(name) for name in names]
        return full_information[np.ix_(keep, keep)]

    values, _ = _relative_conditioning(information_of([]))
    if values[0] < 1e-10 * values[-1]:
        raise GeometryError(
            "degenerate geometry: these alignments do not determine the launch pose (rank test); "
            "align at machine positions spread across X, Y and Z"
        )
    candidates = list(OFFSET_NAMES)
    reasons: dict[str, str] = {}
    while candidates:
        information = information_of(candidates)
        values, vectors = _relative_conditioning(information)
        if values[0] < 1e-9 * values[-1]:
            worst = int(np.argmax(np.abs(vectors[4:, 0])))
            reasons[candidates.pop(worst)] = (
                "cannot be told apart from the pose with these alignments (rank test)"
            )
            continue
        sigma_rad = np.sqrt(np.diag(np.linalg.inv(information))[4:])
        worst = int(np.argmax(sigma_rad))
        if sigma_rad[worst] > _OFFSET_INFORMATION_RATIO * u.zero_offset_rad:
            reasons[candidates.pop(worst)] = (
                f"the alignments pin it only to ±{sigma_rad[worst] * 1e6:.0f} µrad against "
                f"±{u.zero_offset_rad * 1e6:.0f} µrad expected; alignments at more varied "
                "distances and heights would separate it"
            )
            continue
        break
    return tuple(candidates), reasons


@dataclass
class _Solution:
    theta: Vec
    propagation: _Propagation
    normalized: Vec  # (n,) RMS whitened residual per alignment
    chi2: float
    dof: int
    fit: FitResult


def _normalized_residuals(e: _Evaluation, u: IdentificationUncertainty) -> tuple[Vec, Vec]:
    """Per alignment: residual quadratic form with its predicted covariance, and its rank."""
    cov = _residual_covariances(e.d_inputs, input_sigmas(u))
    pinv = np.linalg.pinv(cov, rcond=1e-10, hermitian=True)
    quadratic = np.einsum("ni,nij,nj->n", e.residuals, pinv, e.residuals)
    rank = np.linalg.matrix_rank(cov, tol=None, hermitian=True)
    return quadratic, rank


def _global_chi2(
    model: _Model, e: _Evaluation, weights: Vec, u: IdentificationUncertainty
) -> tuple[float, int]:
    """Chi-square of all residuals with their full predicted covariance, and its dof.

    The residuals' covariance is that of every input and systematic pushed through
    the fit (``(I - A) C (I - A)^T`` with ``A`` the fit's hat matrix): what the
    systematics leave in the residuals after the pose absorbed its share (a common
    tilt of the tool is not a constant offset of any encoder) is expected, not a
    sign of underestimated uncertainties.
    """
    n, k, p = e.d_theta.shape
    per_alignment = _residual_covariances(e.d_inputs, input_sigmas(u))
    covariance = np.zeros((n * k, n * k))
    weight = np.zeros((n * k, n * k))
    for i in range(n):
        block = slice(i * k, (i + 1) * k)
        covariance[block, block] = per_alignment[i]
        weight[block, block] = weights[i].T @ weights[i]
    sigma_c = systematic_sigmas(u)
    sigma_c[[OFFSET_NAMES.index(name) for name in model.estimated]] = 0.0
    jc = e.d_systematics.reshape(n * k, -1)
    covariance += jc @ np.diag(sigma_c**2) @ jc.T
    j = e.d_theta.reshape(n * k, p)
    hat = j @ np.linalg.pinv(j.T @ weight @ j) @ j.T @ weight
    leave = np.eye(n * k) - hat
    values, vectors = np.linalg.eigh(leave @ covariance @ leave.T)
    keep = values > 1e-10 * values.max()
    projected = vectors[:, keep].T @ e.residuals.ravel()
    return float(np.sum(projected**2 / values[keep])), int(keep.sum())


def _fixed_fit(model: _Model, theta: Vec, weights: Vec) -> FitResult:
    """A closed-form estimate as a fit (nothing iterated)."""
    e = model.evaluate(theta)
    return FitResult(
        theta,
        np.einsum("nij,njp->nip", weights, e.d_theta),
        np.einsum("nij,nj->ni", weights, e.residuals),
    )


def _solve(
    method: str, obs: Observations, u: IdentificationUncertainty, estimated: tuple[str, ...]
) -> _Solution:
    model = _Model(method, estimated if method == "joint" else (), obs)
    if method == "intersection":
        weights = _unit_weights(obs.n, 4)
        fit = _fixed_fit(model, _intersection_estimate(obs), weights)
    elif method == "distance":
        weights = _unit_weights(obs.n, 6)
        fit = _gauss_newton(model, _distance_start(obs), weights)
    else:
        theta0 = np.concatenate([_intersection_estimate(obs), np.zeros(len(estimated))])
        weights = _weights(model, theta0, u)
        fit = _gauss_newton(model, theta0, weights)
    at_fit = model.evaluate(fit.theta)
    propagation = _propagate(model, fit, at_fit, weights, u)
    quadratic, rank = _normalized_residuals(at_fit, u)
    chi2, dof = _global_chi2(model, at_fit, weights, u)
    return _Solution(
        fit.theta, propagation, np.sqrt(quadratic / np.maximum(rank, 1)), chi2, dof, fit
    )


def _p_value(solution: _Solution) -> float:
    return float(chdtrc(solution.dof, solution.chi2)) if solution.dof > 0 else 1.0


def _without_outlier(
    obs: Observations, u: IdentificationUncertainty, estimated: tuple[str, ...], full: _Solution
) -> tuple[_Solution, int | None]:
    """Leave-one-out search for one bad alignment, when the fit is suspect."""
    if obs.n < 4 or _p_value(full) >= _SUSPECT_P:
        return full, None
    best, best_index = None, None
    for i in range(obs.n):
        keep = np.arange(obs.n) != i
        try:
            trial = _solve("joint", obs.subset(keep), u, estimated)
        except GeometryError:
            continue
        if best is None or trial.chi2 < best.chi2:
            best, best_index = trial, i
    if best is None or _p_value(best) < _SUSPECT_P:
        return full, None
    return best, best_index


# ------------------------------------------------------------------------ public API


def _minimum_alignments(method: str, obs: Observations, source: str) -> Observations:
    if method == "distance":
        obs = obs.subset(obs.has_distance)
        if obs.n < 2:
            raise InputError(
                f"{source}: method 'distance' needs at least 2 alignments with distance_mm, "
                f"the session has {obs.n}; use --method joint or intersection"
            )
    elif obs.n < 2:
        raise InputError(
            f"{source}: method '{method}' needs at least 2 alignments, the session has {obs.n}"
        )
    return obs


def identify(
    session: Session,
    method: str = "joint",
    uncertainty: IdentificationUncertainty | None = None,
    source: str = "session",
) -> IdentificationResult:
    """Identify the launch-unit pose from a session.

    Parameters
    ----------
    session : Session
        Aligned units at several machine positions.
    method : {"joint", "intersection", "distance"}
    uncertainty : IdentificationUncertainty, optional
        Input uncertainties (defaults: the machine file's defaults).
    source : str
        Name of the session's file, for messages.

    Raises
    ------
    InputError
        Unknown method, or fewer alignments than the method needs.
    GeometryError
        The alignments do not determine the pose.
    """
    if method not in METHODS:
        raise InputError(f"unknown method '{method}' (choose {', '.join(METHODS)})")
    u = uncertainty or IdentificationUncertainty()
    all_obs = observations_from_session(session)
    obs = _minimum_alignments(method, all_obs, source)
    used = np.flatnonzero(all_obs.has_distance) if method == "distance" else np.arange(all_obs.n)
    estimated: tuple[str, ...] = ()
    reasons: dict[str, str] = {}
    if method == "joint":
        estimated, reasons = _select_offsets(obs, _intersection_estimate(obs), u)
    solution = _solve(method, obs, u, estimated)
    outlier = None
    if method == "joint":
        solution, dropped = _without_outlier(obs, u, estimated, solution)
        if dropped is not None:
            outlier = int(used[dropped])
            used = np.delete(used, dropped)
            obs = obs.subset(np.arange(obs.n) != dropped)
    return _assemble(method, all_obs, obs, used, solution, estimated, reasons, outlier, u)


def _covariance_scale(method: str, solution: _Solution) -> float:
    """Inflate the covariance when the joint fit's residuals exceed the stated uncertainties."""
    if method != "joint" or solution.dof <= 0:
        return 1.0
    reduced = solution.chi2 / solution.dof
    return reduced if reduced > 1.0 and _p_value(solution) < 0.05 else 1.0


def _beam_miss_rms_um(theta: Vec, c2: float, obs: Observations) -> float:
    """RMS distance of the beam points from the identified launch beams, um."""
    d = launch_direction(theta[3], obs.inputs[:, PHI1], obs.inputs[:, PHI2] + c2)
    e = obs.inputs[:, BX:DIST] - theta[:3]
    miss = e - np.sum(e * d, axis=1, keepdims=True) * d
    return float(np.sqrt(np.mean(np.sum(miss**2, axis=1))) * 1e3)


def _assemble(
    method: str,
    all_obs: Observations,
    obs: Observations,
    used: NDArray[np.intp],
    solution: _Solution,
    estimated: tuple[str, ...],
    reasons: dict[str, str],
    outlier: int | None,
    u: IdentificationUncertainty,
) -> IdentificationResult:
    scale = _covariance_scale(method, solution)
    cov = solution.propagation.covariance * scale
    per = solution.propagation.per_alignment
    position_var = np.trace(cov[:3, :3]) / scale
    reports = [AlignmentReport(i, 0.0, 0.0, float("nan"), excluded=True) for i in range(all_obs.n)]
    for k, i in enumerate(used):
        reports[i] = AlignmentReport(
            index=int(i),
            share_position=float(np.trace(per[k, :3, :3]) / position_var),
            share_gamma=float(per[k, 3, 3] / cov[3, 3] * scale),
            normalized_residual=float(solution.normalized[k]),
        )
    offsets = {name: float(solution.theta[4 + k]) for k, name in enumerate(estimated)}
    result = IdentificationResult(
        method=method,
        position_mm=solution.theta[:3].copy(),
        gamma_rad=float(wrap_angle(solution.theta[3])),
        covariance=cov[:4, :4],
        offsets_rad=offsets,
        offsets_covariance=cov[4:, 4:],
        offsets_not_estimated=reasons,
        residual_rms_um=_beam_miss_rms_um(solution.theta, offsets.get("c2", 0.0), obs),
        chi2=solution.chi2,
        dof=solution.dof,
        covariance_scale=scale,
        alignments=reports,
        outlier=outlier,
        converged=solution.fit.converged,
        iterations=solution.fit.iterations,
    )
    result.warnings = _geometry_warnings(result, all_obs, obs)
    return result


def _widest_beam_angle_deg(obs: Observations) -> float:
    d = _beam_from_receiver(obs)
    cosines = np.clip(d @ d.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def _geometry_warnings(
    result: IdentificationResult, all_obs: Observations, obs: Observations
) -> list[str]:
    warnings = []
    if not result.converged:
        warnings.append(
            f"the least-squares solver did not converge in {result.iterations} iterations: the"
            " pose may not be the best fit to the alignments; check them and identify again"
        )
    if result.outlier is not None:
        machine = all_obs.inputs[result.outlier, BX:DIST]
        warnings.append(
            f"alignment {result.outlier + 1} (beam point {np.round(machine, 1).tolist()} mm) was "
            "rejected as an outlier: it disagrees with the others far beyond the stated "
            "uncertainties; re-take it"
        )
    if obs.n < 4:
        warnings.append(
            f"only {obs.n} alignments: a bad alignment cannot be detected; "
            "take at least 4 (6-8 recommended)"
        )
    widest = _widest_beam_angle_deg(obs)
    if widest < _NEAR_PARALLEL_DEG:
        warnings.append(
            f"the beam lines are nearly parallel (widest angle between them {widest:.1f}°): "
            "choose identification positions that view the launch unit from different sides"
        )
    values, vectors = np.linalg.eigh(result.covariance[:3, :3])
    if np.sqrt(values[-1]) > _WEAK_POSITION_MM:
        direction_ = np.round(
            vectors[:, -1] * np.sign(vectors[np.argmax(np.abs(vectors[:, -1])), -1]), 2
        )
        warnings.append(
            f"weak geometry: the position is uncertain to ±{2 * np.sqrt(values[-1]):.3f} mm (k=2) "
            f"along {direction_.tolist()}; add alignments that view the launch unit "
            "across that direction"
        )
    if result.covariance_scale > 1.0:
        warnings.append(
            f"the residuals are {np.sqrt(result.covariance_scale):.1f}x larger than the stated "
            "uncertainties; the covariance was scaled up accordingly (check the machine file's "
            "uncertainty section and the alignments)"
        )
    return warnings
