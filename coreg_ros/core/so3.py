"""
Small SO(3) and rigid-transform algebra shared by the estimator, uncertainty and diagnosis.

Rotation vectors φ (rad) with ``Exp(φ)`` about the fixed axes, as in docs/design.md §3.
"""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
import numpy as np


def skew(v: np.ndarray, pair_last: bool = False) -> np.ndarray:
    """
    Cross-product matrix ``[v]×`` with ``[v]× u = v × u``.

    The one skew of the package: the estimator's closed forms take its pair-last layout.

    Parameters
    ----------
    v : array_like, shape (..., 3), or (3, c) with ``pair_last``
        The vector(s) v.
    pair_last : bool
        Vectors as columns (3, c) and matrices (3, 3, c), the structure-of-arrays layout of
        ``estimator.normal_equations``.

    Returns
    -------
    ndarray, shape (..., 3, 3), or (3, 3, c) with ``pair_last``

    """
    v = np.asarray(v, dtype=float)
    if pair_last:
        out = np.zeros((3, 3) + v.shape[1:])
        x, y, z = v[0], v[1], v[2]
        S = out
    else:
        out = np.zeros(v.shape[:-1] + (3, 3))
        x, y, z = v[..., 0], v[..., 1], v[..., 2]
        S = np.moveaxis(out, (-2, -1), (0, 1))  # a view: S[i, j] is out[..., i, j]
    S[0, 1], S[0, 2] = -z, y
    S[1, 0], S[1, 2] = z, -x
    S[2, 0], S[2, 1] = -y, x
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


def invert_poses(position, quat_wxyz) -> tuple[np.ndarray, np.ndarray]:
    """
    Invert rigid transforms: ``T = (p, q) → T⁻¹ = (-R(q)ᵀ p, q*)``.

    Parameters
    ----------
    position : array_like, shape (..., 3)
        Translation of each transform, e.g. the tool position in the base frame, m.
    quat_wxyz : array_like, shape (..., 4)
        Rotation of each transform, (w, x, y, z), unit.

    Returns
    -------
    position : ndarray, shape (..., 3)
        Translation of the inverse (the base's origin in the tool frame), m.
    quat_wxyz : ndarray, shape (..., 4)
        Rotation of the inverse, (w, x, y, z), canonical (w >= 0).

    """
    position = np.asarray(position, dtype=float)
    q = np.asarray(quat_wxyz, dtype=float)
    R = quat.to_matrix(q)
    inv_p = -np.einsum('...ji,...j->...i', R, position)
    return inv_p, quat.canonical(quat.conjugate(q))
