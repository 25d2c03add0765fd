"""Beam envelope: where the beam meets the receiver, given the pose's uncertainty.

The units are commanded to fixed reported angles computed from the identified
pose. The true pose and encoder zero offsets differ from the identified ones
within their covariance, so the real beam leaves the true launch cp in a
slightly different direction and the receiver looks slightly askew. This
module propagates the covariance of the parameters
``q = (x mm, y mm, z mm, gamma rad, c2 rad, c3 rad, c4 rad)`` through the
Jacobian of

- the receiver cp's position relative to the real beam at every target
  (components along the line frame's ``v`` and ``w``, mm), and
- the receiver's angular mismatch, ``u_receiver + d_beam`` projected on ``v``
  and ``w`` (rad; zero when the units are aligned),

and bounds them by the 95 % ellipse: nominal value plus
``K95 · sqrt(largest eigenvalue)`` for the straightness radius, nominal plus
``K95 · sigma`` per component for the angles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from xmalign.geometry import Vec
from xmalign.kinematics import launch_direction, receiver_axis

#: 95 % quantile of a two-dimensional normal's radius, sqrt(chi2_2(0.95)).
K95 = math.sqrt(-2.0 * math.log(0.05))
#: Parameter names of the covariance, in order.
PARAMETERS = ("x_mm", "y_mm", "z_mm", "gamma_rad", "c2_rad", "c3_rad", "c4_rad")
#: Central-difference steps for the parameters (mm, then rad).
_STEPS = np.array([1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7, 1e-7])


@dataclass(frozen=True)
class BeamEnvelope:
    """Predicted beam at the receiver for one line (µm, µrad).

    Attributes
    ----------
    lateral_nominal_um : ndarray, shape (M,)
        Receiver cp's distance from the beam for the identified pose (non-zero
        only for a line that cannot pass through the launch cp).
    lateral_95_um : ndarray, shape (M,)
        Radius of the 95 % envelope of that distance at every target.
    angle_nominal_urad : ndarray, shape (2,)
        Nominal angular mismatch about ``v``-, ``w``-components.
    angle_95_urad : float
        Largest 95 % bound of the two angular components.
    straightness_limit_um, angle_limit_urad : float
        Instrument range minus the allowance for the axis's own errors.
    """

    lateral_nominal_um: Vec
    lateral_95_um: Vec
    angle_nominal_urad: Vec
    angle_95_urad: float
    straightness_limit_um: float
    angle_limit_urad: float

    @property
    def straightness_margin_um(self) -> float:
        """Limit minus the worst 95 % radius; negative means the beam may be lost."""
        return self.straightness_limit_um - float(np.max(self.lateral_95_um))

    @property
    def angle_margin_urad(self) -> float:
        return self.angle_limit_urad - self.angle_95_urad

    @property
    def nominal_fits(self) -> bool:
        """True when the identified pose itself keeps the beam inside the limits."""
        return (
            float(np.max(self.lateral_nominal_um)) <= self.straightness_limit_um
            and float(np.max(np.abs(self.angle_nominal_urad))) <= self.angle_limit_urad
        )

    @property
    def within(self) -> bool:
        """True when the whole 95 % envelope stays inside the limits."""
        return self.straightness_margin_um >= 0.0 and self.angle_margin_urad >= 0.0


def _beam_at_receiver(
    q: Vec,
    receiver_cp_mm: Vec,
    launch_rad: Vec,
    receiver_rad: Vec,
    spindle_angle_rad: float,
    frame_vw: Vec,
) -> Vec:
    """Lateral (M, 2) mm and angular (2,) rad mismatch for true parameters ``q``, flattened."""
    d = launch_direction(q[3], launch_rad[0], launch_rad[1] + q[4])
    axis = receiver_axis(spindle_angle_rad, receiver_rad[0] + q[5], receiver_rad[1] + q[6])
    relative = receiver_cp_mm - q[:3]
    lateral = relative - np.outer(relative @ d, d)
    return np.concatenate([(lateral @ frame_vw.T).ravel(), frame_vw @ (axis + d)])


def predict_envelope(
    q_mm_rad: Vec,
    covariance: Vec,
    receiver_cp_mm: Vec,
    launch_rad: Vec,
    receiver_rad: Vec,
    spindle_angle_rad: float,
    frame: Vec,
    straightness_limit_um: float,
    angle_limit_urad: float,
) -> BeamEnvelope:
    """Propagate the parameter covariance to the beam at every target of a line.

    Parameters
    ----------
    q_mm_rad : ndarray, shape (7,)
        Identified ``(x, y, z, gamma, c2, c3, c4)`` (mm, rad).
    covariance : ndarray, shape (7, 7)
        Covariance of ``q`` (mm², mm·rad, rad²), including the units' positioning noise.
    receiver_cp_mm : ndarray, shape (M, 3)
        Receiver cp at the targets (MCS).
    launch_rad, receiver_rad : ndarray, shapes (2,) and (3,)
        Reported angles commanded for the line.
    spindle_angle_rad : float
        Spindle angle ``gamma_R``.
    frame : ndarray, shape (3, 3)
        Line frame rows ``u, v, w``.
    straightness_limit_um, angle_limit_urad : float
        Range minus allowance the envelope must stay inside.
    """
    args = (
        np.asarray(receiver_cp_mm, dtype=float),
        launch_rad,
        receiver_rad,
        spindle_angle_rad,
        frame[1:],
    )
    q0 = np.asarray(q_mm_rad, dtype=float)
    nominal = _beam_at_receiver(q0, *args)
    jacobian = np.empty((nominal.size, q0.size))
    for k, step in enumerate(_STEPS):
        dq = np.zeros_like(q0)
        dq[k] = step
        jacobian[:, k] = (_beam_at_receiver(q0 + dq, *args) - _beam_at_receiver(q0 - dq, *args)) / (
            2.0 * step
        )
    m = len(receiver_cp_mm)
    lateral_jac = jacobian[: 2 * m].reshape(m, 2, -1)
    lateral_cov = np.einsum("mik,kl,mjl->mij", lateral_jac, covariance, lateral_jac)
    lateral_sigma_max = np.sqrt(np.maximum(np.linalg.eigvalsh(lateral_cov)[:, -1], 0.0))
    lateral_nominal = np.linalg.norm(nominal[: 2 * m].reshape(m, 2), axis=1)
    angle_jac = jacobian[2 * m :]
    angle_sigma = np.sqrt(np.maximum(np.diag(angle_jac @ covariance @ angle_jac.T), 0.0))
    angle_nominal = nominal[2 * m :]
    return BeamEnvelope(
        lateral_nominal_um=1e3 * lateral_nominal,
        lateral_95_um=1e3 * (lateral_nominal + K95 * lateral_sigma_max),
        angle_nominal_urad=1e6 * angle_nominal,
        angle_95_urad=float(1e6 * np.max(np.abs(angle_nominal) + K95 * angle_sigma)),
        straightness_limit_um=straightness_limit_um,
        angle_limit_urad=angle_limit_urad,
    )
