"""
The sums of the clock offset's Gauss-Newton step in closed form (full pose and position only).

``timing.offset_step`` needs, over the pairs, ``h_ττ = Σ cᵀ W c``, ``h_φτ = Σ J_φᵀ W c`` and
``g_τ = Σ eᵀ W c``, with ``c = -F_x ẋ_A`` the offset's column, e the output error at the
measured input and ``W = Σ_eff⁻¹``, ``Σ_eff = Σ_y + s F_x Σ_x F_xᵀ`` (``linearized``). The
generic path forms every pair's Jacobians (m×P and m×6) and solves an m×m system by LAPACK:
about 1.2 µs per pair, more than a TLS linearisation. With isotropic noise per block (position,
rotation; how ``Settings`` states it) the blocks of ``Σ_eff`` are short closed forms in the
marker lever ``c0 = R0 R_A p1`` (B's base frame) and the metric Jacobian
``D = (E_w I - [E_v]×) / 2`` of the error quaternion E (Ikits eq. 15):

    Σ_pp = (σ_yp² + s σ_xp²) I + s σ_xθ² (|c0|² I - c0 c0ᵀ)
    Σ_pr = -s σ_xθ² [c0]× Dᵀ
    Σ_rr = σ_yr² I + s σ_xθ² D Dᵀ,    D Dᵀ = (|E|² I - E_v E_vᵀ) / 4

and ``W c`` is two closed-form 3×3 Cholesky solves per pair (``Σ_pp`` and its Schur
complement). ``F_x ẋ_A`` is the marker's velocity ``R0 (v + ω × R_A p1)`` and ``D R0 ω``;
``J_φᵀ`` is applied to ``W c`` through its blocks (``models.linearize``) and the constant
chart maps ``G0``, ``G1`` once, after the sums.

The sums equal the generic ones to rounding (``test_spatiotemporal.py`` compares them on random
draws); ``structured_offset_sums`` returns None where they do not apply.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.estimator.linearized import PairData
from coreg_ros.core.estimator.pair_algebra import (
    cholesky3,
    CONJ,
    cross,
    error_quaternion,
    metric_jacobian,
    qmul,
    sym_solve3,
)
from coreg_ros.core.estimator.problem import chunk_slices
from coreg_ros.core.models import Parameters, S0, S1, tangent_of_chart
import numpy as np


def _isotropic_blocks(cov: np.ndarray) -> Optional[tuple]:
    """(position variance, rotation variance) of a diagonal covariance with equal blocks."""
    d = np.diag(cov)
    if np.count_nonzero(cov - np.diag(d)) or np.any(d[0:3] != d[0]):
        return None
    if len(d) == 3:
        return float(d[0]), 0.0
    if len(d) != 6 or np.any(d[3:6] != d[3]):
        return None
    return float(d[0]), float(d[3])


def structured_offset_sums(params: Parameters, data: PairData, velocity: np.ndarray,
                           since_ref: Optional[np.ndarray],
                           ready: Optional[Callable[[int], None]] = None
                           ) -> Optional[tuple]:
    """
    ``h_ττ``, ``h_φτ`` and ``g_τ`` of the offset step in closed form (module docstring).

    Parameters
    ----------
    params : Parameters
        φ the pairs are linearised at.
    data : PairData
        The pairs (measured inputs) and the noise: ``cov_a`` 6×6 in the ROS layout, ``cov_b``
        m×m of the output metric.
    velocity : ndarray, shape (N, 6)
        A's linear (m/s) and angular (rad/s, A's base frame) velocity per pair.
    since_ref : ndarray, shape (N,), optional
        ``t_B - t_mid`` (s) per pair when the drift is a second time parameter.
    ready : callable, optional
        ``ready(stop)`` waits until the rows of ``velocity`` before ``stop`` are written
        (the chunks are read in order; None: all are written).

    Returns
    -------
    (h_tt, h_pt, g_t) : ndarrays of shapes (k, k), (P, k), (k,), or None
        None unless the model is full pose or position only, with TLS and isotropic noise per
        block (then ``timing`` takes the generic path). k is 1, or 2 with ``since_ref``.

    """
    spec = params.spec
    if spec.name not in ('full_pose', 'position_only') or not data.tls:
        return None
    noise_a = _isotropic_blocks(np.asarray(data.cov_a, dtype=float).reshape(6, 6))
    noise_b = _isotropic_blocks(np.asarray(data.cov_b, dtype=float))
    if noise_a is None or noise_b is None:
        return None
    k = 1 if since_ref is None else 2
    h_tt = np.zeros((k, k))
    g_t = np.zeros(k)
    # Σ over the pairs of the four 3×k blocks of J_φᵀ W c before the chart maps: p0, θ0 (a
    # rotation of B's base), p1, θ1 (a rotation of the marker, in A's tool frame)
    blocks = np.zeros((4, 3, k))
    for sl in chunk_slices(len(data)):
        if ready is not None:
            ready(sl.stop)
        since = None if since_ref is None else since_ref[sl]
        g, u, y, e = _weighted_columns(params, data, sl, velocity[sl], since, noise_a,
                                       noise_b)
        h_tt += np.einsum('rkn,rln->kl', u, y)
        g_t += np.einsum('rn,rkn->k', e, y)
        _add_parameter_blocks(blocks, params.R0, g, y)
    h_pt = np.zeros((spec.n_params, k))
    h_pt[0:3] = blocks[0]
    h_pt[S0] = tangent_of_chart(params.q0, params.dq0).T @ blocks[1]
    h_pt[spec.marker_slice(0)] = blocks[2]
    if spec.has_q1:
        h_pt[S1] = tangent_of_chart(params.q1, params.dq1).T @ blocks[3]
    return h_tt, h_pt, g_t


class _Geometry:
    """Per-pair quantities of one chunk at φ (pair-last): R_A, R_A p1, R0 v, E and D."""

    def __init__(self, params: Parameters, data: PairData, sl: slice):
        R0 = params.R0
        quat_a = np.ascontiguousarray(data.quat_a[sl].T)
        self.Ra = quat.to_matrix(quat_a, pair_last=True)
        self.c_a = np.einsum('ijn,j->in', self.Ra, params.markers[0])   # R_A p1
        self.r0v = R0 @ (data.pos_a[sl].T + self.c_a)                   # R0 (p_A + R_A p1)
        self.c0 = R0 @ self.c_a                                          # lever in B's base
        self.e_p = params.p0[:, None] + self.r0v - data.pos_b[sl].T
        self.E = self.D = None
        if params.spec.has_q1:
            q_model = qmul(params.q0, qmul(quat_a, params.q1))
            self.E = error_quaternion(q_model, np.ascontiguousarray(data.quat_b[sl].T) * CONJ)
            self.D = metric_jacobian(self.E)


def _tmv(M: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Mᵀ y per pair for M (3, 3, c) and y (3, k, c)."""
    return np.einsum('ijn,ikn->jkn', M, y)


def _weighted_columns(params: Parameters, data: PairData, sl: slice, velocity: np.ndarray,
                      since: Optional[np.ndarray], noise_a: tuple, noise_b: tuple) -> tuple:
    """
    Return the geometry, the columns u = -F_x ẋ (r, k, c), y = Σ_eff⁻¹ u, and e (r, c).

    r = 6 (full pose) or 3 (position only); pair-last.
    """
    g = _Geometry(params, data, sl)
    R0, c0 = params.R0, g.c0
    xp, xth = noise_a
    yp, yr = noise_b
    s = 1.0 if data.a_scale is None else np.asarray(data.a_scale[sl], dtype=float)
    v_lin = velocity[:, 0:3].T
    omega = velocity[:, 3:6].T
    cols = [1.0] if since is None else [1.0, since]
    u_p = -(R0 @ (v_lin + cross(omega, g.c_a)))                 # marker velocity, negated
    u_p = np.stack([u_p * w for w in cols], axis=1)              # (3, k, c)
    # Σ_pp = (σ_yp² + s σ_xp²) I + s σ_xθ² (|c0|² I - c0 c0ᵀ): its lower triangle
    st = s * xth
    diag = yp + s * xp + st * np.einsum('in,in->n', c0, c0)
    S_pp = np.empty((3, 3, c0.shape[1]))
    for i in range(3):
        S_pp[i, i] = diag - st * c0[i] * c0[i]
        for j in range(i):
            S_pp[i, j] = -st * c0[i] * c0[j]
    Lp = cholesky3(S_pp)
    a = sym_solve3(Lp, u_p, transpose=False)
    if g.D is None:
        return g, u_p, sym_solve3(Lp, a, transpose=True), g.e_p
    D, E = g.D, g.E
    w0 = R0 @ omega
    u_r = -np.einsum('ijn,jn->in', D, w0)
    u_r = np.stack([u_r * w for w in cols], axis=1)
    # Σ_pr = -s σ_xθ² [c0]× Dᵀ; G = Lp⁻¹ Σ_pr; the Schur complement Σ_rr - GᵀG
    cxD = cross(c0[:, None, :], np.transpose(D, (1, 0, 2)))     # [c0]× Dᵀ, column by column
    G = sym_solve3(Lp, -st * cxD, transpose=False)
    ev = E[1:]
    e2 = np.einsum('in,in->n', E, E)
    M = np.empty((3, 3, c0.shape[1]))
    for i in range(3):
        for j in range(i + 1):
            dd = (e2 if i == j else 0.0) - ev[i] * ev[j]            # 4 D Dᵀ
            M[i, j] = (yr if i == j else 0.0) + 0.25 * st * dd \
                - np.einsum('an,an->n', G[:, i], G[:, j])
    Lm = cholesky3(M)
    b = u_r - _tmv(G, a)
    y_r = sym_solve3(Lm, sym_solve3(Lm, b, transpose=False), transpose=True)
    y_p = sym_solve3(Lp, a - np.einsum('ijn,jkn->ikn', G, y_r), transpose=True)
    return (g, np.concatenate([u_p, u_r]), np.concatenate([y_p, y_r]),
            np.concatenate([g.e_p, ev]))


def _add_parameter_blocks(blocks: np.ndarray, R0: np.ndarray, g: _Geometry,
                          y: np.ndarray) -> None:
    """
    Add the chunk's Σ J_φᵀ y to ``blocks`` (4, 3, k), block by block (``models.linearize``).

    p0: y_p; θ0: r0v × y_p + Dᵀ y_r; p1: R_Aᵀ R0ᵀ y_p; θ1: R_Aᵀ R0ᵀ Dᵀ y_r (the chart maps
    G0ᵀ, G1ᵀ are applied to the sums).
    """
    y_p = y[0:3]
    blocks[0] += y_p.sum(axis=2)
    turn = cross(g.r0v[:, None, :], y_p)
    blocks[2] += np.einsum('ijn,ikn->jk', g.Ra, np.einsum('ij,ikn->jkn', R0, y_p))
    if g.D is not None:
        dy = _tmv(g.D, y[3:6])
        turn += dy
        blocks[3] += np.einsum('ijn,ikn->jk', g.Ra, np.einsum('ij,ikn->jkn', R0, dy))
    blocks[1] += turn.sum(axis=2)
