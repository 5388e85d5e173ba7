"""
The shape of B's position noise: larger along some axes of B's own frame than along others.

An optical tracker measures depth worse than across its view, an EM tracker one field axis
worse than the others: B's position noise covariance is then ``σ² S`` with S a symmetric
positive 3×3 matrix in B's base frame (the stated noise is S = I). In the coordinates the
likelihood uses (``variance.py``: z = Vᵀ W e, W B's whitening), B's whitened noise has the
covariance M = blockdiag(S for each marker, I for the orientation), and a pair's error

    Cov(zᵢ) = s² (gᵢ Vᵢᵀ M Vᵢ + diag λᵢ) + β uᵢ uᵢᵀ

(noise scale s², distance noise gᵢ, A's carried noise λᵢ, jitter β) is no longer diagonal:
its quadratic form and log-determinant come from a Cholesky factor per pair. S is fitted by
expectation-maximisation: with bᵢ B's whitened noise and zᵢ = Vᵢᵀ bᵢ + (the rest),
``E[bᵢ bᵢᵀ | zᵢ]`` averaged over the pairs (and the markers) is the next M.
"""

from __future__ import annotations

import numpy as np

#: Iterations of the expectation-maximisation of S (each one batched solve per pair).
EM_ITERATIONS = 30
#: ... or until S changes by less than this (relative, largest element).
EM_TOL = 1e-4


def shape_matrix(params: tuple) -> np.ndarray:
    """Return S (3, 3) from its six upper-triangular values (xx, yy, zz, xy, xz, yz)."""
    xx, yy, zz, xy, xz, yz = params
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]], dtype=float)


def shape_params(S: np.ndarray) -> tuple:
    """Return the six upper-triangular values of a symmetric S (3, 3)."""
    return (float(S[0, 0]), float(S[1, 1]), float(S[2, 2]), float(S[0, 1]), float(S[0, 2]),
            float(S[1, 2]))


def whitened_block(S: np.ndarray, m: int, n_markers: int) -> np.ndarray:
    """M (m, m): S for each marker's position rows, the identity for the orientation rows."""
    M = np.eye(m)
    for j in range(n_markers):
        M[3 * j:3 * j + 3, 3 * j:3 * j + 3] = S
    return M


def covariances(M: np.ndarray, V: np.ndarray, lam: np.ndarray, s2: float, g: np.ndarray,
                beta: float, u: np.ndarray) -> np.ndarray:
    """
    Covariance of each pair's decorrelated error, (n, m, m).

    Parameters
    ----------
    M : ndarray, shape (m, m)
        B's whitened noise covariance (``whitened_block``).
    V : ndarray, shape (n, m, m)
        Per pair, the rotation from B's whitened output to the decorrelated coordinates
        (z = Vᵀ W e).
    lam : ndarray, shape (n, m)
        A's carried noise in the decorrelated coordinates.
    s2 : float
        The noise scale's variance factor.
    g : ndarray, shape (n,)
        Distance noise factor on B's variance per pair.
    beta : float
        Jitter variance σ_t², s².
    u : ndarray, shape (n, m)
        Output rate in the decorrelated coordinates, 1/s.

    """
    C = np.matmul(np.transpose(V, (0, 2, 1)), np.matmul(M, V)) * g[:, None, None]
    idx = np.arange(lam.shape[1])
    C[:, idx, idx] += lam
    C *= s2
    if beta > 0.0:
        C += beta * u[:, :, None] * u[:, None, :]
    return C


def quadratic_logdet(C: np.ndarray, z: np.ndarray) -> tuple:
    """Return zᵀ C⁻¹ z and log det C per pair (n,), and the Cholesky factors (n, m, m)."""
    L = np.linalg.cholesky(C)
    y = np.linalg.solve(L, z[:, :, None])[:, :, 0]
    logdet = 2.0 * np.sum(np.log(np.diagonal(L, axis1=1, axis2=2)), axis=1)
    return np.sum(y * y, axis=1), logdet, L


def fit_shape(z: np.ndarray, V: np.ndarray, lam: np.ndarray, weight: np.ndarray, s2: float,
              g: np.ndarray, beta: float, u: np.ndarray, S0: np.ndarray,
              n_markers: int) -> np.ndarray:
    """
    Maximum-likelihood S by expectation-maximisation, the other noise parameters held.

    Parameters
    ----------
    z, V, lam, u : ndarray
        The pairs' statistics (``covariances``).
    weight : ndarray, shape (n,)
        Each pair's weight (its probability of being an inlier).
    s2, g, beta : float, ndarray, float
        The other noise parameters (held).
    S0 : ndarray, shape (3, 3)
        Start.
    n_markers : int
        Markers (position blocks) per pair.

    Returns
    -------
    ndarray, shape (3, 3)

    """
    m = z.shape[1]
    S = S0.copy()
    wsum = max(float(np.sum(weight)), 1e-300)
    for _ in range(EM_ITERATIONS):
        M = whitened_block(S, m, n_markers)
        C = covariances(M, V, lam, s2, g, beta, u)
        # B's whitened noise b = V z-part: its covariance gᵢ s² M, its cross-covariance with
        # z is gᵢ s² M Vᵢ; E[b bᵀ | z] = P - K Vᵀ P + (K z)(K z)ᵀ with P = gᵢ s² M
        # with P = gᵢ s² M (the scale taken out: E below is of the unscaled noise)
        c = (s2 * g)[:, None, None]
        MV = np.matmul(M, V)                                         # (n, m, m)
        K = np.linalg.solve(C, np.transpose(MV, (0, 2, 1))) * c      # C⁻¹ Vᵀ P
        Kz = np.matmul(np.transpose(K, (0, 2, 1)), z[:, :, None])[:, :, 0]   # Kᵀ z
        E = M[None] - np.matmul(MV, K) + Kz[:, :, None] * Kz[:, None, :] / c
        blocks = sum(E[:, 3 * j:3 * j + 3, 3 * j:3 * j + 3] for j in range(n_markers))
        new = np.einsum('n,nij->ij', weight, blocks) / (wsum * n_markers)
        new = 0.5 * (new + new.T)
        done = float(np.max(np.abs(new - S))) < EM_TOL * max(float(np.max(np.abs(S))), 1e-12)
        S = new
        if done:
            break
    return S
