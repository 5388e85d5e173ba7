"""Fusion of two estimates of one pose on the tangent space (Hoff & Vincent §3.4)."""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import InputError
from coreg_ros.core.so3 import left_jacobian
from coreg_ros.core.types import UncertainPose
from coreg_ros.core.uncertainty._unknown import (
    _cov_or_zero,
    _known_part,
    _symmetric,
    _unknown_mask,
)
import numpy as np


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
    layout of docs/design.md §3. Unknown components (negative diagonal) carry no information.

    Parameters
    ----------
    p1, p2 : array_like, shape (..., 3)
        Positions, m.
    q1, q2 : array_like, shape (..., 4)
        Orientations (w, x, y, z).
    cov1, cov2 : array_like, shape (..., 6, 6)
        ROS-layout covariances; their information must add up to a positive definite matrix.
    max_iterations : int
        Largest number of iterations of the mean.
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
    max_iterations, tol : int, float
        As in ``fuse_arrays``.

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
