r"""
Cramér-Rao lower bound of the coregistration parameters in the errors-in-variables model.

Both devices are noisy: ``x̂_i = x_i ⊞ n_a`` and ``ŷ_i = f(x_i, ψ) ⊞ n_b`` with independent
Gaussian ``n_a ~ N(0, Σ_a)`` and ``n_b ~ N(0, Σ_b)`` in the ROS layout (position m, then the
small rotation δθ with ``R_meas = Exp(δθ) R_true`` about the fixed axes of the device's base
frame). The unknowns are ψ and the N true inputs x_i (nuisance parameters). The Fisher
information of ψ with the inputs eliminated is the Schur complement of the full information
matrix, which by the Woodbury identity is

.. math::

    \mathcal{I}(ψ) = \sum_i F_{ψ,i}^T (Σ_b + F_{x,i} Σ_a F_{x,i}^T)^{-1} F_{ψ,i},

the "effective variance" form, evaluated at the true parameters and the true (noise-free)
inputs. Its inverse is the CRLB of any unbiased estimator of ψ, and the asymptotic covariance
of the errors-in-variables maximum-likelihood estimator (Ikits 2000, appendix B.2).

This module is written independently of ``estimator`` (closed-form Jacobians in the ROS tangent
coordinates instead of reduced quaternions) so that it can check the estimator.

Coordinates of ψ (the ROS layout of docs/design.md §3, each rotation a left perturbation
``R_true = Exp(δθ) R``):

============== =====================================================
model          ψ
============== =====================================================
full_pose      δp0, δθ0, δp1, δθ1 (12)
position_only  δp0, δθ0, δp1 (9)
three_marker   δp0, δθ0, δp1, δp2, δp3 (15)
============== =====================================================
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import InputError
from coreg_ros.core.so3 import skew
from coreg_ros.core.types import MODELS
import numpy as np

#: Dimension of ψ per model.
CRLB_DIMENSION = {'full_pose': 12, 'position_only': 9, 'three_marker': 15}


def model_jacobians(model: str, p0, q0, markers, pos_a, quat_a):
    """
    Jacobians of device B's measurement with respect to ψ and to A's pose, in ROS tangents.

    ``p_Bj = p0 + R0 (p_A + R_A p_j)`` and ``R_B = R0 R_A R1`` (Ikits eqs. 16, 18, 19).

    Parameters
    ----------
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    p0 : array_like, shape (3,)
        T0 = T_bbase_abase position, m (in B's base frame).
    q0 : array_like, shape (4,)
        T0 orientation (w, x, y, z).
    markers : array_like, shape (k, 3)
        Marker position(s) in A's tool frame, m (k = 3 for three markers, else 1).
    pos_a : ndarray, shape (N, 3)
        True tool positions in A's base frame, m.
    quat_a : ndarray, shape (N, 4)
        True tool orientations in A's base frame (w, x, y, z).

    Returns
    -------
    f_psi : ndarray, shape (N, m, d)
        ∂y/∂ψ, y = (p_B1.., δθ_B) with m = 6, 3 or 9 and d = 12, 9 or 15.
    f_x : ndarray, shape (N, m, 6)
        ∂y/∂x over A's (δp_A, δθ_A).

    """
    if model not in MODELS:
        raise InputError(f'model {model!r} is unknown; use one of {", ".join(MODELS)}')
    markers = np.atleast_2d(np.asarray(markers, dtype=float))
    k = 3 if model == 'three_marker' else 1
    if markers.shape != (k, 3):
        raise InputError(f'markers must have shape ({k}, 3) for model {model}, got '
                         f'{markers.shape}')
    pos_a = np.asarray(pos_a, dtype=float)
    n = len(pos_a)
    R0 = quat.to_matrix(np.asarray(q0, dtype=float))
    Ra = quat.to_matrix(np.asarray(quat_a, dtype=float))
    R0Ra = R0 @ Ra
    full = model == 'full_pose'
    m = 3 * k + (3 if full else 0)
    d = CRLB_DIMENSION[model]
    f_psi = np.zeros((n, m, d))
    f_x = np.zeros((n, m, 6))
    for j in range(k):
        rows = slice(3 * j, 3 * j + 3)
        u = Ra @ markers[j]  # R_A p_j, (N, 3)
        r0v = (pos_a + u) @ R0.T  # R0 v
        f_psi[:, rows, 0:3] = np.eye(3)
        f_psi[:, rows, 3:6] = -skew(r0v)  # Exp(δθ0) R0 v ≈ R0 v - [R0 v]× δθ0
        f_psi[:, rows, 6 + 3 * j:9 + 3 * j] = R0Ra
        f_x[:, rows, 0:3] = R0
        f_x[:, rows, 3:6] = -R0 @ skew(u)  # R0 Exp(δθA) R_A p_j
    if full:
        f_psi[:, 3:6, 3:6] = np.eye(3)  # Exp(δθ0) R0 R_A R1
        f_psi[:, 3:6, 9:12] = R0Ra  # R0 R_A Exp(δθ1) R1 = Exp(R0 R_A δθ1) R0 R_A R1
        f_x[:, 3:6, 3:6] = R0  # R0 Exp(δθA) R_A R1 = Exp(R0 δθA) R0 R_A R1
    return f_psi, f_x


def fisher_information(model: str, p0, q0, markers, pos_a, quat_a, cov_a, cov_b,
                       a_var_scale: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Fisher information of ψ for N pairs with noise on both devices (``cramer_rao_bound``).

    Returns
    -------
    ndarray, shape (d, d)
        The Schur complement at the truth, coordinates of the module table (singular where
        the motion leaves a direction undetermined).

    """
    cov_a = np.asarray(cov_a, dtype=float).reshape(6, 6)
    cov_b = np.asarray(cov_b, dtype=float).reshape(6, 6)
    f_psi, f_x = model_jacobians(model, p0, q0, markers, pos_a, quat_a)
    m = f_psi.shape[1]
    if model == 'full_pose':
        sigma_b = cov_b
    else:
        sigma_b = np.kron(np.eye(m // 3), cov_b[0:3, 0:3])
    scale = (np.ones(len(f_x)) if a_var_scale is None
             else np.asarray(a_var_scale, dtype=float))
    M = sigma_b + scale[:, None, None] * (f_x @ cov_a @ f_x.transpose(0, 2, 1))
    Minv_f = np.linalg.solve(M, f_psi)
    info = np.einsum('nmi,nmj->ij', f_psi, Minv_f)
    return 0.5 * (info + info.T)


def cramer_rao_bound(model: str, p0, q0, markers, pos_a, quat_a, cov_a, cov_b,
                     a_var_scale: Optional[np.ndarray] = None):
    """
    CRLB of ψ for N pairs with noise on both devices (inputs as nuisance parameters).

    Parameters
    ----------
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    p0, q0, markers :
        True calibration, as in ``model_jacobians`` (q1 does not enter the bound).
    pos_a, quat_a : ndarray, shapes (N, 3), (N, 4)
        True (noise-free) tool poses in A's base frame.
    cov_a : ndarray, shape (6, 6)
        Noise covariance of A, ROS layout (m², rad²).
    cov_b : ndarray, shape (6, 6)
        Noise covariance of B, ROS layout; only its position block is used for the
        position-only models (every marker independent with that covariance).
    a_var_scale : ndarray, shape (N,), optional
        Factor on A's covariance per pair.

    Returns
    -------
    crlb : ndarray, shape (d, d)
        Inverse Fisher information, coordinates of the module table.
    info : ndarray, shape (d, d)
        Fisher information (the Schur complement at the truth).

    """
    info = fisher_information(model, p0, q0, markers, pos_a, quat_a, cov_a, cov_b, a_var_scale)
    return np.linalg.inv(info), info
