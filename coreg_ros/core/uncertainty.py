"""
First-order algebra of uncertain poses: composition, inversion, points, fusion, ellipsoids, cones.

Every covariance follows DESIGN.md §3 (``geometry_msgs/PoseWithCovariance``): 6×6 over
(x, y, z, δθx, δθy, δθz), the truth being ``p_true = p + δp`` and
``R_true = Exp(δθ) · R`` about the fixed axes of the frame the pose is expressed in. A negative
diagonal entry marks a component that is not known (``covariance.UNKNOWN``); it is carried as
infinite variance: every output that depends on it is marked unknown too, and fusion gives it
zero information.

Functions on arrays (``*_arrays``) are vectorised over leading axes, for Monte Carlo checks and
per-sample streams; the ``UncertainPose`` functions wrap them for one pose.

Method (Hoff & Vincent 2000): the covariance of a function y = g(x, w) of two uncertain
operands is ``C_y = J_x C_x J_xᵀ + J_w C_w J_wᵀ`` (eqs. 6-7; with their cross-covariance when
the operands are correlated, e.g. the two transforms of one calibration); the positional
uncertainty is the ellipsoid ``{z : (z - z̄)ᵀ C_z⁻¹ (z - z̄) ≤ k²}`` of the upper-left 3×3 block
(eqs. 8-9, §3.3); the rotational uncertainty is shown as a cone about each axis a = R e, whose
covariance ``C_a = [a]× C_θ [a]×ᵀ`` has rank 2 (§3.3, Fig. 1); two estimates of one pose are
fused by inverse-covariance weighting on the tangent space (§3.4).

References
----------
Hoff, W., Vincent, T. (2000). Analysis of head pose accuracy in augmented reality. IEEE TVCG
6(4), 319-334.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import stats

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import InputError
from coreg_ros.core.types import CalibrationResult, UncertainPose

#: Diagonal value marking an unknown component (same as ``covariance.UNKNOWN``).
UNKNOWN = -1.0
#: Below this absolute value a Jacobian entry does not propagate an unknown component.
_ZERO = 1e-12


# --------------------------------------------------------------------------- small algebra

def skew(v: np.ndarray) -> np.ndarray:
    """
    Cross-product matrix ``[v]×`` with ``[v]× u = v × u``.

    Parameters
    ----------
    v : array_like, shape (..., 3)

    Returns
    -------
    ndarray, shape (..., 3, 3)

    """
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """
    Left Jacobian of SO(3): ``Exp(φ + δ) ≈ Exp(J_l(φ) δ) · Exp(φ)``.

    Its inverse gives ``Log(Exp(δ) · Exp(φ)) ≈ φ + J_l(φ)⁻¹ δ``, used to move a covariance
    between tangent charts in ``fuse``.

    Parameters
    ----------
    phi : array_like, shape (..., 3)
        Rotation vectors, rad.

    Returns
    -------
    ndarray, shape (..., 3, 3)

    """
    phi = np.asarray(phi, dtype=float)
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = th < 1e-5
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th ** 2 / 24.0, (1.0 - np.cos(ths)) / ths ** 2)
    b = np.where(small, 1.0 / 6.0 - th ** 2 / 120.0, (ths - np.sin(ths)) / ths ** 3)
    K = skew(phi)
    return np.eye(3) + a * K + b * (K @ K)


def _rotation(q: np.ndarray) -> np.ndarray:
    return quat.to_matrix(np.asarray(q, dtype=float))


def _unknown_mask(cov: np.ndarray) -> np.ndarray:
    """Components (..., n) whose diagonal is negative (not known)."""
    return np.diagonal(cov, axis1=-2, axis2=-1) < 0.0


def _known_part(cov: np.ndarray) -> np.ndarray:
    """Covariance with unknown rows/columns zeroed (their variance excluded from products)."""
    cov = np.array(cov, dtype=float)
    unk = _unknown_mask(cov)
    if unk.any():
        cov = np.where(unk[..., :, None] | unk[..., None, :], 0.0, cov)
    return cov


def _mark_unknown(cov: np.ndarray, jacobians: Sequence[np.ndarray],
                  unknowns: Sequence[np.ndarray]) -> np.ndarray:
    """Mark outputs depending on an unknown input: rows/cols 0, diagonal UNKNOWN."""
    out_unk = np.zeros(cov.shape[:-1], dtype=bool)
    for J, unk in zip(jacobians, unknowns, strict=True):
        if unk.any():
            touches = (np.abs(J) > _ZERO) & unk[..., None, :]
            out_unk |= touches.any(axis=-1)
    if out_unk.any():
        cov = np.where(out_unk[..., :, None] | out_unk[..., None, :], 0.0, cov)
        idx = np.arange(cov.shape[-1])
        cov[..., idx, idx] = np.where(out_unk, UNKNOWN, cov[..., idx, idx])
    return cov


def _symmetric(c: np.ndarray) -> np.ndarray:
    return 0.5 * (c + np.swapaxes(c, -1, -2))


def _cov_or_zero(pose: UncertainPose) -> np.ndarray:
    if pose.covariance is None:
        return np.zeros((6, 6))
    cov = np.asarray(pose.covariance, dtype=float)
    if cov.size != 36:
        raise InputError(f'a pose covariance must have 36 entries (6×6), got shape {cov.shape}')
    return cov.reshape(6, 6)


# --------------------------------------------------------------------------- errors

def pose_error(p_true, q_true, p_est, q_est) -> np.ndarray:
    """
    Error of estimates in the ROS layout: the δ with ``truth = Exp(δ) ⊞ estimate``.

    Parameters
    ----------
    p_true, p_est : array_like, shape (..., 3)
        Positions, m.
    q_true, q_est : array_like, shape (..., 4)
        Orientations (w, x, y, z).

    Returns
    -------
    ndarray, shape (..., 6)
        ``(p_true - p_est, Log(R_true R_estᵀ))``: m, then rad about the fixed axes.

    """
    dp = np.asarray(p_true, dtype=float) - np.asarray(p_est, dtype=float)
    dth = quat.log(quat.multiply(q_true, quat.conjugate(q_est)))
    return np.concatenate([dp, dth], axis=-1)


def nees(errors: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """
    Normalised estimation error squared ``eᵀ C⁻¹ e`` (χ² with dim(e) degrees of freedom).

    Parameters
    ----------
    errors : array_like, shape (..., n)
    cov : array_like, shape (..., n, n)
        Positive definite.

    Returns
    -------
    ndarray, shape (...)

    """
    e = np.asarray(errors, dtype=float)
    sol = np.linalg.solve(np.asarray(cov, dtype=float), e[..., None])[..., 0]
    return np.sum(e * sol, axis=-1)


def coverage_probability(n_sigma: float, dim: int) -> float:
    """
    Probability that a Gaussian error lies inside its ``n_sigma`` ellipsoid in ``dim`` dimensions.

    The ellipsoid is ``eᵀ C⁻¹ e ≤ n_sigma²``; in 3-D, 3σ holds about 97 % (Hoff eq. 8, note 3);
    in 2-D (an axis cone) about 98.9 %.
    """
    return float(stats.chi2.cdf(float(n_sigma) ** 2, int(dim)))


def sigma_for_probability(probability: float, dim: int) -> float:
    """Scale k of the ellipsoid ``eᵀ C⁻¹ e ≤ k²`` that holds ``probability`` in ``dim`` dims."""
    return float(np.sqrt(stats.chi2.ppf(float(probability), int(dim))))


# --------------------------------------------------------------------------- composition

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
    joint = (np.zeros((12, 12)) if result.cov_joint is None
             else np.asarray(result.cov_joint, dtype=float))
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
    q : array_like, shape (..., 4)

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


# --------------------------------------------------------------------------- fusion

def _information(cov: np.ndarray) -> np.ndarray:
    """Inverse covariance with zero information on unknown components, shape (..., n, n)."""
    cov = np.asarray(cov, dtype=float)
    unk = _unknown_mask(cov)
    if not unk.any():
        return np.linalg.inv(cov)
    known = _known_part(cov)
    eye = np.eye(cov.shape[-1])
    # unknown rows/cols become the identity, inverted, then zeroed: blockwise inverse.
    padded = np.where(unk[..., :, None] | unk[..., None, :], eye, known)
    info = np.linalg.inv(padded)
    return np.where(unk[..., :, None] | unk[..., None, :], 0.0, info)


def fuse_arrays(p1, q1, cov1, p2, q2, cov2, *, max_iterations: int = 20, tol: float = 1e-12):
    r"""
    Fuse two uncertain estimates of one pose on the tangent space (Hoff & Vincent §3.4).

    In a chart centred on the current mean (p̄, R̄), estimate i sits at
    ``ξ_i = (p_i - p̄, Log(R_i R̄ᵀ))`` with covariance ``J_i C_i J_iᵀ``,
    ``J_i = diag(I, J_l(ξ_i,θ)⁻¹)``. The fused chart point is

    .. math::

        C = (C_1'^{-1} + C_2'^{-1})^{-1}, \qquad ξ = C (C_1'^{-1} ξ_1 + C_2'^{-1} ξ_2);

    the mean moves to ``(p̄ + ξ_p, Exp(ξ_θ) R̄)`` and the chart is re-centred there until the step
    is below ``tol``. At convergence the chart is centred on the fused pose, so C is in the ROS
    layout of DESIGN.md §3. Unknown components (negative diagonal) carry no information.

    Parameters
    ----------
    p1, p2 : array_like, shape (..., 3)
        Positions, m.
    q1, q2 : array_like, shape (..., 4)
        Orientations (w, x, y, z).
    cov1, cov2 : array_like, shape (..., 6, 6)
        ROS-layout covariances; their information must add up to a positive definite matrix.
    max_iterations : int
    tol : float
        Step norm (m and rad together) below which the mean is settled.

    Returns
    -------
    p : ndarray, shape (..., 3)
    q : ndarray, shape (..., 4)
    cov : ndarray, shape (..., 6, 6)
    iterations : int
        Re-centrings done (the largest over the batch).

    """
    p1 = np.asarray(p1, dtype=float)
    p2 = np.asarray(p2, dtype=float)
    q1 = quat.canonical(np.asarray(q1, dtype=float))
    q2 = quat.canonical(np.asarray(q2, dtype=float))
    info1 = _information(cov1)
    info2 = _information(cov2)
    shape = np.broadcast_shapes(p1.shape[:-1], p2.shape[:-1], info1.shape[:-2],
                                info2.shape[:-2])
    # start from the estimate with more rotational information
    pick1 = (np.trace(info1[..., 3:6, 3:6], axis1=-2, axis2=-1)
             >= np.trace(info2[..., 3:6, 3:6], axis1=-2, axis2=-1))
    p_bar = np.where(pick1[..., None], p1, p2) * np.ones(shape + (3,))
    q_bar = np.where(pick1[..., None], q1, q2) * np.ones(shape + (4,))
    iterations = 0
    while iterations < int(max_iterations):
        iterations += 1
        infos, etas = [], []
        for p_i, q_i, info_i in ((p1, q1, info1), (p2, q2, info2)):
            xi = np.concatenate([p_i - p_bar,
                                 quat.log(quat.multiply(q_i, quat.conjugate(q_bar)))], axis=-1)
            Jinv = np.broadcast_to(np.eye(6), shape + (6, 6)).copy()
            Jinv[..., 3:6, 3:6] = left_jacobian(xi[..., 3:6])
            info_c = np.swapaxes(Jinv, -1, -2) @ info_i @ Jinv
            infos.append(info_c)
            etas.append(np.einsum('...ij,...j->...i', info_c, xi))
        info = infos[0] + infos[1]
        try:
            step = np.linalg.solve(info, (etas[0] + etas[1])[..., None])[..., 0]
        except np.linalg.LinAlgError as e:
            raise InputError('the two estimates together do not determine the pose (their '
                             'information is singular); give a covariance with every '
                             'component known in one of them') from e
        p_bar = p_bar + step[..., 0:3]
        q_bar = quat.canonical(quat.multiply(quat.exp(step[..., 3:6]), q_bar))
        if np.max(np.linalg.norm(step, axis=-1)) < tol:
            break
    return p_bar, q_bar, _symmetric(np.linalg.inv(info)), iterations


def fuse(a: UncertainPose, b: UncertainPose, *, max_iterations: int = 20,
         tol: float = 1e-12) -> UncertainPose:
    """
    Fuse two uncertain estimates of one pose (inverse-covariance weighting, Hoff §3.4).

    Parameters
    ----------
    a, b : UncertainPose
        Estimates of the same pose in the same frame, both with covariance.

    Returns
    -------
    UncertainPose
        The fused pose; its covariance is at most each input's (Loewner order).

    Raises
    ------
    InputError
        If a covariance is missing or the combined information is singular.

    """
    if a.covariance is None or b.covariance is None:
        raise InputError('fusion needs both covariances; an estimate without one cannot be '
                         'weighted')
    p, q, c, _ = fuse_arrays(a.position, a.quat_wxyz, _cov_or_zero(a), b.position,
                             b.quat_wxyz, _cov_or_zero(b), max_iterations=max_iterations,
                             tol=tol)
    return UncertainPose(p, q, c)


# --------------------------------------------------------------------------- ellipsoids, cones

@dataclass(frozen=True)
class Ellipsoid:
    """
    Uncertainty ellipsoid ``{z : zᵀ C⁻¹ z ≤ k²}`` of a 3×3 covariance (Hoff §3.3).

    Attributes
    ----------
    semi_axes : ndarray, shape (3,)
        Semi-axis lengths k·√λ, largest first (units of √C, e.g. m).
    axes : ndarray, shape (3, 3)
        Unit direction of each semi-axis, as columns, in the covariance's frame.
    n_sigma : float
        k.
    probability : float
        Probability that the error lies inside (≈ 0.971 for k = 3).

    """

    semi_axes: np.ndarray
    axes: np.ndarray
    n_sigma: float
    probability: float

    def surface(self, center=(0.0, 0.0, 0.0), n: int = 24):
        """Mesh (X, Y, Z), each shape (n, n), of the ellipsoid surface around ``center``."""
        u = np.linspace(0.0, 2.0 * np.pi, n)
        v = np.linspace(0.0, np.pi, n)
        sphere = np.stack([np.outer(np.cos(u), np.sin(v)), np.outer(np.sin(u), np.sin(v)),
                           np.outer(np.ones_like(u), np.cos(v))], axis=-1)
        pts = (sphere * self.semi_axes) @ self.axes.T + np.asarray(center, dtype=float)
        return pts[..., 0], pts[..., 1], pts[..., 2]


def ellipsoid_axes(cov, n_sigma: float = 3.0) -> Ellipsoid:
    """
    Principal axes of the ``n_sigma`` ellipsoid of a covariance (eigen-decomposition).

    Parameters
    ----------
    cov : array_like, shape (3, 3)
        E.g. the position block of a pose covariance (Hoff eq. 9), m².
    n_sigma : float
        k of ``zᵀ C⁻¹ z ≤ k²`` (3 by default, as Hoff).

    Returns
    -------
    Ellipsoid

    """
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (3, 3):
        raise InputError(f'ellipsoid_axes needs a 3×3 covariance, got {cov.shape}')
    if (np.diag(cov) < 0).any():
        raise InputError('the covariance has unknown components (negative diagonal); no '
                         'ellipsoid can be drawn')
    lam, vec = np.linalg.eigh(_symmetric(cov))
    order = np.argsort(lam)[::-1]
    lam = np.clip(lam[order], 0.0, None)
    vec = vec[:, order]
    vec = vec * np.where(np.linalg.det(vec) < 0, -1.0, 1.0)  # right-handed
    return Ellipsoid(semi_axes=float(n_sigma) * np.sqrt(lam), axes=vec, n_sigma=float(n_sigma),
                     probability=coverage_probability(n_sigma, 3))


@dataclass(frozen=True)
class AxisCone:
    """
    Uncertainty of the direction of one axis of a frame (Hoff §3.3, Fig. 1).

    Attributes
    ----------
    index : int
        0, 1, 2 for the frame's x, y, z axis.
    direction : ndarray, shape (3,)
        The axis a = R e in the parent frame (unit).
    covariance : ndarray, shape (3, 3)
        ``C_a = [a]× C_θ [a]×ᵀ``, rank 2 (flat along a), of the unit axis' tip.
    half_angles : ndarray, shape (2,)
        Cone half-angles ``atan(k √λ)`` of the ``n_sigma`` ellipse at the tip, rad, largest
        first.
    ellipse_axes : ndarray, shape (3, 2)
        Unit directions (perpendicular to a) of those half-angles, as columns.
    n_sigma : float
    probability : float
        Probability that the tip lies inside the ellipse (2-D; ≈ 0.989 for k = 3).

    """

    index: int
    direction: np.ndarray
    covariance: np.ndarray
    half_angles: np.ndarray
    ellipse_axes: np.ndarray
    n_sigma: float
    probability: float


def axis_covariance(q, cov_rot) -> np.ndarray:
    """
    Covariance of each unit axis a_i = R e_i of a frame: ``[a]× C_θ [a]×ᵀ``, shape (..., 3, 3, 3).

    With ``R_true = Exp(δθ) R``, the axis moves by ``δθ × a = -[a]× δθ`` to first order.

    Parameters
    ----------
    q : array_like, shape (..., 4)
    cov_rot : array_like, shape (..., 3, 3)
        Rotation block of the pose covariance, rad².

    Returns
    -------
    ndarray, shape (..., 3, 3, 3)
        Index -3 is the axis (x, y, z).

    """
    R = _rotation(q)
    A = skew(np.swapaxes(R, -1, -2))  # (..., 3 axes, 3, 3): [a_i]×
    c = np.asarray(cov_rot, dtype=float)[..., None, :, :]
    return A @ c @ np.swapaxes(A, -1, -2)


def axis_cones(pose: UncertainPose, n_sigma: float = 3.0) -> list[AxisCone]:
    """
    Compute the three axis cones of Hoff's Fig. 1 for a pose with covariance.

    Parameters
    ----------
    pose : UncertainPose
        Orientation and ROS-layout covariance (its rotation block must be known).
    n_sigma : float
        Size of the ellipse at each axis tip.

    Returns
    -------
    list of AxisCone
        For the x, y and z axes.

    """
    cov = _cov_or_zero(pose)
    if (np.diag(cov)[3:6] < 0).any():
        raise InputError('the orientation is not estimated (unknown covariance); no axis '
                         'cones can be drawn')
    R = _rotation(pose.quat_wxyz)
    cones = []
    for i, c_a in enumerate(axis_covariance(pose.quat_wxyz, cov[3:6, 3:6])):
        a = R[:, i]
        lam, vec = np.linalg.eigh(_symmetric(c_a))
        # the eigenvector along a has eigenvalue 0; keep the two perpendicular ones
        perp = np.argsort(np.abs(vec.T @ a))[:2]
        lam, vec = lam[perp], vec[:, perp]
        order = np.argsort(lam)[::-1]
        lam = np.clip(lam[order], 0.0, None)
        cones.append(AxisCone(index=i, direction=a, covariance=c_a,
                              half_angles=np.arctan(float(n_sigma) * np.sqrt(lam)),
                              ellipse_axes=vec[:, order], n_sigma=float(n_sigma),
                              probability=coverage_probability(n_sigma, 2)))
    return cones


# --------------------------------------------------------------------------- display geometry

def ellipsoid_orientation(ell: Ellipsoid) -> np.ndarray:
    """
    Orientation (w, x, y, z) whose rotation matrix has the ellipsoid's axes as columns.

    With it, a unit sphere scaled by ``2 · semi_axes`` (diameters, e.g. an RViz SPHERE
    marker's ``scale``) and rotated is the ellipsoid. Shape (4,).
    """
    return quat.from_matrix(ell.axes)


def cone_mesh(cone: AxisCone, length: float = 1.0, gain: float = 1.0, n: int = 24,
              origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """
    Triangles of an axis cone (Hoff Fig. 1): apex at the frame origin, elliptical rim at the tip.

    Parameters
    ----------
    cone : AxisCone
    length : float
        Drawn axis length, m.
    gain : float
        Magnification of tan(half-angle), so that milliradian cones can be seen.
    n : int
        Segments of the rim.
    origin : array_like, shape (3,)
        Frame origin in the parent frame, m.

    Returns
    -------
    ndarray, shape (n, 3, 3)
        Triangle k is (apex, rim_k, rim_k+1), e.g. for an RViz TRIANGLE_LIST marker.

    """
    t = np.linspace(0.0, 2.0 * np.pi, int(n) + 1)
    ext = float(gain) * np.tan(cone.half_angles)
    rim = (cone.direction[None, :] + np.cos(t)[:, None] * ext[0] * cone.ellipse_axes[:, 0]
           + np.sin(t)[:, None] * ext[1] * cone.ellipse_axes[:, 1]) * float(length)
    rim = rim + np.asarray(origin, dtype=float)
    apex = np.broadcast_to(np.asarray(origin, dtype=float), (int(n), 3))
    return np.stack([apex, rim[:-1], rim[1:]], axis=1)
