"""
Weighted OLS (Ikits B.1) and errors-in-variables TLS (B.2) by Levenberg-Marquardt.

Both work through the pairs in chunks, so memory stays O(chunk) above the O(N) state, and time
is O(N) per iteration:

- OLS accumulates the normal equations ``JᵀJ δφ = -Jᵀg`` (eq. 36) chunk by chunk.
- TLS treats every input pose as a parameter (eq. 42). Its normal matrix is block-arrowhead:
  one 6×6 block ``U_i`` per pair, coupled to φ by ``W_i`` (6×P). Eliminating the per-pair
  blocks (Schur complement) leaves a P×P system ``S δφ = b`` with
  ``S = V - Σ W_iᵀ U_i⁻¹ W_i``; the input corrections follow pair by pair,
  ``δx_i = U_i⁻¹(-g_i - W_i δφ)``. No dense (6N+P)² matrix ever exists. The posterior
  covariance of φ is ``S⁻¹`` (the φ block of the inverse, B.4.2).

Residuals are whitened (eq. 29-30): ``r = L e`` with ``W = LᵀL``; the chi-square is ``Σ r²``
(eq. 57).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core import batched
from coreg_ros.core.estimator import normal_equations as structured
from coreg_ros.core.models import (
    error_rotation_jacobian,
    linearize,
    ModelSpec,
    Parameters,
)
import numpy as np

#: Pairs processed at once; bounds the transient memory (about 3 KB per pair in a chunk).
CHUNK = 4096

#: A prior term returns whitened residual rows (k,) and their Jacobian (k, P) at φ (Ikits B.3).
PriorTerm = Callable[[Parameters], tuple]


@dataclass
class Problem:
    """
    A calibration problem: pairs, noise whitening and optional priors.

    Attributes
    ----------
    spec : ModelSpec
    pos_a : ndarray, shape (N, 3)
    quat_a : ndarray, shape (N, 4)
        Unit quaternions (w, x, y, z), as ``calibrate`` validates them; the closed forms of
        ``structured`` rely on unit length.
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
    quat_b : ndarray, shape (N, 4) or None
        Unit quaternions, or None for position-only models.
    whiten_b : ndarray, shape (m, m)
        L_y with ``L_yᵀ L_y`` the inverse covariance of the output error metric.
    whiten_a : ndarray, shape (6, 6)
        L_x for the input error metric (TLS only).
    a_scale : ndarray, shape (N,) or None
        Per-pair factor on A's noise variance.
    priors : list of PriorTerm
    weights : ndarray, shape (N,) or None
        OLS on the structured path only: pair i's terms count w_i times (1 kept, 0 left
        out, its residuals still computed). TLS and the generic path take subsets instead.

    """

    spec: ModelSpec
    pos_a: np.ndarray
    quat_a: np.ndarray
    pos_b: np.ndarray
    quat_b: Optional[np.ndarray]
    whiten_b: np.ndarray
    whiten_a: np.ndarray
    a_scale: Optional[np.ndarray] = None
    priors: list = field(default_factory=list)
    weights: Optional[np.ndarray] = None

    def __post_init__(self):
        # Diagonal output whitening (independent noise per axis, the usual case) is applied by
        # broadcasting instead of a batched matrix product.
        self.diag_b = _diagonal_or_none(self.whiten_b)

    def whiten_out(self, M: np.ndarray) -> np.ndarray:
        """L_y M for a stack M of shape (c, m, k)."""
        return M * self.diag_b[:, None] if self.diag_b is not None else np.matmul(self.whiten_b, M)

    @property
    def n(self) -> int:
        """Return the number of pairs N."""
        return len(self.pos_a)

    @property
    def n_fitted(self) -> int:
        """Return the number of pairs the fit counts (N, or the number of non-zero weights)."""
        return self.n if self.weights is None else int(np.count_nonzero(self.weights))

    def chunks(self):
        """Slices of at most CHUNK pairs covering all pairs."""
        return structured.chunk_slices(self.n, CHUNK)

    def output(self, sl: slice):
        """Measured output of the pairs in ``sl``."""
        return self.pos_b[sl], None if self.quat_b is None else self.quat_b[sl]


@dataclass(frozen=True)
class Solution:
    """
    Outcome of a solver run.

    Attributes
    ----------
    params : Parameters
    cov : ndarray, shape (P, P) or None
        Posterior covariance of φ (eq. 58; TLS: inverse Schur complement).
    info : ndarray, shape (P, P)
        Information matrix JᵀJ (OLS) or Schur complement S (TLS) at the solution.
    chi2 : float
    n_rows : int
        Residual rows beyond the input blocks: N·m plus prior rows.
    residuals : ndarray, shape (N, m)
        Whitened output residuals.
    input_residuals : ndarray, shape (N, 6) or None
        Whitened input residuals (TLS).
    iterations : int
    status : int
        1 step small, 2 cost change small, 0 iteration limit, -1 no acceptable step.
    message : str
    inputs : InputState or None
        TLS: the estimated inputs at the solution (a warm start for a refit of nearly the
        same pairs).
    gradient : ndarray, shape (P,) or None
        OLS: Jᵀr at the solution (with ``info`` and ``chi2``, the normal equations there).
    sums : TlsSums or None
        TLS on the structured path: the last linearisation, for a refit of fewer pairs.

    """

    params: Parameters
    cov: Optional[np.ndarray]
    info: np.ndarray
    chi2: float
    n_rows: int
    residuals: np.ndarray
    input_residuals: Optional[np.ndarray]
    iterations: int
    status: int
    message: str
    inputs: Optional[InputState] = None
    gradient: Optional[np.ndarray] = None
    sums: Optional[TlsSums] = None


def _diagonal_or_none(L: np.ndarray):
    """Return the diagonal of L if L is diagonal, else None."""
    return np.diag(L).copy() if np.count_nonzero(L - np.diag(np.diag(L))) == 0 else None


def _prior_rows(problem: Problem, params: Parameters):
    """Stacked prior residuals, Jacobian and count (Ikits eqs. 55-56)."""
    P = problem.spec.n_params
    if not problem.priors:
        return np.zeros(0), np.zeros((0, P))
    parts = [term(params) for term in problem.priors]
    return np.concatenate([r for r, _ in parts]), np.concatenate([j for _, j in parts])


def _inverse_or_none(info: np.ndarray) -> Optional[np.ndarray]:
    """Inverse of a symmetric information matrix, None if it is singular."""
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(cov).all() or (np.diag(cov) <= 0).any():
        return None
    return 0.5 * (cov + cov.T)


@dataclass
class _Linearization:
    """
    One linearisation of the problem for the LM driver.

    ``info`` is the (damped) normal matrix of φ, ``rhs`` its right-hand side (the step solves
    ``info δ = rhs``), ``cost`` the cost at the linearisation point. ``propose(δ, λ')``
    returns the trial state, its cost and the linearisation at the trial made with damping λ'
    (or None): when the trial is accepted that linearisation is the next one, so evaluating a
    trial and linearising there is one pass over the pairs, not two.
    """

    info: np.ndarray
    rhs: np.ndarray
    cost: float
    propose: Callable
    residuals: Optional[tuple] = None
    damping_share: float = 0.0  # largest λ·V_jj / info_jj: how far info is from undamped
    factors: object = None      # TLS: the per-pair factors (for a refit's first step)


@dataclass(frozen=True)
class TlsSums:
    """
    A TLS linearisation kept for a refit: the damped reduced system, the cost, the damping.

    The sums are over pairs; a refit of the same pairs less a few starts from these sums less
    the removed pairs' terms (``solve_tls(seed=...)``), with the kept pairs' factors for its
    first input step, instead of a pass over all pairs.
    """

    S: np.ndarray
    b: np.ndarray
    cost: float
    lam: float
    factors: object   # structured.TlsFactors over the fit's pairs


def _levenberg_marquardt(state, linearize: Callable, max_iterations: int, xtol: float,
                         ftol: float, damping: float = 1e-6, first=None, min_steps: int = 0):
    """
    Levenberg-Marquardt iterations shared by OLS and TLS.

    Convergence: status 1 when the step is below ``xtol`` posterior standard deviations on
    every component (tested before a step is tried, so rounding noise at the optimum is never
    mistaken for a misfit, and after an accepted step); status 2 when the cost stops
    decreasing by more than ``ftol`` relative; 0 at the iteration limit; -1 when no damping
    gives a decrease although the step is not small (the model does not fit).

    Returns
    -------
    state, status, iterations, last : _Linearization or None, lam : float
        ``last`` is the linearisation at the returned state, made with damping ``lam``
        (None if there is none).

    ``damping`` is the first λ (lower for a start next to the minimum); ``first``, if given,
    is the linearisation at ``state`` with that damping (made by the caller without a pass).
    ``min_steps`` accepted steps come before a small step may prove convergence: TLS from the
    measured inputs must move them at least once, since a small step of φ says nothing about
    the inputs (whose adjustment lowers the cost by about the input noise's share of chi2).

    """
    lam = damping
    lin = linearize(state, lam) if first is None else first
    for it in range(1, max_iterations + 1):
        rejected = False
        while True:
            delta = np.linalg.lstsq(lin.info, lin.rhs, rcond=None)[0]
            # Only a step damped as little as the last accepted one may prove convergence: a
            # damping raised by rejections shrinks any step below xtol·σ eventually.
            if not rejected and it > min_steps and _step_is_small(delta, lin.info, xtol):
                return state, 1, it, lin, lam
            lam_next = max(lam / 10.0, 1e-12)
            # the residuals at the current state are not needed while the trial is made
            # (a return after a rejection re-linearises): their memory goes first
            lin.residuals = None
            trial, new_cost, trial_lin = lin.propose(delta, lam_next)
            if np.isfinite(new_cost) and new_cost <= lin.cost:
                break
            trial_lin = None  # release the rejected trial's per-pair factors
            if new_cost - lin.cost <= ftol * max(lin.cost, 1.0):
                return state, 2, it, lin, lam
            if lam * 10.0 > 1e16:
                return state, -1, it, lin, lam
            rejected = True
            lam *= 10.0
            lin = None
            lin = linearize(state, lam)
        state, old, lam = trial, lin, lam_next
        lin = None
        lin = trial_lin if trial_lin is not None else linearize(state, lam)
        if _step_is_small(delta, old.info, xtol):
            return state, 1, it, lin, lam
        if old.cost - new_cost <= ftol * max(new_cost, 1.0):
            return state, 2, it, lin, lam
    return state, 0, max_iterations, lin, lam


def _step_is_small(delta: np.ndarray, info: np.ndarray, xtol: float) -> bool:
    """Tell whether every |δ_j| <= xtol · σ_j, σ from the inverse of ``info``."""
    cov = _inverse_or_none(info)
    return cov is not None and bool(np.all(np.abs(delta) <= xtol * np.sqrt(np.diag(cov))))


#: Default convergence tolerance: stop when the next step would move every parameter by at
#: most this many of its posterior standard deviations. 1e-5 σ is far below anything a
#: statistic can see (scipy's default, 1e-8 relative to |φ|, is ~1e-2 σ at 100k pairs) and
#: lets TLS stop at the linearisation that proves convergence instead of taking one more
#: step of ~1e-7 σ and a whole pass over the pairs to evaluate it.
XTOL = 1e-5

#: A converged TLS linearisation serves as the posterior information (saving a pass over
#: the pairs) only when its damping adds at most this share to any diagonal element. The
#: share is λ·V_jj/S_jj, not λ: the Schur complement S can be far smaller than V = Σ BᵀB
#: when A is much noisier than B.
DAMPING_SHARE = 1e-6


# ----------------------------------------------------------------------------------------------
# OLS (B.1)
# ----------------------------------------------------------------------------------------------

def _ols_normal(problem: Problem, params: Parameters, residuals: Optional[np.ndarray] = None):
    """
    JᵀJ, Jᵀr and the cost at φ (eqs. 32-36), priors included, chunk by chunk.

    ``residuals`` (N, m), if given, is filled with the whitened output residuals.
    """
    if structured.applies(problem, inputs=False):
        H, g, cost = structured.ols_normal(problem, params, residuals)
    elif problem.weights is not None:
        raise ValueError('pair weights need the structured path (structured.applies)')
    else:
        P = problem.spec.n_params
        H = np.zeros((P, P))
        g = np.zeros(P)
        cost = 0.0
        L = problem.whiten_b
        for sl in problem.chunks():
            pos_b, quat_b = problem.output(sl)
            e, j_phi, _ = linearize(params, problem.pos_a[sl], problem.quat_a[sl], pos_b,
                                    quat_b, with_input=False)
            r = e @ L.T
            J = problem.whiten_out(j_phi).reshape(-1, P)
            H += J.T @ J
            g += J.T @ r.reshape(-1)
            cost += float(np.sum(r * r))
            if residuals is not None:
                residuals[sl] = r
    r_prior, j_prior = _prior_rows(problem, params)
    H += j_prior.T @ j_prior
    g += j_prior.T @ r_prior
    cost += float(r_prior @ r_prior)
    return H, g, cost


def solve_ols(problem: Problem, params: Parameters, max_iterations: int = 100,
              xtol: Optional[float] = None, ftol: float = 1e-12,
              normal: Optional[tuple] = None) -> Solution:
    """
    Weighted OLS by Levenberg-Marquardt with Marquardt's diagonal scaling.

    Parameters
    ----------
    problem : Problem
        The whitened problem.
    params : Parameters
        Initial φ (e.g. from ``initialize``).
    max_iterations : int
        Largest number of Gauss-Newton iterations.
    xtol : float, optional
        Stop when every |δφ_j| <= xtol · σ_j (default ``XTOL``).
    ftol : float
        Stop when the relative cost decrease is below ftol.
    normal : tuple, optional
        (H, g, cost, residuals) of this problem at ``params``, when the caller has them
        (e.g. a robust refit: the last fit's sums less the pairs it now leaves out), which
        saves the first pass over the pairs.

    Returns
    -------
    Solution
        With ``problem.weights``, ``residuals`` holds every pair's residuals.

    """
    xtol = XTOL if xtol is None else xtol
    # (state, H, g, cost, residuals) of the current state and the last trial
    normals = [] if normal is None else [(params, *normal)]

    def normal_at(state: Parameters):
        for entry in normals:
            if entry[0] is state:  # re-damping needs no new pass over the pairs
                normals.remove(entry)
                normals.append(entry)  # the most recently used stays when a trial is added
                return entry
        res = _pair_last(problem.n, problem.spec.n_res)
        entry = (state, *_ols_normal(problem, state, res), res)
        normals[:] = normals[-1:] + [entry]
        return entry

    def linearize(state: Parameters, lam: float) -> _Linearization:
        _, H, g, cost, res = normal_at(state)

        def propose(delta, lam_next):
            trial = state.stepped(delta)
            if not trial.valid:
                return trial, np.inf, None
            trial = trial.recharted()
            lin = linearize(trial, lam_next)
            return trial, lin.cost, lin

        return _Linearization(H + lam * np.diag(np.diag(H)), -g, cost, propose)

    params, status, it, _, _ = _levenberg_marquardt(params, linearize, max_iterations, xtol,
                                                    ftol)
    # JᵀJ does not depend on the damping: the linearisation at the solution gives the
    # posterior information and the residuals (Ikits B.4.2)
    _, H, g, cost, res = normal_at(params)
    n_prior = len(_prior_rows(problem, params)[0])
    return Solution(params, _inverse_or_none(H), H, cost,
                    problem.n_fitted * problem.spec.n_res + n_prior,
                    res, None, it, status, _status_message(status, it, xtol), gradient=g)


# ----------------------------------------------------------------------------------------------
# TLS (B.2) with the Schur complement over the per-pair input blocks
# ----------------------------------------------------------------------------------------------

class InputState:
    """
    The TLS estimates of the inputs x_i = (p_A, q_A), stored pair-last: (3, N) and (4, N).

    ``pos`` and ``quat`` are the (N, 3) and (N, 4) views. Each orientation is stepped
    multiplicatively, ``q ← Exp(δ) ⊗ q``: a chart centred at the current estimate (the limit
    of §3.1's re-charting), so no per-pair chart bookkeeping is needed and every input block
    is equally well conditioned.
    """

    def __init__(self, pos: np.ndarray, quats: np.ndarray):
        self.pos_t = np.ascontiguousarray(np.asarray(pos, dtype=float).T)
        self.quat_t = np.ascontiguousarray(np.asarray(quats, dtype=float).T)

    @property
    def pos(self) -> np.ndarray:
        """Input positions, (N, 3) view."""
        return self.pos_t.T

    @property
    def quat(self) -> np.ndarray:
        """Input orientations, (N, 4) view."""
        return self.quat_t.T

    @classmethod
    def _pair_last(cls, pos_t: np.ndarray, quat_t: np.ndarray) -> InputState:
        """Wrap pair-last arrays (3, N) and (4, N) without copying them."""
        out = cls.__new__(cls)
        out.pos_t, out.quat_t = pos_t, quat_t
        return out

    def stepped(self, dx: np.ndarray) -> InputState:
        """Return the state after the step dx (6, N) = (δp, δθ), pair-last."""
        return InputState._pair_last(self.pos_t + dx[0:3],
                                     structured.rotated(self.quat_t, dx[3:6]))


def _tls_blocks(problem: Problem, params: Parameters, x: InputState, sl: slice):
    """
    Whitened residuals and Jacobian blocks of the pairs in ``sl`` (eqs. 44, 48, 49).

    Returns r_x (c, 6), r_y (c, m), A_x (c, 6, 6), A_y (c, m, 6), B (c, m, P).
    """
    pos_b, quat_b = problem.output(sl)
    e_y, j_phi, j_x = linearize(params, x.pos[sl], x.quat[sl], pos_b, quat_b, with_input=True)
    ex_rot, dex = error_rotation_jacobian(x.quat[sl], problem.quat_a[sl])
    e_x = np.concatenate([x.pos[sl] - problem.pos_a[sl], ex_rot], axis=1)
    Lx = problem.whiten_a
    A_x = np.empty((len(e_x), 6, 6))
    A_x[:, :, 0:3] = Lx[:, 0:3]
    A_x[:, :, 3:6] = Lx[:, 3:6] @ dex
    r_x = e_x @ Lx.T
    if problem.a_scale is not None:
        w = 1.0 / np.sqrt(problem.a_scale[sl])
        r_x = r_x * w[:, None]
        A_x = A_x * w[:, None, None]
    return r_x, e_y @ problem.whiten_b.T, A_x, problem.whiten_out(j_x), problem.whiten_out(j_phi)


def _damped(U: np.ndarray, lam: float) -> np.ndarray:
    """U + λ diag(U) for a stack of 6×6 blocks."""
    if lam == 0.0:
        return U
    U = U.copy()
    idx = np.arange(6)
    U[:, idx, idx] *= 1.0 + lam
    return U


def _tls_schur(problem: Problem, params: Parameters, x: InputState, lam: float,
               residuals: Optional[tuple] = None):
    """
    Reduced system S δφ = b and the cost at (x, φ), chunk by chunk (Schur complement).

    With ``U_i = L_i L_iᵀ`` (batched Cholesky of the damped 6×6 input blocks) and
    ``Z_i = L_i⁻¹ [W_i | g_i]``, ``S = Σ B_iᵀB_i - Σ Z_iᵀZ_i`` (W and g parts). Only the
    factors and Z are kept per pair, for ``back_substitute``. Priors and the damping of the φ
    block are added by the caller.

    Returns
    -------
    S : ndarray, shape (P, P)
    b : ndarray, shape (P,)
    v_diag : ndarray, shape (P,)
        diag(Σ BᵀB), the scale of the φ damping.
    cost : float
    factors : list
        Per-chunk (L, Z) for ``back_substitute``.

    """
    P = problem.spec.n_params
    S = np.zeros((P, P))
    v_diag = np.zeros(P)
    b = np.zeros(P)
    cost = 0.0
    factors = []
    for sl in problem.chunks():
        r_x, r_y, A_x, A_y, B = _tls_blocks(problem, params, x, sl)
        A = np.concatenate([A_x, A_y], axis=1)  # (c, 6 + m, 6)
        At = np.ascontiguousarray(A.transpose(0, 2, 1))
        U = At @ A
        # [W_i | g_i] = A_yᵀ [B_i | r_y,i] + [0 | A_xᵀ r_x,i], in one product
        Wg = At[:, :, 6:] @ np.concatenate([B, r_y[:, :, None]], axis=2)
        Wg[:, :, P] += (At[:, :, :6] @ r_x[:, :, None])[:, :, 0]
        L = batched.cholesky(_damped(U, lam))
        Z = batched.solve_lower(L, np.ascontiguousarray(Wg.transpose(1, 2, 0)))  # (6, P+1, c)
        # The factors are kept only for the input back-substitution. Stored in float32 they
        # take 9 instead of 17 bytes of each 1 KB per pair; S and b below are accumulated in
        # float64 first, so δφ is exact and only the input corrections δx_i carry a relative
        # error of ~1e-7, which the next linearisation absorbs (an inexact Newton step in x).
        factors.append(([[None if v is None else v.astype(np.float32) for v in row] for row in L],
                        Z.astype(np.float32)))
        B2 = B.reshape(-1, P)
        Zt = Z.transpose(0, 2, 1).reshape(-1, P + 1)  # rows (k, pair)
        ZW, Zg = Zt[:, :P], Zt[:, P]
        S += B2.T @ B2 - ZW.T @ ZW
        v_diag += np.einsum('ij,ij->j', B2, B2)
        b += -(B2.T @ r_y.reshape(-1)) + ZW.T @ Zg
        cost += float(np.sum(r_x ** 2) + np.sum(r_y ** 2))
        if residuals is not None:
            residuals[0][sl], residuals[1][sl] = r_y, r_x
    return S, b, v_diag, cost, factors


def back_substitute(problem: Problem, factors: list, delta_phi: np.ndarray) -> np.ndarray:
    """Input corrections ``δx_i = -U_i⁻¹(g_i + W_i δφ) = -L_i⁻ᵀ(Z_g,i + Z_W,i δφ)``, (6, N)."""
    if isinstance(factors, structured.TlsFactors):
        return structured.back_substitute(problem.n, factors, delta_phi)
    dx = np.empty((6, problem.n))
    for sl, (L, Z) in zip(problem.chunks(), factors, strict=True):
        rhs = Z[:, :-1, :].transpose(0, 2, 1) @ delta_phi + Z[:, -1, :]  # (6, c), float64
        dx[:, sl] = -batched.solve_upper_t(L, rhs[:, None, :])[:, 0, :]
    return dx


def tls_linearization(problem: Problem, params: Parameters, x: InputState, lam: float):
    """
    Linearise TLS at (x, φ): the damped reduced system with priors, cost and residuals.

    The structured path (``structured.applies``) and the generic one give the same system.

    Returns
    -------
    S : ndarray, shape (P, P)
        Damped Schur complement (undamped when λ = 0: the posterior information).
    b : ndarray, shape (P,)
    cost : float
    residuals : tuple of ndarray
        Whitened output (N, m) and input (N, 6) residuals.
    factors
        For ``back_substitute``.
    damping_share : float
        Largest share of the φ damping in a diagonal element of S, max_j λ·V_jj / S_jj.

    """
    if problem.weights is not None:
        raise ValueError('TLS takes subsets of the pairs, not pair weights (Problem.weights)')
    residuals = (_pair_last(problem.n, problem.spec.n_res), _pair_last(problem.n, 6))
    schur = structured.tls_schur if structured.applies(problem) else _tls_schur
    S, b, v_diag, cost, factors = schur(problem, params, x, lam, residuals)
    r_prior, j_prior = _prior_rows(problem, params)
    damping = lam * (v_diag + np.einsum('ij,ij->j', j_prior, j_prior))
    S = S + j_prior.T @ j_prior + np.diag(damping)
    b = b - j_prior.T @ r_prior
    share = float(np.max(damping / np.diag(S))) if lam > 0 else 0.0
    return S, b, cost + float(r_prior @ r_prior), residuals, factors, share


def solve_tls(problem: Problem, params: Parameters, max_iterations: int = 100,
              xtol: Optional[float] = None, ftol: float = 1e-12,
              inputs: Optional[InputState] = None, damping: float = 1e-6,
              seed: Optional[tuple] = None) -> Solution:
    """
    Errors-in-variables TLS (Ikits B.2) by Levenberg-Marquardt on the Schur complement.

    The inputs start at their measured values; damping λ·diag is applied to both the per-pair
    blocks and the φ block, so a damped step is the exact minimiser of the damped linearised
    problem. Time and memory per iteration are O(N).

    Parameters
    ----------
    problem : Problem
        The whitened problem.
    params : Parameters
        Initial φ, e.g. the OLS solution.
    max_iterations : int
        Largest number of iterations.
    xtol, ftol : float
        As in ``solve_ols``.
    inputs : InputState, optional
        Where the input estimates start (default: the measured inputs). The inputs of a fit
        of nearly the same pairs (``Solution.inputs``) start a refit next to its solution;
        the minimum and the stopping rule are the same from any start.
    damping : float
        First λ. A start next to the minimum (a refit) needs little: with λ small the
        linearisation at the solution is also the posterior information (``DAMPING_SHARE``)
        instead of needing one more pass at λ = 0.
    seed : tuple, optional
        ``(sums, dx)``: the linearisation at (``params``, ``inputs``) with damping ``damping``
        (a ``TlsSums`` of exactly this problem's pairs, e.g. a fit's sums less the removed
        pairs' terms; its factors, if any, are released after the first step) and ``dx(δφ)``
        giving the inputs' step (6, N) from it. The first step then needs no pass over the
        pairs.

    Returns
    -------
    Solution

    """
    def linearize(state, lam: float) -> _Linearization:
        phi, x = state
        S, b, cost, residuals, factors, share = tls_linearization(problem, phi, x, lam)

        def propose(delta, lam_next):
            trial = phi.stepped(delta)
            if not trial.valid:
                return state, np.inf, None
            trial = (trial.recharted(), x.stepped(back_substitute(problem, factors, delta)))
            factors.clear()  # spent: free them before the trial's are made
            lin = linearize(trial, lam_next)
            return trial, lin.cost, lin

        return _Linearization(S, b, cost, propose, residuals, share, (factors, lam))

    def seeded(sums: TlsSums, dx_of: Callable) -> _Linearization:
        phi, x = state

        def propose(delta, lam_next):
            trial = phi.stepped(delta)
            if not trial.valid:
                return state, np.inf, None
            trial = (trial.recharted(), x.stepped(dx_of(delta)))
            if sums.factors is not None:
                sums.factors.clear()  # spent: free them before the trial's are made
            lin = linearize(trial, lam_next)
            return trial, lin.cost, lin

        # residuals None: if this very state is returned, the posterior is made afresh
        return _Linearization(sums.S, sums.b, sums.cost, propose)

    cold = inputs is None  # inputs at their measured values: they must move at least once
    if cold:
        inputs = InputState(problem.pos_a, problem.quat_a)
    elif inputs.pos_t.shape != (3, problem.n):
        raise ValueError(f'inputs for {inputs.pos_t.shape[1]} pairs, problem has {problem.n}')
    state = (params, inputs)
    xtol = XTOL if xtol is None else xtol
    first = None if seed is None else seeded(*seed)
    (params, x), status, it, last, lam = _levenberg_marquardt(
        state, linearize, max_iterations, xtol, ftol, damping, first, min_steps=int(cold))
    if status > 0 and last.residuals is not None and last.damping_share <= DAMPING_SHARE:
        # Converged within xtol·σ (or on a flat cost), and the linearisation at the solution
        # is almost undamped: its Schur complement is the posterior information (relative
        # change of the covariance below DAMPING_SHARE), which saves a pass over the pairs.
        info, chi2, (res_y, res_x) = last.info, last.cost, last.residuals
        sums = TlsSums(last.info, last.rhs, last.cost, lam, last.factors[0])
    else:
        last = None
        info, b, chi2, (res_y, res_x), factors, _ = tls_linearization(problem, params, x, 0.0)
        sums = TlsSums(info, b, chi2, 0.0, factors)
    if not (isinstance(sums.factors, structured.TlsFactors) and sums.factors.chunks):
        # a refit from sums needs the structured factors (back_substitution by n), intact
        # (a rejected last trial spent them)
        sums = None
    n_prior = len(_prior_rows(problem, params)[0])
    return Solution(params, _inverse_or_none(info), info, chi2,
                    problem.n * problem.spec.n_res + n_prior, res_y, res_x, it, status,
                    _status_message(status, it, xtol), x, sums=sums)


def _pair_last(n: int, m: int) -> np.ndarray:
    """Return an (n, m) array stored pair-last (chunks of pair-last rows copy in at once)."""
    return np.empty((m, n)).T


def _status_message(status: int, iterations: int, xtol: float) -> str:
    return {
        1: f'converged in {iterations} iterations: steps below {xtol:g} standard deviations',
        2: f'converged in {iterations} iterations: cost no longer decreases',
        0: f'stopped at the iteration limit ({iterations}) before converging; raise '
           f'max_iterations or check the noise settings',
        -1: f'no step reduced the cost after {iterations} iterations; the model does not '
            f'fit the data (check stream directions and units)',
    }[status]
