"""
Per-pair linearisation at the measured input: the one place that weighs a pair on its own.

Both estimators reduce, pair by pair and to first order, to one weighted output error: the
error at the *measured* input ``e = f(x̃, φ) - ŷ`` with the effective covariance
``Σ_eff = Σ_y + s F_x Σ_x F_xᵀ`` (OLS: ``Σ_eff = Σ_y``; TLS: the input noise carried through
the model, Ikits eq. 52, with ``s`` the interpolation factor ``a_var_scale``). This is what
eliminating a TLS input block leaves (the Schur complement of one pair), so it serves

- the robust fit: a pair's normalised squared residual ``d² = eᵀ Σ_eff⁻¹ e ~ χ²_m``;
- the time offset: A's interpolated pose moves with its velocity, ``∂x̃/∂τ = -ẋ_A``, so the
  offset's column is ``c = -F_x ẋ_A`` (the predicted marker velocity, negated).

Error metric and units as in ``models``: positions m, rotation metric about half the angle.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.estimator.problem import CHUNK
from coreg_ros.core.models import linearize, Parameters
import numpy as np


@dataclass(frozen=True)
class PairData:
    """
    Pairs as the linearisation needs them.

    Attributes
    ----------
    pos_a : ndarray, shape (N, 3)
        A's tool position in A's base frame (measured, interpolated), m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientation, (w, x, y, z).
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
    quat_b : ndarray, shape (N, 4) or None
    cov_a : ndarray, shape (6, 6)
        Covariance of A's noise in the ROS layout (position m², rotation angle rad²): the
        input perturbation of ``models.linearize`` is a rotation vector (the full angle), not
        the half-angle error metric.
    cov_b : ndarray, shape (m, m)
        Covariance of B's output error metric.
    a_scale : ndarray, shape (N,) or None
        Factor on A's covariance per pair.
    tls : bool
        Whether A's noise enters (errors in both devices).

    """

    pos_a: np.ndarray
    quat_a: np.ndarray
    pos_b: np.ndarray
    quat_b: Optional[np.ndarray]
    cov_a: np.ndarray
    cov_b: np.ndarray
    a_scale: Optional[np.ndarray]
    tls: bool

    def __len__(self) -> int:
        return int(self.pos_a.shape[0])

    def take(self, idx: np.ndarray) -> PairData:
        """Return the pairs ``idx`` (indices, shape (K,)) with the same noise, a copy."""
        def sub(x):
            return None if x is None else np.take(x, idx, axis=0)

        return PairData(sub(self.pos_a), sub(self.quat_a), sub(self.pos_b), sub(self.quat_b),
                        self.cov_a, self.cov_b, sub(self.a_scale), self.tls)


@dataclass(frozen=True)
class Chunk:
    """
    Linearisation of the pairs in ``sl``.

    Attributes
    ----------
    sl : slice
    e : ndarray, shape (n, m)
        Output error at the measured input.
    j_phi : ndarray, shape (n, m, P)
    j_x : ndarray, shape (n, m, 6)
        ∂e/∂x over (p_A, δ_A), δ_A a rotation of A's tool in A's base frame.
    cov : ndarray, shape (n, m, m) or (m, m)
        Σ_eff (one matrix for all pairs when A's noise does not enter).

    """

    sl: slice
    e: np.ndarray
    j_phi: np.ndarray
    j_x: np.ndarray
    cov: np.ndarray

    def weighted(self, rhs: np.ndarray) -> np.ndarray:
        """Σ_eff⁻¹ rhs for rhs of shape (n, m, k): a batched solve, not an inverse."""
        if self.cov.ndim == 2:
            return np.einsum('ij,njk->nik', np.linalg.inv(self.cov), rhs)
        return np.linalg.solve(self.cov, rhs)


def chunks(params: Parameters, data: PairData, chunk: int = CHUNK) -> Iterator[Chunk]:
    """Linearise the pairs chunk by chunk (see the module docstring)."""
    n = len(data)
    for start in range(0, n, chunk):
        sl = slice(start, min(n, start + chunk))
        quat_b = None if data.quat_b is None else data.quat_b[sl]
        e, j_phi, j_x = linearize(params, data.pos_a[sl], data.quat_a[sl], data.pos_b[sl],
                                  quat_b, with_input=True)
        cov = data.cov_b
        if data.tls:
            cov = j_x @ data.cov_a @ np.swapaxes(j_x, 1, 2)
            if data.a_scale is not None:
                cov *= data.a_scale[sl, None, None]
            cov += data.cov_b
        yield Chunk(sl, e, j_phi, j_x, cov)


def reference_squares(params: Parameters, data: PairData) -> np.ndarray:
    """
    d² = eᵀ Σ_eff⁻¹ e per pair, shape (N,): χ²_m distributed when the model holds.

    Parameters
    ----------
    params : Parameters
        The calibration to test the pairs against.
    data : PairData
        The pairs.

    """
    out = np.empty(len(data))
    for ch in chunks(params, data):
        out[ch.sl] = np.einsum('ni,ni->n', ch.e, ch.weighted(ch.e[:, :, None])[:, :, 0])
    return out
