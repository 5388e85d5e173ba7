"""
TLS normal equations of full-pose and position-only problems in closed form (Ikits B.2).

The TLS half of ``normal_equations`` (whose docstring derives the channels and the moment
matrix): the input position is eliminated in closed form (one constant 3×3 inverse, Schur
complement ``Q_e``), and only a 3×3 block per pair remains for the input rotation, factored by
closed-form Cholesky. ``tls.tls_linearization`` uses ``tls_schur`` where
``normal_equations.applies`` holds; ``tls.back_substitute`` takes the input step from its
factors (``closed_form_back_substitute``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple, Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConvergenceError
from coreg_ros.core.estimator.normal_equations import (
    _add_rotation_block,
    _add_rotation_moments,
    _channels,
    _Chunk,
    _chunk_of,
    _features,
    _Frame,
    _rotation_information,
    _scalar,
    _sum_chunks,
    _sum_gradient,
    position_residual,
)
from coreg_ros.core.estimator.pair_algebra import (
    cholesky3,
    CONJ,
    cross,
    error_quaternion,
    gram,
    left,
    mm,
    sym_solve3,
)
from coreg_ros.core.estimator.problem import Columns
from coreg_ros.core.models import Parameters
from coreg_ros.core.so3 import skew
import numpy as np


class ChunkFactors(NamedTuple):
    """
    What the back-substitution needs of one chunk of c pairs (float32 where marked).

    The float32 arrays cost half the memory; δφ is solved from S and b accumulated in float64,
    so only the input steps carry a relative error of ~1e-7, which the next linearisation
    absorbs (an inexact Newton step in x, as in the generic path). R_A, c and v are not kept:
    the back-substitution makes them again from the input state (``TlsFactors.inputs``),
    and the input position's gradient and M_p from the pairs (``TlsFactors.position_terms``):
    148 bytes a pair less at the peak of a long recording's fit.
    """

    pairs: slice
    L: np.ndarray        # (6, c) float32: l00, l10, l11, l20, l21, l22 of the 3×3 factor
    Z: np.ndarray        # (3, k, c) float32: L⁻¹ [N | H_r | g̃_θ]


@dataclass
class TlsFactors:
    """What the input back-substitution needs of one linearisation."""

    T: np.ndarray                 # (P, P) φ' = T φ (reduced coordinates)
    Mp: Optional[np.ndarray]      # (3, 3) constant M_p, None when it is a scalar
    Qp_bar: np.ndarray            # (3, 3) Q̄p
    chunks: list                  # of ChunkFactors
    marker: np.ndarray            # (3,) p1, the tool-to-marker position at the linearisation
    inputs: tuple                 # (3, N), (4, N) the input state x linearised at (held)
    frame: _Frame                 # φ and the whitening of the linearisation
    problem: object               # its pairs (a Problem; not copied)
    m_of: Optional[Callable]      # pair weights (c,) or 1.0 -> scalar M_p; None: matrix M_p

    def position_terms(self, sl: slice, v: np.ndarray) -> tuple:
        """
        Return the input position's gradient g_p + g_ap (3, c) and M_p of the pairs ``sl``.

        Made as ``tls_schur`` made them, from the same inputs: the same numbers to the bit.
        """
        pos_a = np.ascontiguousarray(self.problem.pos_a[sl].T)
        pos_b = np.ascontiguousarray(self.problem.pos_b[sl].T)
        w = _input_weights(self.problem, sl)
        _, gap = _input_position(self.frame, self.inputs[0][:, sl], pos_a, w)
        g_pos = position_residual(self.frame, v, pos_b)[1] + gap
        return g_pos, None if self.m_of is None else self.m_of(w)

    def geometry(self, sl: slice) -> tuple:
        """
        R_A (float32, as kept before), c = R_A p1 and v = p_A + c of the pairs ``sl``.

        Made as ``_channels`` made them at the linearisation, from the same inputs: the same
        numbers to the bit.
        """
        xp, xq = self.inputs[0][:, sl], self.inputs[1][:, sl]
        Ra = quat.to_matrix(xq, pair_last=True)
        c = self.marker @ Ra
        return Ra.astype(np.float32), c, xp + c

    def clear(self) -> None:
        """Drop the per-pair factors and the inputs (spent after the back-substitution)."""
        self.chunks.clear()
        self.inputs = ()


def tls_schur(problem, params: Parameters, x, lam: float, residuals=None):
    """
    Reduced system ``S δφ = b`` and the cost at (x, φ) (Ikits eqs. 42-49), damped by λ.

    Per pair, the input position is eliminated in closed form (``M_p``, ``Q_e``) and the input
    rotation by the closed-form Cholesky factor L of the remaining 3×3 block
    ``Ũ = [c]×ᵀ Q_e [c]× + H_r + H_ar``. With ``Z = L⁻¹ [N | H_r | g̃_θ]`` (``N = [c]× Q_e``)
    the pair's coupling to φ' is ``Z_W = Z_N B_p + Z_H B_r`` and
    ``S' = Σ B_pᵀ Q_e B_p + Σ B_rᵀ H_r B_r - Σ Z_Wᵀ Z_W``.

    ``Q_e = Q̄p - Q̄p M_p Q̄p`` is evaluated as ``Q̄p M_p (Q_ap + Λ_p)``, without the
    cancellation of the first form when A is far noisier than B.

    Damping as in the generic path: λ·diag on every pair's 6×6 input block and λ·diag(V) on
    the φ block, V = Σ Bᵀ B. Priors are not included (the caller adds them).

    Parameters
    ----------
    problem : Problem
        One for which ``applies(problem)`` is true.
    params : Parameters
        The calibration φ the sums are taken at.
    x : tls.InputState
        Current input estimates.
    lam : float
        Damping λ.
    residuals : tuple of ndarray, optional
        (N, m) and (N, 6) arrays filled with the whitened output and input residuals.

    Returns
    -------
    S : ndarray, shape (P, P)
    b : ndarray, shape (P,)
    v_diag : ndarray, shape (P,)
        diag(V), for the damping of the φ block by the caller.
    cost : float
    factors : TlsFactors

    """
    frame = _Frame.of(problem, params)
    P, Qp_bar, has_rot = frame.P, frame.Qp_bar, frame.has_rot
    weighted = problem.a_scale is not None
    lp, lap = _scalar(frame.Lp), _scalar(frame.Lap)
    iso = lp is not None and lap is not None
    if iso:  # Q̄p = q_p I, Q_ap = q_a I: eliminating δp_A is a scalar per pair
        q_p, q_a = lp * lp, lap * lap
        Mp = Qe = None

        def eliminated(w):
            """M_p⁻¹ - q_p, m = M_p and q_e = q_p - q_p² m (without its cancellation)."""
            extra = q_a * w + lam * (q_p + q_a * w)
            m = 1.0 / (q_p + extra)
            return extra, m, q_p * extra * m
    elif weighted:
        raise ValueError('per-pair input weights need isotropic position noise here '
                         '(normal_equations.applies is false for this problem)')
    else:  # constant 3×3 blocks
        Qap = frame.Lap.T @ frame.Lap
        Upp = Qp_bar + Qap
        extra = Qap + lam * np.diag(np.diag(Upp))   # M_p⁻¹ - Q̄p
        Mp = np.linalg.inv(Upp + lam * np.diag(np.diag(Upp)))
        Qe = Qp_bar @ Mp @ extra
        Qe = 0.5 * (Qe + Qe.T)
        keep = extra @ Mp    # I - Q̄p M_p, as hp = gp - Q̄p M_p (gp + gap) needs it
    factors = TlsFactors(frame.T, Mp, Qp_bar, [], params.markers[0], (x.pos_t, x.quat_t),
                         frame, problem, (lambda w: eliminated(w)[1]) if iso else None)
    k = 7 if has_rot else 4   # columns of Z: N, (H_r,) g̃_θ

    def chunk(sl):
        pos_a, quat_a, pos_b, quat_b = _chunk_of(problem, sl)
        xp, xq = x.pos_t[:, sl], x.quat_t[:, sl]
        ch = _channels(frame, xp, xq, pos_b, quat_b)
        n_pairs = ch.c.shape[1]
        Ea = error_quaternion(xq, quat_a * CONJ)
        r_ar, U, gar, _ = _rotation_information(frame.Lar, Ea, None)
        w = _input_weights(problem, sl)
        r_ap, gap = _input_position(frame, xp, pos_a, w)
        if weighted:
            r_ap *= np.sqrt(w)
            r_ar *= np.sqrt(w)
            U *= w
            gar *= w
        rhs = np.empty((3, k, n_pairs))
        if iso:
            # [c]×ᵀ (q I) [c]× = q (|c|² I - c cᵀ); after eliminating δp_A, q_e in place of q_p
            extra, m, q_e = eliminated(w)
            cc = ch.c * ch.c
            c2 = cc.sum(axis=0)
            pre = q_p * (c2 - cc) + U[[0, 1, 2], [0, 1, 2]]   # scales the damping
            for i in range(3):
                U[i, i] += q_e * (c2 - cc[i])
                for j in range(i):
                    U[i, j] -= q_e * (ch.c[i] * ch.c[j])  # the lower triangle is all L uses
            _scaled_skew(q_e, ch.c, rhs)   # N = q_e [c]×, into its columns of the rhs
            hp = (extra * m) * ch.gp - (q_p * m) * gap
        else:
            m = None
            C = skew(ch.c, pair_last=True)
            pre = (C * left(Qp_bar, C)).sum(axis=0) + U[[0, 1, 2], [0, 1, 2]]
            N = np.einsum('abn,bc->acn', C, Qe)
            U -= mm(N, C)
            hp = keep @ ch.gp - (Qp_bar @ Mp) @ gap
            rhs[:, 0:3] = N
        rhs[:, k - 1] = cross(ch.c, hp) + gar
        Vr = np.zeros((P, P))   # Σ B_rᵀ H_r B_r, in both V and S
        if has_rot:
            pre += ch.Hr[[0, 1, 2], [0, 1, 2]]
            U += ch.Hr
            rhs[:, 3:6] = ch.Hr
            rhs[:, k - 1] += ch.gr
            if ch.hr_f is not None:
                _add_rotation_moments(Vr, ch)
            else:
                _add_rotation_block(Vr, ch.Hr, mm(ch.Hr, ch.Ra), ch.Ra)
        for i in range(3):
            U[i, i] += lam * pre[i]
        L = cholesky3(U)
        Zs = sym_solve3(L, rhs, transpose=False)
        f = _features(ch)
        if residuals is not None:
            residuals[0][sl] = ch.r_out.T
            residuals[1][sl, 0:3] = r_ap.T
            residuals[1][sl, 3:6] = r_ar.T
        kept = ChunkFactors(sl, np.array(L, dtype=np.float32), Zs.astype(np.float32))
        cost = np.vdot(ch.r_out, ch.r_out) + np.vdot(r_ap, r_ap) + np.vdot(r_ar, r_ar)
        # Σ B_pᵀ Q_e B_p from moments: weighted by q_e per pair, or Q_e applied at the end
        F = f @ f.T
        Fe = (f * q_e) @ f.T if iso and weighted else F
        return F, Fe, Vr, gram(_coupling(Zs, ch, P)), _sum_gradient(frame, ch, hp), cost, [kept]

    F, Fe, Vr, ZZ, g, cost, factors.chunks = _sum_chunks(chunk, problem.n)
    if iso and not weighted:  # q_e is one scalar for all pairs
        Qe = eliminated(1.0)[2] * np.eye(3)
    elif iso:
        Qe = np.eye(3)
    T = frame.T
    S = T.T @ (frame.gram(Fe, Qe) + Vr - ZZ[:P, :P]) @ T
    b = T.T @ (-g + ZZ[:P, P])
    v_diag = np.diag(T.T @ (frame.gram(F, Qp_bar) + Vr) @ T).copy()
    if not (np.isfinite(S).all() and np.isfinite(b).all()):
        raise ConvergenceError('the linearised TLS system is not finite (a sample or an input '
                               'weight is inf or NaN, or the noise is zero); check the pairs '
                               'and the noise settings')
    return S, b, v_diag, float(cost), factors


def _input_weights(problem, sl: slice):
    """Per-pair weights w (c,) on A's information (1 / a_scale, from A's interpolation), or 1."""
    return 1.0 if problem.a_scale is None else 1.0 / problem.a_scale[sl]


def _input_position(frame: _Frame, xp: np.ndarray, pos_a: np.ndarray, w) -> tuple:
    """A's whitened input position residual r_ap (3, c), unweighted, and its gradient w·g_ap."""
    r_ap = frame.Lap @ (xp - pos_a)
    gap = frame.Lap.T @ r_ap
    gap *= w  # (w = 1.0: exact, the same numbers)
    return r_ap, gap


def residuals_into(problem, params: Parameters, x, out: tuple) -> None:
    """
    Fill ``out`` with the whitened output (N, m) and input (N, 6) residuals at (x, φ).

    The residuals ``tls_schur`` writes, by the same arithmetic chunk by chunk (the same
    numbers to the bit), in a light pass: a fit needs them only at its solution, so its
    linearisations need not hold them (183 MB at 2M pairs) on the way there.
    """
    frame = _Frame.of(problem, params)
    for sl in problem.chunks():
        pos_a, quat_a, pos_b, quat_b = _chunk_of(problem, sl)
        xp, xq = x.pos_t[:, sl], x.quat_t[:, sl]
        r_out = _channels(frame, xp, xq, pos_b, quat_b, matrices=False).r_out
        w = _input_weights(problem, sl)
        r_ap = _input_position(frame, xp, pos_a, w)[0]
        r_ar = _rotation_information(frame.Lar, error_quaternion(xq, quat_a * CONJ), None,
                                     matrices=False)[0]
        if problem.a_scale is not None:
            r_ap *= np.sqrt(w)
            r_ar *= np.sqrt(w)
        out[0][sl] = r_out.T
        out[1][sl, 0:3] = r_ap.T
        out[1][sl, 3:6] = r_ar.T


def _scaled_skew(q, c: np.ndarray, out: np.ndarray) -> None:
    """Write ``q [c]×`` (q scalar or (n,), c (3, n)) into ``out[:, 0:3]`` (3, k, n)."""
    x, y, z = c
    out[0, 0] = out[1, 1] = out[2, 2] = 0.0
    np.multiply(q, -z, out=out[0, 1])
    np.multiply(q, y, out=out[0, 2])
    np.multiply(q, z, out=out[1, 0])
    np.multiply(q, -x, out=out[1, 2])
    np.multiply(q, -y, out=out[2, 0])
    np.multiply(q, x, out=out[2, 1])


def _coupling(Zs: np.ndarray, ch: _Chunk, P: int) -> np.ndarray:
    """``[Z_W | Z_g]`` (3, P+1, c) from ``Zs = L⁻¹[N | H_r | g̃_θ]``: Z_W = Z_N B_p + Z_H B_r."""
    Zn = Zs[:, 0:3]
    out = np.empty((3, P + 1, Zs.shape[2]))
    out[:, 0:3] = Zn
    # -Z_N [v]×: row a is v × (row a of Z_N), for the three rows at once
    v0, v1, v2 = ch.v
    z0, z1, z2 = Zn[:, 0], Zn[:, 1], Zn[:, 2]
    out[:, 3] = v1 * z2 - v2 * z1
    out[:, 4] = v2 * z0 - v0 * z2
    out[:, 5] = v0 * z1 - v1 * z0
    np.einsum('abn,bcn->acn', Zn, ch.Ra, out=out[:, 6:9])
    if P == 12:
        out[:, 3:6] += Zs[:, 3:6]
        np.einsum('abn,bcn->acn', Zs[:, 3:6], ch.Ra, out=out[:, 9:12])
    out[:, P] = Zs[:, -1]
    return out


def closed_form_back_substitute(n: int, factors: TlsFactors, delta_phi: np.ndarray,
                                kept: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Input corrections of a parameter step, from the factors of ``tls_schur``.

    ``δθ_A = -L⁻ᵀ(Z_g + Z_N B_p δφ' + Z_H B_r δφ')``, then
    ``δp_A = -M_p(g_p + g_ap - Q̄p[c]× δθ_A + Q̄p B_p δφ')``.

    Parameters
    ----------
    n : int
        Number of pairs N.
    factors : TlsFactors
        The factors ``tls_schur`` returned.
    delta_phi : ndarray, shape (P,)
        The parameter step in reduced coordinates.
    kept : ndarray of int, shape (K,), optional
        Increasing indices of the pairs whose corrections are wanted (None: all).

    Returns
    -------
    dx : ndarray, shape (6, N) or (6, K)
        (δp_A in m, δθ_A in rad) per pair, pair-last.

    """
    d = factors.T @ delta_phi
    dx = Columns(n, kept)
    for ch in factors.chunks:
        L = tuple(ch.L.astype(float))
        Z = ch.Z.astype(float)
        Ra, c, v = factors.geometry(ch.pairs)
        g_pos, m = factors.position_terms(ch.pairs, v)
        Bp = d[0:3, None] - cross(v, np.broadcast_to(d[3:6, None], v.shape)) \
            + np.einsum('abn,b->an', Ra, d[6:9])
        rhs = np.einsum('abn,bn->an', Z[:, 0:3], Bp) + Z[:, -1]
        if len(d) == 12:
            Br = d[3:6, None] + np.einsum('abn,b->an', Ra, d[9:12])
            rhs += np.einsum('abn,bn->an', Z[:, 3:6], Br)
        dth = -sym_solve3(L, rhs, transpose=True)
        y = g_pos + factors.Qp_bar @ (Bp - cross(c, dth))
        dx.put(ch.pairs, -(factors.Mp @ y) if m is None else -(m * y), slice(0, 3))
        dx.put(ch.pairs, dth, slice(3, 6))
    return dx.out
