"""
Normal equations of full-pose and position-only problems through their block structure.

The generic code in ``ols`` and ``tls`` forms every pair's Jacobian blocks and multiplies them as
stacks of small matrices. For one marker (full pose, position only) with noise that does not
correlate position and rotation (block-diagonal whitening, the usual case), the same normal
equations (Ikits eqs. 36, 42) follow from far less work:

- Every pair is written in *channels* expressed in A's base frame: the position channel
  ``ε_p = R0ᵀ e_p`` (information ``Q̄p = R0ᵀ Qp R0``, one 3×3 matrix for all pairs) and the
  rotation channel, whose linearisation depends on the parameters and the input only through
  the total left perturbation ``t = θ0' + δθ_A + R_A θ1`` (information
  ``H_r = (D R0)ᵀ Q_r (D R0)`` with D the §3.2 metric's Jacobian, eq. 15). In the parameter
  coordinates ``φ' = (R0ᵀ δp0, R0ᵀ δθ0, δp1, δθ1)`` a pair's Jacobian is
  ``B_p = [I, -[v]×, R_A, 0]`` and ``B_r = [0, I, 0, R_A]`` with ``v = p_A + R_A p1``; φ' maps
  to the reduced-quaternion φ by one constant block-diagonal matrix T.
- The position part of ``Σ B_pᵀ Q B_p`` (Q constant) is a contraction of the 13×13 moment
  matrix of ``f = (1, v, R_A)``, one matrix product over the pairs.
- TLS (B.2): the input position enters linearly with a constant information block, so it is
  eliminated in closed form (one constant 3×3 inverse, Schur complement ``Q_e``); only a 3×3
  block per pair remains for the input rotation, factored by closed-form Cholesky. Per pair
  that is a few dozen vector operations on arrays with the pair index last, instead of 6×6
  factorisations with 13 right-hand sides.

The results equal the generic path's to rounding (``test_structured.py`` compares them, damped
and undamped); ``applies`` says when this path is valid. This module holds the channels and
OLS; ``normal_equations_tls`` the TLS Schur complement and back-substitution.
"""

from __future__ import annotations

from dataclasses import dataclass
import functools
import operator
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.estimator.pair_algebra import (
    CONJ,
    cross,
    error_quaternion,
    left,
    metric_jacobian,
    mm,
    tmm,
)
from coreg_ros.core.estimator.problem import chunk_slices
from coreg_ros.core.models import Parameters, tangent_of_chart
import numpy as np


def applies(problem, inputs: bool = True) -> bool:
    """
    Tell whether the structured path computes this problem's normal equations.

    True for full-pose and position-only models whose noise does not correlate position
    with rotation (block-diagonal whitening of both devices). With ``inputs`` (TLS), per-pair
    weights on A's noise (``a_scale``) also need isotropic position noise of both devices, so
    that eliminating the input position stays a scalar per pair.
    """
    if problem.spec.name not in ('full_pose', 'position_only'):
        return False
    if not (_block_diagonal(problem.whiten_a) and _block_diagonal(problem.whiten_b)):
        return False
    return (not inputs or problem.a_scale is None
            or (_scalar(problem.whiten_b[0:3, 0:3]) is not None
                and _scalar(problem.whiten_a[0:3, 0:3]) is not None))


def _block_diagonal(L: np.ndarray) -> bool:
    """Tell whether L (3×3 or 6×6) has no position-rotation cross blocks."""
    return L.shape == (3, 3) or (not L[0:3, 3:6].any() and not L[3:6, 0:3].any())


# ----------------------------------------------------------------------------------------------
# Per-chunk channels
# ----------------------------------------------------------------------------------------------

@dataclass
class _Frame:
    """Constants of one linearisation: φ, whitening blocks and the φ' -> φ map."""

    params: Parameters
    has_rot: bool
    P: int
    Lp: np.ndarray
    Lr: Optional[np.ndarray]
    Lap: np.ndarray
    Lar: np.ndarray
    Qp_bar: np.ndarray
    T: np.ndarray
    xi: np.ndarray
    q_model: np.ndarray

    @classmethod
    def of(cls, problem, params: Parameters) -> _Frame:
        spec = problem.spec
        has_rot = spec.has_q1
        P = spec.n_params
        Lb, La = problem.whiten_b, problem.whiten_a
        R0 = params.R0
        Lp = Lb[0:3, 0:3]
        T = np.zeros((P, P))
        T[0:3, 0:3] = R0.T
        T[3:6, 3:6] = R0.T @ tangent_of_chart(params.q0, params.dq0)
        T[6:9, 6:9] = np.eye(3)
        if has_rot:
            T[9:12, 9:12] = tangent_of_chart(params.q1, params.dq1)
        return cls(params, has_rot, P, Lp, Lb[3:6, 3:6] if has_rot else None, La[0:3, 0:3],
                   La[3:6, 3:6], R0.T @ (Lp.T @ Lp) @ R0, T, _moment_map(P),
                   # q0 ⊗ q_A ⊗ q1 as one constant 4×4 matrix on q_A
                   quat.left_matrix(params.q0) @ quat.right_matrix(params.q1))

    def gram(self, F: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """``Σ B_pᵀ Q B_p`` (P×P, φ' coordinates) from the moments F = Σ f fᵀ."""
        path = _gram_path(self.xi.shape, Q.shape, F.shape)
        return np.einsum(_GRAM, self.xi, Q, self.xi, F, optimize=path)


_GRAM = 'akl,ab,bjm,lm->kj'


@functools.cache
def _gram_path(xi_shape: tuple, q_shape: tuple, f_shape: tuple) -> list:
    """
    Return the contraction order ``np.einsum(optimize=True)`` picks for ``gram``'s shapes.

    Found once: the same order, so the same numbers; searching it anew cost more than the
    contraction on a small fit (the offset search fits 1.5k-pair subsamples several times).
    """
    xi = np.empty(xi_shape)
    return np.einsum_path(_GRAM, xi, np.empty(q_shape), xi, np.empty(f_shape),
                          optimize=True)[0]


@functools.cache  # a constant per P; read-only, shared by every linearisation
def _moment_map(P: int) -> np.ndarray:
    """Ξ (3, P, 13) with ``B_p[a, k] = Σ_l Ξ[a, k, l] f_l``, ``f = (1, v, vec R_A)``."""
    xi = np.zeros((3, P, 13))
    eps = np.zeros((3, 3, 3))
    eps[0, 1, 2] = eps[1, 2, 0] = eps[2, 0, 1] = 1.0
    eps[0, 2, 1] = eps[2, 1, 0] = eps[1, 0, 2] = -1.0
    for a in range(3):
        xi[a, a, 0] = 1.0                       # p0': I
        for j in range(3):
            for lv in range(3):
                xi[a, 3 + j, 1 + lv] = -eps[a, lv, j]   # θ0': -[v]×
            xi[a, 6 + j, 4 + 3 * a + j] = 1.0   # p1: R_A
    xi.setflags(write=False)
    return xi


@dataclass
class _Chunk:
    """Channel quantities of the pairs of one chunk (pair index last)."""

    Ra: np.ndarray      # (3, 3, c) input orientations
    c: np.ndarray       # (3, c) R_A p1
    v: np.ndarray       # (3, c) p_A + R_A p1
    r_out: np.ndarray   # (m, c) whitened output residuals
    gp: np.ndarray      # (3, c) R0ᵀ Qp e_p
    Hr: Optional[np.ndarray]   # (3, 3, c) rotation channel information
    gr: Optional[np.ndarray]   # (3, c) rotation channel gradient
    # isotropic rotation noise: H_r = h (I - f fᵀ) with h = w²/4 (the moment form of the
    # θ0', θ1 blocks needs only these); None otherwise
    hr_f: Optional[np.ndarray] = None   # (3, c)
    hr_scale: Optional[float] = None


def _scalar(L: np.ndarray) -> Optional[float]:
    """
    Return w if L = w·I to rounding (isotropic noise), else None.

    A relative tolerance of 1e-12 admits covariances that went through a message or a file;
    the closed forms then differ from the exact ones by as little.
    """
    w = float(L[0, 0])
    # |L - w I| <= atol elementwise, as np.allclose(rtol=0) decides it, without its ~70 µs of
    # overhead (called a few times per chunk); non-finite entries go to allclose itself
    dev = np.abs(L - w * np.eye(len(L))).max()
    if np.isfinite(dev):
        return w if dev <= 1e-12 * abs(w) else None
    return w if np.allclose(L, w * np.eye(len(L)), rtol=0.0, atol=1e-12 * abs(w)) else None


def _rotation_information(L: np.ndarray, E: np.ndarray, R: Optional[np.ndarray],
                          matrices: bool = True):
    """
    Whitened residual, information and gradient of a rotation error E (4, c) (§3.2).

    The metric ``e = vec(E)`` is perturbed by ``E ← Exp(R t) ⊗ E``, so ``∂e/∂t = D R`` with
    D of eq. 15. Returns ``r = L e`` (3, c), ``H = (D R)ᵀ Lᵀ L (D R)`` (3, 3, c) and
    ``g = (D R)ᵀ Lᵀ r`` (3, c). For isotropic L = w·I these are closed forms: with
    ``f = Rᵀ e``, ``H = w²/4 (I - f fᵀ)`` (since DᵀD = (I - e eᵀ)/4 for a unit E) and
    ``g = w²/2 E_w f``. ``R`` None stands for the identity. Without ``matrices``, H is None
    for isotropic L (OLS sums it from moments, ``_add_rotation_moments``). The fourth value is
    f (3, c) for isotropic L, the moment form's vector, and None otherwise.
    """
    ev = E[1:]
    w = _scalar(L)
    if w is None:
        r = L @ ev
        D = metric_jacobian(E)
        X = left(L, D if R is None else np.einsum('abn,bc->acn', D, R))
        return r, tmm(X, X), np.einsum('ban,bn->an', X, r), None
    f = ev if R is None else R.T @ ev
    g = (0.5 * w * w * E[0]) * f
    if not matrices:
        return w * ev, None, g, f
    H = np.empty((3, 3, E.shape[1]))
    quarter = 0.25 * w * w
    for i in range(3):
        for j in range(i + 1):
            H[i, j] = H[j, i] = -quarter * f[i] * f[j]
        H[i, i] += quarter
    return w * ev, H, g, f


def _channels(frame: _Frame, pos_a, qa, pos_b, quat_b, matrices: bool = True) -> _Chunk:
    """
    Residuals and channel Jacobians of a chunk, all pair-last: inputs (3, c), (4, c).

    Without ``matrices``, ``Hr`` is None where the moment form (``hr_f``) replaces it.
    """
    Ra = quat.to_matrix(qa, pair_last=True)
    c = frame.params.markers[0] @ Ra   # Σ_b R_A[a, b] p1[b], (3, c)
    v = pos_a + c
    r_p, gp = position_residual(frame, v, pos_b)
    if not frame.has_rot:
        return _Chunk(Ra, c, v, r_p, gp, None, None)
    E = error_quaternion(frame.q_model @ qa, quat_b)
    r_r, Hr, gr, f = _rotation_information(frame.Lr, E, frame.params.R0, matrices)
    out = _Chunk(Ra, c, v, np.concatenate([r_p, r_r]), gp, Hr, gr)
    if f is not None:   # isotropic Lr = w I: H_r = w²/4 (I - f fᵀ)
        w = float(frame.Lr[0, 0])
        out.hr_f, out.hr_scale = f, 0.25 * w * w
    return out


def position_residual(frame: _Frame, v: np.ndarray, pos_b: np.ndarray) -> tuple:
    """
    Whitened position residual r_p (3, c) and its gradient g_p = R0ᵀ L_pᵀ r_p (3, c).

    ``v = p_A + R_A p1`` (3, c) per pair, ``pos_b`` B's positions (3, c), m.
    """
    R0 = frame.params.R0
    e_p = (frame.params.p0[:, None] + R0 @ v) - pos_b
    r_p = frame.Lp @ e_p
    return r_p, (R0.T @ frame.Lp.T) @ r_p


def _features(ch: _Chunk) -> np.ndarray:
    """Moment features ``f = (1, v, vec R_A)`` per pair, (13, c)."""
    return np.concatenate([np.ones((1, ch.v.shape[1])), ch.v, ch.Ra.reshape(9, -1)])


def _pair_sum(M: np.ndarray) -> np.ndarray:
    """Sum over the pairs (last axis) of a C-contiguous stack, as one matrix-vector product."""
    return (M.reshape(-1, M.shape[-1]) @ np.ones(M.shape[-1])).reshape(M.shape[:-1])


def _transposed_apply(Ra: np.ndarray, h: np.ndarray) -> np.ndarray:
    """``Σ_pairs R_Aᵀ h`` (3,) for matrices (3, 3, c) and vectors (3, c), by matrix products."""
    return sum(Ra[a] @ h[a] for a in range(3))


def _sum_gradient(frame: _Frame, ch: _Chunk, hp: np.ndarray) -> np.ndarray:
    """``Σ (B_pᵀ hp + B_rᵀ gr)`` over the chunk, (P,) in φ' coordinates."""
    g = np.zeros(frame.P)
    g[0:3] = _pair_sum(hp)
    g[3:6] = _pair_sum(cross(ch.v, hp))
    g[6:9] = _transposed_apply(ch.Ra, hp)
    if frame.has_rot:
        g[3:6] += _pair_sum(ch.gr)
        g[9:12] = _transposed_apply(ch.Ra, ch.gr)
    return g


def _add_rotation_moments(M: np.ndarray, ch: _Chunk, w: Optional[np.ndarray] = None):
    """
    Add ``Σ w B_rᵀ H_r B_r`` to M in place for isotropic rotation noise, from moments.

    With ``H_r = h (I - f fᵀ)`` and ``u = R_Aᵀ f``: ``Σ H_r = h (Σ1·I - Σ f fᵀ)``,
    ``Σ H_r R_A = h (Σ R_A - Σ f uᵀ)`` and ``Σ R_Aᵀ H_r R_A = h (Σ1·I - Σ u uᵀ)``
    (R_Aᵀ R_A = I to rounding): one 6×6 moment matrix of (f, u) instead of 3×3 products per
    pair. ``w`` (c,) weights the pairs (None: all 1).
    """
    f, Ra = ch.hr_f, ch.Ra
    fu = np.empty((6, f.shape[1]))
    fu[0:3] = f
    u = fu[3:6]     # u[b] = Σ_a R_A[a, b] f[a]
    np.multiply(Ra[0], f[0], out=u)
    u += Ra[1] * f[1]
    u += Ra[2] * f[2]
    if w is None:
        G = fu @ fu.T
        total = float(f.shape[1])
        s_ra = _pair_sum(Ra)
    else:
        G = (fu * w) @ fu.T
        total = float(w.sum())
        s_ra = (Ra.reshape(9, -1) @ w).reshape(3, 3)
    h = ch.hr_scale
    eye = total * np.eye(3)
    M[3:6, 3:6] += h * (eye - G[0:3, 0:3])
    M[3:6, 9:12] += h * (s_ra - G[0:3, 3:6])
    M[9:12, 3:6] = M[3:6, 9:12].T
    M[9:12, 9:12] += h * (eye - G[3:6, 3:6])


def _add_rotation_block(M: np.ndarray, Hr: np.ndarray, HrRa: np.ndarray, Ra: np.ndarray):
    """
    Add ``Σ B_rᵀ H_r B_r`` (the θ0', θ1 blocks, ``B_r = [0, I, 0, R_A]``) to M in place.

    Blocks: ``Σ H_r``, ``Σ H_r R_A`` and ``Σ R_Aᵀ H_r R_A``.
    """
    M[3:6, 3:6] += _pair_sum(Hr)
    M[3:6, 9:12] += _pair_sum(HrRa)
    M[9:12, 3:6] = M[3:6, 9:12].T
    # Σ_a R_A[a]ᵀ (H_r R_A)[a] as three (3, c)(c, 3) matrix products (3× faster than einsum)
    M[9:12, 9:12] += sum(Ra[a] @ HrRa[a].T for a in range(3))


def _chunk_of(problem, sl: slice) -> tuple:
    """
    Pair-last copies of the measured pairs in ``sl``.

    Returns p_A (3, c), q_A (4, c), p_B (3, c) and q_B* (4, c): B's orientations conjugated,
    as the error quaternions use them. Copied per chunk (a few µs), not cached on the
    problem: a cache would cost 112 B per pair for the problem's lifetime.
    """
    def t(a):
        return np.ascontiguousarray(a[sl].T)
    q_b = None if problem.quat_b is None else t(problem.quat_b) * CONJ
    return t(problem.pos_a), t(problem.quat_a), t(problem.pos_b), q_b


def _sum_chunks(fn, n: int) -> list:
    """
    Apply ``fn`` to every chunk of pairs and add up what it returns, term by term.

    (Linearising chunks in two threads was tried: slower, as the GIL is held between the
    short numpy calls and BLAS threads oversubscribe the two cores.)
    """
    parts = [fn(sl) for sl in chunk_slices(n)]
    return [functools.reduce(operator.add, terms) for terms in zip(*parts, strict=True)]


def _weighted(M: Optional[np.ndarray], w: np.ndarray) -> Optional[np.ndarray]:
    """Per-pair weights on a pair-last stack (None stays None)."""
    return None if M is None else M * w


# ----------------------------------------------------------------------------------------------
# OLS (B.1)
# ----------------------------------------------------------------------------------------------

def ols_normal(problem, params: Parameters, residuals: Optional[np.ndarray] = None):
    """
    JᵀJ, Jᵀr and the cost of the whitened output residuals at φ (Ikits eqs. 32-36).

    Parameters
    ----------
    problem : Problem
        One for which ``applies`` is true. With ``problem.weights`` (N,), pair i's terms
        count w_i times (0 leaves a pair out, -1 takes it back out of a sum) while every
        pair's residuals are still given: the robust fit tests the pairs it left out.
    params : Parameters
        The calibration φ the sums are taken at.
    residuals : ndarray, shape (N, m), optional
        Filled with the whitened output residuals.

    Returns
    -------
    H : ndarray, shape (P, P)
    g : ndarray, shape (P,)
        Jᵀr, the half-gradient of the cost.
    cost : float

    """
    frame = _Frame.of(problem, params)
    weights = getattr(problem, 'weights', None)

    def chunk(sl):
        ch = _channels(frame, *_chunk_of(problem, sl), matrices=False)
        f = _features(ch)
        if residuals is not None:
            residuals[sl] = ch.r_out.T
        r2 = ch.r_out
        w = None
        if weights is not None:
            w = weights[sl]
            fw, ch.gp, r2 = f * w, ch.gp * w, ch.r_out * w
            if ch.gr is not None:
                ch.gr = ch.gr * w
        else:
            fw = f
        H = np.zeros((frame.P, frame.P))
        if frame.has_rot and ch.hr_f is not None:
            _add_rotation_moments(H, ch, w)
        elif frame.has_rot:
            Hr = _weighted(ch.Hr, w) if w is not None else ch.Hr
            _add_rotation_block(H, Hr, mm(Hr, ch.Ra), ch.Ra)
        return (fw @ f.T, H, _sum_gradient(frame, ch, ch.gp),
                np.vdot(r2, ch.r_out))

    F, H, g, cost = _sum_chunks(chunk, problem.n)
    H += frame.gram(F, frame.Qp_bar)
    T = frame.T
    return T.T @ H @ T, T.T @ g, float(cost)
