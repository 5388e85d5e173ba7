"""
Per-pair algebra in the pair-last layout: vectors (3, c), matrices (3, 3, c), quaternions (4, c).

The closed-form normal equations (``normal_equations``, ``normal_equations_tls``) and the
robust statistic (``core.screening``) work on whole chunks of pairs at once; these are their
small building blocks (products, cross products, the 3×3 Cholesky factor and its solves, the
error quaternion of §3.2 and its metric Jacobian, eq. 15), written out component by component
because numpy's general routines are several times slower on stacks of 3×3 blocks.
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.estimator.problem import chunk_slices
from coreg_ros.core.so3 import skew
import numpy as np


def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (4,) or (4, c), broadcast to (4, c)."""
    return np.array(quat.multiply_parts(p, q))


def rotated(q: np.ndarray, d: np.ndarray, idx: Optional[np.ndarray] = None) -> np.ndarray:
    """
    ``Exp(d) ⊗ q``, renormalised, for quaternions (4, N) and rotation vectors d (3, N), rad.

    The TLS input step (pair-last layout), chunk by chunk so that the temporaries stay in
    cache. With ``idx`` (K,), the columns ``idx`` of q are stepped by d (3, K), gathered a
    chunk at a time: the numbers of ``rotated(np.take(q, idx, axis=1), d)``.
    """
    n = d.shape[1]
    out = np.empty((4, n))
    for sl in chunk_slices(n):
        qc = qmul(quat.exp_parts(*d[:, sl]),
                  q[:, sl] if idx is None else np.take(q, idx[sl], axis=1))
        out[:, sl] = qc / np.sqrt(qc[0] * qc[0] + qc[1] * qc[1] + qc[2] * qc[2] + qc[3] * qc[3])
    return out


def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross products of vectors (3, c) (np.cross with axis=0 is 1.5× slower here)."""
    return np.array([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                     u[0] * v[1] - u[1] * v[0]])


def mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Per-pair products A B of matrices (3, 3, c) (contiguous inputs keep einsum fast)."""
    return np.einsum('abn,bcn->acn', A, B)


def tmm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Per-pair products Aᵀ B of matrices (3, 3, c)."""
    return np.einsum('ban,bcn->acn', A, B)


def left(Q: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Q A for a constant Q (3, 3) and matrices (3, 3, c): one matrix product."""
    return (Q @ A.reshape(3, -1)).reshape(A.shape)


def gram(Y: np.ndarray) -> np.ndarray:
    """``Σ_pairs Y_iᵀ Y_i`` for Y (r, k, c): k×k, by r symmetric matrix products."""
    return sum(Y[a] @ Y[a].T for a in range(Y.shape[0]))


def metric_jacobian(E: np.ndarray) -> np.ndarray:
    """D = ∂vec(E)/∂a (3, 3, c) for ``E ← Exp(a) ⊗ E``: ``(E_w I - [E_v]×) / 2`` (eq. 15)."""
    D = skew(-0.5 * E[1:], pair_last=True)
    for k in range(3):
        D[k, k] = 0.5 * E[0]
    return D


CONJ = np.array([1.0, -1.0, -1.0, -1.0])[:, None]


def error_quaternion(q_model: np.ndarray, q_meas_conj: np.ndarray) -> np.ndarray:
    """``q_model ⊗ q_meas*`` (given q_meas*) with its scalar part made >= 0 (§3.2), (4, c)."""
    E = qmul(q_model, q_meas_conj)
    np.negative(E, out=E, where=E[0] < 0.0)   # in place, without a (4, c) sign array
    return E


def sym_solve3(L: tuple, rhs: np.ndarray, transpose: bool) -> np.ndarray:
    """Solve ``L y = rhs`` (or ``Lᵀ y = rhs``) with L the closed-form 3×3 Cholesky factor."""
    l00, l10, l11, l20, l21, l22 = L
    # one division per pair and diagonal entry, then products (rhs may have many columns)
    i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
    y = np.empty_like(rhs)
    if not transpose:
        np.multiply(rhs[0], i00, out=y[0])
        y[1] = (rhs[1] - l10 * y[0]) * i11
        y[2] = (rhs[2] - l20 * y[0] - l21 * y[1]) * i22
    else:
        np.multiply(rhs[2], i22, out=y[2])
        y[1] = (rhs[1] - l21 * y[2]) * i11
        y[0] = (rhs[0] - l10 * y[1] - l20 * y[2]) * i00
    return y


def cholesky3(U: np.ndarray) -> tuple:
    """Closed-form lower Cholesky factors of SPD blocks (3, 3, c): l00, l10, l11, l20, l21, l22."""
    l00 = np.sqrt(U[0, 0])
    l10 = U[1, 0] / l00
    l20 = U[2, 0] / l00
    l11 = np.sqrt(U[1, 1] - l10 * l10)
    l21 = (U[2, 1] - l20 * l10) / l11
    l22 = np.sqrt(U[2, 2] - l20 * l20 - l21 * l21)
    return l00, l10, l11, l20, l21, l22
