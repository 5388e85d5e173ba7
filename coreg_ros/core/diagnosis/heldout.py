"""
Held-out predictions of a fitted model, without refitting from scratch.

Cross-validation on blocks (contiguous in time, or cells of the workspace): the normal
equations are accumulated per block at the all-data solution (``Pass``), and the solution
without block k is one Gauss-Newton step away, ``δ_k = -(H - H_k)⁻¹ (g - g_k)``; the
variance parameters are refitted on the other blocks. Each pair is then predicted by the fit
without its block.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.calibration.observability import WEAK_SHARE
from coreg_ros.core.diagnosis import variance as vm
import numpy as np


@dataclass
class Pass:
    """One pass over the pairs: normal equations, -2 log L, stats (and optional per-block)."""

    H: np.ndarray
    g: np.ndarray
    obj: float
    stats: vm.PairStats
    folds: Optional[np.ndarray]
    Hk: Optional[np.ndarray]
    gk: Optional[np.ndarray]
    kept: Optional[list]


@dataclass
class Heldout:
    """
    Held-out predictions of every pair (each by the fit without its block).

    Attributes
    ----------
    ll : ndarray, shape (n,)
        Log-likelihood of each pair under the model fitted without its block.
    quad_stated : ndarray, shape (n,)
        Squared normalized error under the stated noise (chi-square with m dof if it holds).
    quad : ndarray, shape (n,)
        The same under the fitted noise model (inlier part).
    p_in : ndarray, shape (n,)
        Probability of being an inlier (1 without the outlier effect).
    e : ndarray, shape (n, m)
        Raw held-out output errors.

    """

    folds: np.ndarray
    n_folds: int
    ll: np.ndarray
    quad_stated: np.ndarray
    quad: np.ndarray
    p_in: np.ndarray
    e: np.ndarray
    var_k: list

    def fold_sums(self, values: np.ndarray) -> np.ndarray:
        """Sum of values per fold."""
        return np.bincount(self.folds, weights=values, minlength=self.n_folds)


def predict_blocks(fit, folds: np.ndarray, n_folds: int) -> Heldout:
    """
    Held-out evaluation on blocks: each block predicted by the fit on the others.

    Parameters
    ----------
    fit : fit.Fit
        The fitted model (its last pass is reused when it has these blocks).
    folds : ndarray of int, shape (len(fit.idx),)
        Block of each pair of ``fit.idx``.
    n_folds : int
        Number of blocks.

    Returns
    -------
    Heldout

    """
    model, state, idx = fit.model, fit.state, fit.idx
    last = fit.last
    if last is None or last.folds is not folds or last.Hk is None:
        last = model.normal(state, idx, folds, n_folds)
    H, g, stats, Hk, gk = last.H, last.g, last.stats, last.Hk, last.gk
    deltas = np.zeros((n_folds, model.n_mean))
    var_k = []
    for k in range(n_folds):
        train = folds != k
        deltas[k] = -solve_psd(H - Hk[k], g - gk[k])
        if model.var_names and train.any():
            var_k.append(vm.fit_variance(stats.take(train), state.var, model.var_names,
                                         step=0.03))
        else:
            var_k.append(state.var)
    n = len(idx)
    m = model.data.m
    ll = np.zeros(n)
    quad0 = np.zeros(n)
    quad = np.zeros(n)
    p_in = np.ones(n)
    e_out = np.zeros((n, m))
    pos = 0
    evals = last.kept if last.kept is not None else (
        model.evaluate(state, ch) for ch in model.chunks(idx))
    for ev in evals:
        st, Jz, e, T = ev.st, ev.Jz, ev.e, ev.T
        c = len(e)
        fo = folds[pos:pos + c]
        dz = np.einsum('nij,nj->ni', Jz, deltas[fo])
        zc = st.z + dz
        # raw error correction e + J δ: z = T e, so δe = T⁻¹ δz
        e_out[pos:pos + c] = e + np.linalg.solve(T, dz[:, :, None])[:, :, 0]
        stc = st.with_z(zc)
        quad0[pos:pos + c] = np.sum(zc ** 2 / (1.0 + st.lam), axis=1)
        for k in np.unique(fo):
            sel = fo == k
            sub = stc.take(sel)
            lk, pk, qk = vm.loglik(var_k[k], sub, with_parts=True)
            ll[pos:pos + c][sel] = lk
            p_in[pos:pos + c][sel] = pk
            quad[pos:pos + c][sel] = qk
        pos += c
    return Heldout(folds=folds, n_folds=n_folds, ll=ll, quad_stated=quad0, quad=quad,
                   p_in=p_in, e=e_out, var_k=var_k)


def solve_psd(A: np.ndarray, b: np.ndarray, weak: float = WEAK_SHARE) -> np.ndarray:
    """
    Solve a symmetric PSD system along the directions it determines; leave the others still.

    ``A`` is scaled to unit diagonal; its eigen-directions whose eigenvalue is at most
    ``weak`` times the largest carry no information worth the name (a rig that cannot turn
    about some axis, an effect whose term the calibration absorbs there: only the noise of A's
    orientations lends them some, ``calibration.observability``) and get no step. A step
    along them would only amplify noise: held-out blocks predicted along a direction no block
    determines would make any extension of the model look better than the base.

    Parameters
    ----------
    A : ndarray, shape (p, p)
        Symmetric positive semi-definite.
    b : ndarray, shape (p,)
        The right-hand side.
    weak : float
        Share of the largest scaled eigenvalue at or below which a direction is undetermined
        (the calibration's ``WEAK_SHARE``).

    Returns
    -------
    ndarray, shape (p,)
        The solution in the determined subspace (minimum norm in the scaled coordinates).

    """
    d = np.sqrt(np.clip(np.diag(A), 0.0, None))
    scale = np.where(d > 0, d, 1.0)
    try:
        w, V = np.linalg.eigh(A / np.outer(scale, scale))
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(A, b, rcond=1e-12)[0]
    keep = w > weak * max(float(w[-1]), 0.0)
    Vk = V[:, keep]
    return (Vk @ ((Vk.T @ (b / scale)) / w[keep])) / scale
