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
(encoder noise, machine positioning, unit kinematics, zero offsets), not only
from the fit's scatter, and which alignment contributes what.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
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
    """Standard uncertainties (k = 1) of the inputs, in mm and rad."""

    encoder_rad: float = 10e-6
    machine_position_mm: float = 0.020
    unit_kinematics_mm: float = 0.010
    zero_offset_rad: float = 100e-6
    distance_mm: float = 0.020
    straightness_mm: float = 0.002

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
        )

    @property
    def position_mm(self) -> float:
        """Per-axis uncertainty of where the receiver cp really is at one alignment."""
        return float(np.hypot(self.machine_position_mm, self.straightness_mm))


# Columns of the per-alignment input array: reported angles (rad), beam point (mm), distance (mm).
PHI1, PHI2, PHI3, PHI4, BX, BY, BZ, DIST = range(8)
N_INPUTS = 8


@dataclass(frozen=True)
class Observations:
    """A session as arrays.

    Attributes
    ----------
    inputs : ndarray, shape (n, 8)
        Per alignment: reported ``phi1..phi4`` (rad), the beam point (mm) where
        the beam crosses the receiver (its cp minus the residual straightness),
        and the cp-to-cp distance (mm, 0 where unknown).
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
        rows.append([*a.launch_rad[:2], *a.receiver_rad[:2], *cp, distance])
    has_distance = np.array([a.distance_mm is not None for a in session.alignments], dtype=bool)
    inputs = np.array(rows, dtype=float).reshape(-1, N_INPUTS)
    return Observations(inputs, has_distance, session.spindle_angle_rad)


def input_sigmas(u: IdentificationUncertainty) -> Vec:
    """Standard uncertainty of each input column, shape (8,)."""
    p = u.position_mm
    return np.array([u.encoder_rad] * 4 + [p, p, p, u.distance_mm])


def systematic_sigmas(u: IdentificationUncertainty) -> Vec:
    """Standard uncertainty of the zero offsets and optical-centre offsets, shape (9,)."""
    return np.array([u.zero_offset_rad] * 3 + [u.unit_kinematics_mm] * 6)


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
# Every method is a residual function r(theta, inputs, systematics) -> (n, k): theta the
# parameters, inputs the (n, 8) array above and systematics (9,) what is common to all
# alignments and not estimated, nominally zero: the encoder zero offsets c2, c3, c4
# beyond those estimated, and the optical centres' offsets from the cps in the launch
# and receiver head frames (axes that do not intersect). The estimate minimises the
# (whitened) residuals; its covariance follows from the implicit-function theorem,
# d theta / d z = -(J^T J)^-1 J^T dr/dz, with the stated uncertainties of every z.

ResidualFn = Callable[[Vec, Vec, Vec], Vec]
C2, C3, C4 = 0, 1, 2
LAUNCH_CENTRE = slice(3, 6)
RECEIVER_CENTRE = slice(6, 9)
N_SYSTEMATICS = 9


def _head_to_mcs(azimuth: Vec, elevation: Vec, vector_head: Vec) -> Vec:
    """``Rz(az)·Ry(-el)·vector`` for arrays of angles (n,) and one vector (3,), (n, 3)."""
    if not np.any(vector_head):
        return np.zeros((len(azimuth), 3))
    ca, sa, ce, se = np.cos(azimuth), np.sin(azimuth), np.cos(elevation), np.sin(elevation)
    x_axis = np.stack([ca * ce, sa * ce, se], axis=-1)
    y_axis = np.stack([-sa, ca, np.zeros_like(ca)], axis=-1)
    z_axis = np.stack([-ca * se, -sa * se, ce], axis=-1)
    return vector_head[0] * x_axis + vector_head[1] * y_axis + vector_head[2] * z_axis


def _optical_points(
    theta: Vec, inputs: Vec, systematics: Vec, spindle_angle_rad: float
) -> tuple[Vec, Vec]:
    """Launch optical centre and beam point at the receiver, (n, 3) each, mm."""
    launch = theta[:3] + _head_to_mcs(
        theta[3] + inputs[:, PHI1], inputs[:, PHI2], systematics[LAUNCH_CENTRE]
    )
    receiver = inputs[:, BX:DIST] + _head_to_mcs(
        spindle_angle_rad + inputs[:, PHI3], inputs[:, PHI4], systematics[RECEIVER_CENTRE]
    )
    return launch, receiver


def _beam_from_receiver(inputs: Vec, systematics: Vec, spindle_angle_rad: float) -> Vec:
    """Beam direction launch -> receiver from the receiver encoders (true angles), (n, 3)."""
    return -receiver_axis(
        spindle_angle_rad, inputs[:, PHI3] + systematics[C3], inputs[:, PHI4] + systematics[C4]
    )


def _joint_residuals(estimated: tuple[str, ...], obs: Observations) -> ResidualFn:
    """Angle and distance residuals of the joint model, (n, 5)."""
    slots = [OFFSET_NAMES.index(name) for name in estimated]

    def residuals(theta: Vec, inputs: Vec, systematics: Vec) -> Vec:
        c = systematics[:3].copy()
        c[slots] += theta[4:]
        launch, receiver = _optical_points(theta, inputs, systematics, obs.spindle_angle_rad)
        e = receiver - launch
        azimuth, elevation = azimuth_elevation(e)
        r = np.empty((len(inputs), 5))
        r[:, 0] = wrap_angle(inputs[:, PHI1] - azimuth + theta[3])
        r[:, 1] = inputs[:, PHI2] + c[C2] - elevation
        r[:, 2] = wrap_angle(inputs[:, PHI3] + c[C3] - azimuth - np.pi + obs.spindle_angle_rad)
        r[:, 3] = inputs[:, PHI4] + c[C4] + elevation
        r[:, 4] = np.where(obs.has_distance, inputs[:, DIST] - np.linalg.norm(e, axis=1), 0.0)
        return r

    return residuals


def _intersection_residuals(obs: Observations) -> ResidualFn:
    """Perpendicular miss of the launch cp from each receiver beam line, and gamma, (n, 4)."""

    def residuals(theta: Vec, inputs: Vec, systematics: Vec) -> Vec:
        d = _beam_from_receiver(inputs, systematics, obs.spindle_angle_rad)
        launch, receiver = _optical_points(theta, inputs, systematics, obs.spindle_angle_rad)
        miss = launch - receiver
        perpendicular = miss - np.sum(miss * d, axis=1, keepdims=True) * d
        azimuth, _ = azimuth_elevation(d)
        gamma = wrap_angle(azimuth - inputs[:, PHI1] - theta[3])
        return np.column_stack([perpendicular, gamma])

    return residuals


def _distance_residuals(obs: Observations) -> ResidualFn:
    """Both chains of the closed loop with known distances, mm, (n, 6)."""

    def residuals(theta: Vec, inputs: Vec, systematics: Vec) -> Vec:
        length = inputs[:, DIST, None]
        launch, receiver = _optical_points(theta, inputs, systematics, obs.spindle_angle_rad)
        d_receiver = _beam_from_receiver(inputs, systematics, obs.spindle_angle_rad)
        d_launch = launch_direction(theta[3], inputs[:, PHI1], inputs[:, PHI2] + systematics[C2])
        receiver_chain = receiver - length * d_receiver - launch
        launch_chain = launch + length * d_launch - receiver
        return np.column_stack([receiver_chain, launch_chain])

    return residuals


# ------------------------------------------------------------------ numerical machinery

_THETA_STEP = np.array([1e-4, 1e-4, 1e-4, 1e-7, 1e-7, 1e-7, 1e-7])
_INPUT_STEP = np.array([1e-7, 1e-7, 1e-7, 1e-7, 1e-4, 1e-4, 1e-4, 1e-4])
_SYSTEMATIC_STEP = np.array([1e-7] * 3 + [1e-4] * 6)
_NO_SYSTEMATICS = np.zeros(N_SYSTEMATICS)


def _central_difference(f: Callable[[Vec], Vec], x: Vec, steps: Vec) -> Vec:
    """Derivatives of f (any shape) w.r.t. each entry of the vector x, stacked last."""
    columns = []
    for j, step in enumerate(steps):
        h = np.zeros_like(x)
        h[j] = step
        columns.append((f(x + h) - f(x - h)) / (2 * step))
    return np.stack(columns, axis=-1)


def _theta_jacobian(fn: ResidualFn, theta: Vec, inputs: Vec) -> Vec:
    """d r / d theta, (n, k, p)."""
    return _central_difference(
        lambda t: fn(t, inputs, _NO_SYSTEMATICS), theta, _THETA_STEP[: len(theta)]
    )


def _input_jacobian(fn: ResidualFn, theta: Vec, inputs: Vec) -> Vec:
    """d r_i / d inputs_i, (n, k, 8).

    Alignment i's residuals depend only on its own inputs, so one column of
    every alignment is differentiated at once.
    """
    per_input = []
    for j in range(N_INPUTS):
        h = np.zeros_like(inputs)
        h[:, j] = _INPUT_STEP[j]
        plus = fn(theta, inputs + h, _NO_SYSTEMATICS)
        minus = fn(theta, inputs - h, _NO_SYSTEMATICS)
        per_input.append((plus - minus) / (2 * _INPUT_STEP[j]))
    return np.stack(per_input, axis=-1)


def _systematic_jacobian(fn: ResidualFn, theta: Vec, inputs: Vec) -> Vec:
    """d r / d systematics, (n, k, 9)."""
    return _central_difference(lambda z: fn(theta, inputs, z), _NO_SYSTEMATICS, _SYSTEMATIC_STEP)


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
class _Fit:
    theta: Vec
    jacobian: Vec  # whitened, (n, k, p)
    residuals: Vec  # whitened, (n, k)


def _gauss_newton(
    fn: ResidualFn, theta0: Vec, inputs: Vec, weights: Vec, max_iterations: int = 60
) -> _Fit:
    """Minimise sum |W_i r_i|^2 by Gauss-Newton with step halving."""

    def whitened(theta: Vec) -> Vec:
        return np.einsum("nij,nj->ni", weights, fn(theta, inputs, _NO_SYSTEMATICS))

    theta = np.asarray(theta0, dtype=float).copy()
    r = whitened(theta)
    cost = float(np.sum(r**2))
    for _ in range(max_iterations):
        j = np.einsum("nij,njp->nip", weights, _theta_jacobian(fn, theta, inputs))
        jf = j.reshape(-1, len(theta))
        step, *_ = np.linalg.lstsq(jf, -r.ravel(), rcond=None)
        for _ in range(30):
            candidate = theta + step
            r_new = whitened(candidate)
            cost_new = float(np.sum(r_new**2))
            if cost_new <= cost * (1 + 1e-12) or cost < 1e-30:
                break
            step = step / 2
        theta, r, converged = (
            candidate,
            r_new,
            np.all(np.abs(step) <= 1e-13 * np.maximum(1, np.abs(theta))),
        )
        cost = cost_new
        if converged:
            break
    j = np.einsum("nij,njp->nip", weights, _theta_jacobian(fn, theta, inputs))
    return _Fit(theta, j, r)


@dataclass
class _Propagation:
    covariance: Vec  # (p, p), all inputs and systematics
    per_alignment: Vec  # (n, p, p)
    from_systematics: Vec  # (p, p)


def _propagate(
    fn: ResidualFn,
    fit: _Fit,
    inputs: Vec,
    weights: Vec,
    u: IdentificationUncertainty,
    estimated: tuple[str, ...] = (),
) -> _Propagation:
    """Covariance of theta from the input and systematic uncertainties (implicit function).

    Offsets in ``estimated`` are parameters, not systematics, and carry no prior.
    """
    p = len(fit.theta)
    jz = _input_jacobian(fn, fit.theta, inputs)
    jc = _systematic_jacobian(fn, fit.theta, inputs)
    jf = fit.jacobian.reshape(-1, p)
    hessian_inv = np.linalg.pinv(jf.T @ jf)
    # G_i = -H^-1 J_i^T W_i dr_i/dz_i, per alignment (p, 8)
    g_inputs = -np.einsum("pq,nkq,nkl,nlj->npj", hessian_inv, fit.jacobian, weights, jz)
    sigma = input_sigmas(u)
    per_alignment = np.einsum("npj,j,nqj->npq", g_inputs, sigma**2, g_inputs)
    g_systematic = -hessian_inv @ np.einsum("nkq,nkl,nlj->qj", fit.jacobian, weights, jc)
    sigma_systematic = systematic_sigmas(u)
    sigma_systematic[[OFFSET_NAMES.index(name) for name in estimated]] = 0.0
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
    d = _beam_from_receiver(obs.inputs, _NO_SYSTEMATICS, obs.spindle_angle_rad)
    position = _nearest_point_to_lines(obs.inputs[:, BX:DIST], d)
    azimuth, _ = azimuth_elevation(d)
    return np.append(position, circular_mean(azimuth - obs.inputs[:, PHI1]))


def _distance_estimate(obs: Observations, weights: Vec, start: Vec) -> _Fit:
    return _gauss_newton(_distance_residuals(obs), start, obs.inputs, weights)


def _unit_weights(n: int, k: int) -> Vec:
    return np.broadcast_to(np.eye(k), (n, k, k)).copy()


def _distance_start(obs: Observations) -> Vec:
    d = _beam_from_receiver(obs.inputs, _NO_SYSTEMATICS, obs.spindle_angle_rad)
    launch_cps = obs.inputs[:, BX:DIST] - obs.inputs[:, DIST, None] * d
    position = launch_cps.mean(axis=0)
    azimuth, _ = azimuth_elevation(obs.inputs[:, BX:DIST] - position)
    return np.append(position, circular_mean(azimuth - obs.inputs[:, PHI1]))


def _joint_weights(
    fn: ResidualFn, theta: Vec, obs: Observations, u: IdentificationUncertainty
) -> Vec:
    jz = _input_jacobian(fn, theta, obs.inputs)
    return _whitening(_residual_covariances(jz, input_sigmas(u)))


def _information(fn: ResidualFn, theta: Vec, inputs: Vec, weights: Vec) -> Vec:
    """Whitened normal matrix J^T J, (p, p)."""
    j = np.einsum("nij,njp->nip", weights, _theta_jacobian(fn, theta, inputs))
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
    weights = _joint_weights(_joint_residuals((), obs), start, obs, u)
    values, _ = _relative_conditioning(
        _information(_joint_residuals((), obs), start, obs.inputs, weights)
    )
    if values[0] < 1e-10 * values[-1]:
        raise GeometryError(
            "degenerate geometry: these alignments do not determine the launch pose (rank test); "
            "align at machine positions spread across X, Y and Z"
        )
    candidates = list(OFFSET_NAMES)
    reasons: dict[str, str] = {}
    while candidates:
        theta = np.concatenate([start, np.zeros(len(candidates))])
        fn = _joint_residuals(tuple(candidates), obs)
        information = _information(fn, theta, obs.inputs, weights)
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


def _normalized_residuals(
    fn: ResidualFn, theta: Vec, obs: Observations, u: IdentificationUncertainty
) -> tuple[Vec, Vec]:
    """Per alignment: residual quadratic form with its predicted covariance, and its rank."""
    r = fn(theta, obs.inputs, _NO_SYSTEMATICS)
    jz = _input_jacobian(fn, theta, obs.inputs)
    cov = _residual_covariances(jz, input_sigmas(u))
    pinv = np.linalg.pinv(cov, rcond=1e-10, hermitian=True)
    quadratic = np.einsum("ni,nij,nj->n", r, pinv, r)
    rank = np.linalg.matrix_rank(cov, tol=None, hermitian=True)
    return quadratic, rank


def _solve(
    method: str, obs: Observations, u: IdentificationUncertainty, estimated: tuple[str, ...]
) -> _Solution:
    if method == "intersection":
        fn = _intersection_residuals(obs)
        fit = _Fit(_intersection_estimate(obs), np.empty(0), np.empty(0))
        weights = _unit_weights(obs.n, 4)
        fit.jacobian = _theta_jacobian(fn, fit.theta, obs.inputs)
    elif method == "distance":
        fn = _distance_residuals(obs)
        weights = _unit_weights(obs.n, 6)
        fit = _distance_estimate(obs, weights, _distance_start(obs))
    else:
        fn = _joint_residuals(estimated, obs)
        theta0 = np.concatenate([_intersection_estimate(obs), np.zeros(len(estimated))])
        weights = _joint_weights(fn, theta0, obs, u)
        fit = _gauss_newton(fn, theta0, obs.inputs, weights)
    propagation = _propagate(fn, fit, obs.inputs, weights, u, estimated)
    quadratic, rank = _normalized_residuals(fn, fit.theta, obs, u)
    dof = int(rank.sum()) - len(fit.theta)
    return _Solution(
        fit.theta,
        propagation,
        np.sqrt(quadratic / np.maximum(rank, 1)),
        float(quadratic.sum()),
        dof,
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
    used: Vec,
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
    )
    result.warnings = _geometry_warnings(result, all_obs, obs)
    return result


def _widest_beam_angle_deg(obs: Observations) -> float:
    d = _beam_from_receiver(obs.inputs, _NO_SYSTEMATICS, obs.spindle_angle_rad)
    cosines = np.clip(d @ d.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


def _geometry_warnings(
    result: IdentificationResult, all_obs: Observations, obs: Observations
) -> list[str]:
    warnings = []
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
