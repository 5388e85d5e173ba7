"""Composition, chains, inversion and points of uncertain poses (Hoff & Vincent eqs. 6-7)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import InputError
from coreg_ros.core.quaternion import to_matrix as _rotation
from coreg_ros.core.so3 import skew
from coreg_ros.core.types import CalibrationResult, UncertainPose
from coreg_ros.core.uncertainty._unknown import (
    _cov_or_zero,
    _known_part,
    _mark_unknown,
    _symmetric,
    _unknown_mask,
)
import numpy as np


def compose_jacobians(p_ab, q_ab, p_bc) -> tuple[np.ndarray, np.ndarray]:
    r"""
    Jacobians of ``T_ac = T_ab · T_bc`` with respect to both operands (Hoff eq. 7).

    With ``p_ac = p_ab + R_ab p_bc`` and ``R_ac = R_ab R_bc``, perturbing each operand by its
    ROS-layout δ gives to first order

    .. math::

        δ_{ac} = \begin{pmatrix} I & -[R_{ab} p_{bc}]_× \\ 0 & I \end{pmatrix} δ_{ab}
               + \begin{pmatrix} R_{ab} & 0 \\ 0 & R_{ab} \end{pmatrix} δ_{bc}.

    Parameters
    ----------
    p_ab : array_like, shape (..., 3)
        Position of frame b in frame a, m.
    q_ab : array_like, shape (..., 4)
        Orientation of b in a (w, x, y, z).
    p_bc : array_like, shape (..., 3)
        Position of frame c in frame b, m.

    Returns
    -------
    J_ab, J_bc : ndarray, shape (..., 6, 6)

    """
    R = _rotation(q_ab)
    lever = np.einsum('...ij,...j->...i', R, np.asarray(p_bc, dtype=float))
    shape = lever.shape[:-1]
    R = np.broadcast_to(R, shape + (3, 3))
    J_ab = np.broadcast_to(np.eye(6), shape + (6, 6)).copy()
    J_ab[..., 0:3, 3:6] = -skew(lever)
    J_bc = np.zeros(shape + (6, 6))
    J_bc[..., 0:3, 0:3] = R
    J_bc[..., 3:6, 3:6] = R
    return J_ab, J_bc


def compose_arrays(p_ab, q_ab, cov_ab, p_bc, q_bc, cov_bc, cross_cov=None):
    """
    Compose uncertain poses ``T_ac = T_ab · T_bc`` with first-order covariance (Hoff eqs. 6-7).

    Parameters
    ----------
    p_ab, q_ab : array_like, shapes (..., 3), (..., 4)
        Pose of frame b in frame a (m; w, x, y, z).
    cov_ab : array_like, shape (..., 6, 6)
        Its covariance, ROS layout about frame a's axes.
    p_bc, q_bc : array_like, shapes (..., 3), (..., 4)
        Pose of frame c in frame b.
    cov_bc : array_like, shape (..., 6, 6)
        Its covariance, ROS layout about frame b's axes.
    cross_cov : array_like, shape (..., 6, 6), optional
        ``E[δ_ab δ_bcᵀ]`` when the operands are correlated (e.g. T0 and T1 of one calibration);
        zero by default.

    Returns
    -------
    p_ac : ndarray, shape (..., 3)
    q_ac : ndarray, shape (..., 4)
        Canonical (w >= 0).
    cov_ac : ndarray, shape (..., 6, 6)
        ROS layout about frame a's axes; UNKNOWN where an unknown input component enters.

    """
    p_ab = np.asarray(p_ab, dtype=float)
    p_bc = np.asarray(p_bc, dtype=float)
    R = _rotation(q_ab)
    p_ac = p_ab + np.einsum('...ij,...j->...i', R, p_bc)
    q_ac = quat.canonical(quat.multiply(q_ab, q_bc))
    J_ab, J_bc = compose_jacobians(p_ab, q_ab, p_bc)
    cab = np.asarray(cov_ab, dtype=float)
    cbc = np.asarray(cov_bc, dtype=float)
    c_ab, c_bc = _known_part(cab), _known_part(cbc)
    cov = J_ab @ c_ab @ np.swapaxes(J_ab, -1, -2) + J_bc @ c_bc @ np.swapaxes(J_bc, -1, -2)
    if cross_cov is not None:
        x = J_ab @ np.asarray(cross_cov, dtype=float) @ np.swapaxes(J_bc, -1, -2)
        cov = cov + x + np.swapaxes(x, -1, -2)
    cov = _mark_unknown(_symmetric(cov), (J_ab, J_bc),
                        (_unknown_mask(cab), _unknown_mask(cbc)))
    return p_ac, q_ac, cov


def compose(a: UncertainPose, b: UncertainPose,
            cross_cov: Optional[np.ndarray] = None) -> UncertainPose:
    """
    Uncertain ``T_ac = T_ab · T_bc`` (Hoff eqs. 6-7); see ``compose_arrays``.

    Parameters
    ----------
    a : UncertainPose
        T_ab, pose of frame b in frame a; covariance None means exactly known.
    b : UncertainPose
        T_bc, pose of frame c in frame b.
    cross_cov : ndarray, shape (6, 6), optional
        ``E[δ_a δ_bᵀ]``.

    Returns
    -------
    UncertainPose
        T_ac, covariance about frame a's axes (None if neither operand has one).

    """
    p, q, c = compose_arrays(a.position, a.quat_wxyz, _cov_or_zero(a), b.position, b.quat_wxyz,
                             _cov_or_zero(b), cross_cov)
    none = a.covariance is None and b.covariance is None
    return UncertainPose(p, q, None if none else c)


def chain(poses: Sequence[UncertainPose], joint_cov: Optional[np.ndarray] = None
          ) -> UncertainPose:
    """
    Uncertain product ``T_1 · T_2 ⋯ T_k`` with a joint covariance of all operands.

    Parameters
    ----------
    poses : sequence of UncertainPose
        The operands, left to right.
    joint_cov : ndarray, shape (6k, 6k), optional
        Joint covariance of the operands' δ (ROS layout each). Default: block diagonal from the
        operands' own covariances (None counts as exactly known).

    Returns
    -------
    UncertainPose
        Covariance ``Σ_ij J_i C_ij J_jᵀ`` about the first frame's axes (Hoff eq. 7 extended to
        correlated operands).

    """
    k = len(poses)
    if k == 0:
        raise InputError('chain needs at least one pose')
    if joint_cov is None:
        joint_cov = np.zeros((6 * k, 6 * k))
        for i, pose in enumerate(poses):
            joint_cov[6 * i:6 * i + 6, 6 * i:6 * i + 6] = _cov_or_zero(pose)
    joint_cov = np.asarray(joint_cov, dtype=float)
    if joint_cov.shape != (6 * k, 6 * k):
        raise InputError(f'joint_cov must be ({6 * k}, {6 * k}) for {k} poses, got '
                         f'{joint_cov.shape}')
    # J of the running product with respect to every operand, updated left to right.
    p = np.asarray(poses[0].position, dtype=float)
    q = np.asarray(poses[0].quat_wxyz, dtype=float)
    J = np.zeros((6, 6 * k))
    J[:, 0:6] = np.eye(6)
    for i in range(1, k):
        J_left, J_right = compose_jacobians(p, q, poses[i].position)
        J = J_left @ J
        J[:, 6 * i:6 * i + 6] = J_right
        p = p + _rotation(q) @ np.asarray(poses[i].position, dtype=float)
        q = quat.multiply(q, poses[i].quat_wxyz)
    known = _known_part(joint_cov)
    cov = _symmetric(J @ known @ J.T)
    cov = _mark_unknown(cov, (J,), (_unknown_mask(joint_cov),))
    return UncertainPose(p, quat.canonical(q), cov)


def through_calibration_arrays(result: CalibrationResult, position_a, quat_a, cov_a):
    """
    Device A's tool poses carried into B's base frame: ``T0 · T_A · T1`` with its covariance.

    The calibration's joint covariance of (T0, T1) (``result.cov_joint``, correlated) and A's
    measurement noise (independent of it) both enter (Hoff eq. 7).

    Parameters
    ----------
    result : CalibrationResult
        T0 = T_bbase_abase, T1 = T_atool_bmarker and ``cov_joint`` (12×12; None: exact).
    position_a : array_like, shape (..., 3)
        A's tool position in A's base frame, m.
    quat_a : array_like, shape (..., 4)
        A's tool orientation in A's base frame (w, x, y, z).
    cov_a : array_like, shape (6, 6) or (..., 6, 6)
        A's measurement noise, ROS layout about A's base axes.

    Returns
    -------
    p_b : ndarray, shape (..., 3)
        Predicted position of B's marker in B's base frame, m.
    q_b : ndarray, shape (..., 4)
        Predicted orientation of B's marker in B's base frame.
    cov_b : ndarray, shape (..., 6, 6)
        ROS layout about B's base axes; rotation UNKNOWN for models that do not estimate q1.

    """
    t0, t1 = result.base_to_base, result.tool_to_marker
    pa = np.asarray(position_a, dtype=float)
    qa = np.asarray(quat_a, dtype=float)
    # a held direction (a restricted rig) changes no prediction: its unknown variance stays out
    # (``CalibrationResult.cov_for_propagation``; a ``FusionCalibration`` holds that already)
    joint = getattr(result, 'cov_for_propagation', result.cov_joint)
    joint = np.zeros((12, 12)) if joint is None else np.asarray(joint, dtype=float)
    shape = pa.shape[:-1]
    # X = T0 · T_A
    J0_x, Ja_x = compose_jacobians(t0.position, t0.quat_wxyz, pa)
    R0 = _rotation(t0.quat_wxyz)
    px = t0.position + pa @ R0.T
    qx = quat.multiply(t0.quat_wxyz, qa)
    # Y = X · T1
    Jx_y, J1_y = compose_jacobians(px, qx, np.broadcast_to(t1.position, shape + (3,)))
    J0 = Jx_y @ J0_x
    Ja = Jx_y @ Ja_x
    J01 = np.concatenate([np.broadcast_to(J0, shape + (6, 6)), J1_y], axis=-1)
    ca = np.broadcast_to(np.asarray(cov_a, dtype=float), shape + (6, 6))
    cov = (J01 @ _known_part(joint) @ np.swapaxes(J01, -1, -2)
           + Ja @ _known_part(ca) @ np.swapaxes(Ja, -1, -2))
    cov = _mark_unknown(_symmetric(cov), (J01, Ja), (_unknown_mask(joint), _unknown_mask(ca)))
    p_b = px + np.einsum('...ij,j->...i', _rotation(qx), np.asarray(t1.position, dtype=float))
    q_b = quat.canonical(quat.multiply(qx, t1.quat_wxyz))
    return p_b, q_b, cov


def through_calibration(result: CalibrationResult, pose_a: UncertainPose) -> UncertainPose:
    """
    One A measurement carried into B's base frame (``T0 · T_A · T1``), uncertainty included.

    Parameters
    ----------
    result : CalibrationResult
        The calibration (T0, T1 and their covariance).
    pose_a : UncertainPose
        A's tool pose in A's base frame with A's noise covariance (None: exact).

    Returns
    -------
    UncertainPose
        Pose of B's marker in B's base frame as A and the calibration predict it.

    """
    p, q, c = through_calibration_arrays(result, pose_a.position, pose_a.quat_wxyz,
                                         _cov_or_zero(pose_a))
    return UncertainPose(p, q, c)


# --------------------------------------------------------------------------- inversion

def inverse_jacobian(p, q) -> np.ndarray:
    r"""
    Jacobian of ``T⁻¹ = (-Rᵀ p, Rᵀ)`` with respect to T's δ (Hoff eq. 6).

    .. math::

        δ_{inv} = -\begin{pmatrix} R^T & R^T [p]_× \\ 0 & R^T \end{pmatrix} δ

    Parameters
    ----------
    p : array_like, shape (..., 3)
        Position of T, m.
    q : array_like, shape (..., 4)
        Orientation of T (w, x, y, z).

    Returns
    -------
    ndarray, shape (..., 6, 6)

    """
    Rt = np.swapaxes(_rotation(q), -1, -2)
    J = np.zeros(Rt.shape[:-2] + (6, 6))
    J[..., 0:3, 0:3] = -Rt
    J[..., 0:3, 3:6] = -Rt @ skew(np.asarray(p, dtype=float))
    J[..., 3:6, 3:6] = -Rt
    return J


def invert_arrays(p, q, cov):
    """
    Invert uncertain poses: T_ba from T_ab with first-order covariance.

    Parameters
    ----------
    p, q : array_like, shapes (..., 3), (..., 4)
        T_ab (pose of b in a).
    cov : array_like, shape (..., 6, 6)
        About a's axes.

    Returns
    -------
    p_ba, q_ba, cov_ba
        Pose of a in b; covariance about b's axes.

    """
    p = np.asarray(p, dtype=float)
    Rt = np.swapaxes(_rotation(q), -1, -2)
    p_inv = -np.einsum('...ij,...j->...i', Rt, p)
    q_inv = quat.canonical(quat.conjugate(q))
    J = inverse_jacobian(p, q)
    c = np.asarray(cov, dtype=float)
    out = _symmetric(J @ _known_part(c) @ np.swapaxes(J, -1, -2))
    return p_inv, q_inv, _mark_unknown(out, (J,), (_unknown_mask(c),))


def invert(pose: UncertainPose) -> UncertainPose:
    """Uncertain inverse of a pose (T_ab → T_ba); see ``invert_arrays``."""
    p, q, c = invert_arrays(pose.position, pose.quat_wxyz, _cov_or_zero(pose))
    return UncertainPose(p, q, None if pose.covariance is None else c)


# --------------------------------------------------------------------------- points

def propagate_point_arrays(p, q, cov, point, point_cov=None):
    """
    Express a point given in a frame in the parent frame, with its 3×3 covariance (§3.3).

    ``y = p + R x``; ``δy = δp - [R x]× δθ + R δx``: the rotational uncertainty of the frame
    grows into a positional one proportional to the lever arm |x| (Hoff's ΔP = d Δθ).

    Parameters
    ----------
    p, q : array_like, shapes (..., 3), (..., 4)
        Pose of the frame in the parent frame.
    cov : array_like, shape (..., 6, 6)
        Its covariance, ROS layout about the parent's axes.
    point : array_like, shape (..., 3)
        The point in the frame, m (e.g. a stylus tip 15 cm from the tracked frame).
    point_cov : array_like, shape (..., 3, 3), optional
        Uncertainty of the point itself, in the frame's axes; zero by default.

    Returns
    -------
    y : ndarray, shape (..., 3)
        The point in the parent frame, m.
    cov_y : ndarray, shape (..., 3, 3)
        m²; UNKNOWN on the diagonal where an unknown pose component enters.

    """
    R = _rotation(q)
    x = np.asarray(point, dtype=float)
    rx = np.einsum('...ij,...j->...i', R, x)
    y = np.asarray(p, dtype=float) + rx
    J = np.zeros(rx.shape[:-1] + (3, 6))
    J[..., 0:3] = np.eye(3)
    J[..., 3:6] = -skew(rx)
    c = np.asarray(cov, dtype=float)
    out = J @ _known_part(c) @ np.swapaxes(J, -1, -2)
    if point_cov is not None:
        out = out + R @ np.asarray(point_cov, dtype=float) @ np.swapaxes(R, -1, -2)
    return y, _mark_unknown(_symmetric(out), (J,), (_unknown_mask(c),))


def propagate_point(pose: UncertainPose, point, point_cov=None) -> tuple[np.ndarray, np.ndarray]:
    """
    Express a point given in the pose's frame in the parent frame, with covariance (m, m²).

    See ``propagate_point_arrays``; a pose without covariance gives only the point's own.
    """
    return propagate_point_arrays(pose.position, pose.quat_wxyz, _cov_or_zero(pose), point,
                                  point_cov)
