"""
Errors-in-variables TLS (Ikits B.2) by Levenberg-Marquardt on the Schur complement.

TLS treats every input pose as a parameter (eq. 42). Its normal matrix is block-arrowhead:
one 6×6 block ``U_i`` per pair, coupled to φ by ``W_i`` (6×P). Eliminating the per-pair
blocks (Schur complement) leaves a P×P system ``S δφ = b`` with ``S = V - Σ W_iᵀ U_i⁻¹ W_i``;
the input corrections follow pair by pair, ``δx_i = U_i⁻¹(-g_i - W_i δφ)`` (``back_substitute``).
No dense (6N+P)² matrix ever exists, and time and memory per iteration are O(N). The posterior
covariance of φ is ``S⁻¹`` (the φ block of the inverse, B.4.2).

The per-pair blocks are formed here for any model (``_tls_blocks``, factored by the batched
Cholesky of ``batched``), or in closed form by ``normal_equations_tls.tls_schur`` where that
applies; both give the same reduced system.
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core.estimator import (
    batched,
    normal_equations,
    normal_equations_tls,
)
from coreg_ros.core.estimator.lm import (
    levenberg_marquardt,
    Linearization,
    PAUSED,
    status_message,
    XTOL,
)
from coreg_ros.core.estimator.posterior import covariance, Solution
from coreg_ros.core.estimator.priors import gauge_diagonal, prior_rows
from coreg_ros.core.estimator.problem import chunk_slices, Columns, pair_last, Problem
from coreg_ros.core.estimator.state import InputState, TlsResume, TlsSeed, TlsSums
from coreg_ros.core.models import error_rotation_jacobian, linearize, Parameters
import numpy as np

#: A converged TLS linearisation serves as the posterior information (saving a pass over
#: the pairs) only when its damping adds at most this share to any diagonal element. The
#: share is λ·V_jj/S_jj, not λ: the Schur complement S can be far smaller than V = Σ BᵀB
#: when A is much noisier than B.
DAMPING_SHARE = 1e-6


def _tls_blocks(problem: Problem, params: Parameters, x: InputState, sl: slice):
    """
    Whitened residuals and Jacobian blocks of the pairs in ``sl`` (eqs. 44, 48, 49).

    Returns r_x (c, 6), r_y (c, m), A_x (c, 6, 6), A_y (c, m, 6), B (c, m, P).
    """
    pos_b, quat_b = problem.output(sl)
    e_y, j_phi, j_x = linearize(params, x.pos[sl], x.quat[sl], pos_b, quat_b, with_input=True)
    r_x, A_x = input_blocks(problem, x, sl)
    return r_x, e_y @ problem.whiten_b.T, A_x, problem.whiten_out(j_x), problem.whiten_out(j_phi)


def input_blocks(problem, x: InputState, sl: slice) -> tuple[np.ndarray, np.ndarray]:
    """
    A's whitened input residuals r_x (c, 6) and their Jacobian A_x (c, 6, 6) (eqs. 44, 49).

    ``problem`` is anything with A's measured ``pos_a``, ``quat_a``, ``whiten_a`` and
    ``a_scale`` (a ``Problem``; the instants shared by a rig's devices, ``rig.shared_instants``).
    """
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
    return r_x, A_x


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


def back_substitute(n: int, factors, delta_phi: np.ndarray,
                    kept: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Input corrections ``δx_i = -U_i⁻¹(g_i + W_i δφ)`` of a parameter step, (6, N) pair-last.

    Generic factors (``_tls_schur``): ``δx_i = -L_i⁻ᵀ(Z_g,i + Z_W,i δφ)`` with the batched
    Cholesky factors; structured ones (``normal_equations_tls.TlsFactors``): their closed form.

    Parameters
    ----------
    n : int
        Number of pairs N.
    factors : list or normal_equations_tls.TlsFactors
        The factors of the linearisation (``tls_linearization``).
    delta_phi : ndarray, shape (P,)
        The parameter step.
    kept : ndarray of int, shape (K,), optional
        Increasing indices of the pairs whose corrections are wanted (a refit of fewer
        pairs): (6, K), without the (6, N) array of all.

    """
    if isinstance(factors, normal_equations_tls.TlsFactors):
        return normal_equations_tls.closed_form_back_substitute(n, factors, delta_phi, kept)
    dx = Columns(n, kept)
    for sl, (L, Z) in zip(chunk_slices(n), factors, strict=True):
        rhs = Z[:, :-1, :].transpose(0, 2, 1) @ delta_phi + Z[:, -1, :]  # (6, c), float64
        dx.put(sl, -batched.solve_upper_t(L, rhs[:, None, :])[:, 0, :])
    return dx.out


def tls_residuals(problem: Problem, params: Parameters, x: InputState) -> tuple:
    """
    Return the whitened output (N, m) and input (N, 6) residuals at (x, φ), as linearised.

    A light pass on the structured path (``normal_equations_tls.residuals_into``); the same
    numbers to the bit as ``tls_linearization``'s.
    """
    out = (pair_last(problem.n, problem.spec.n_res), pair_last(problem.n, 6))
    if normal_equations.applies(problem):
        normal_equations_tls.residuals_into(problem, params, x, out)
    else:
        for sl in problem.chunks():
            r_x, r_y = _tls_blocks(problem, params, x, sl)[:2]
            out[0][sl], out[1][sl] = r_y, r_x
    return out


def tls_linearization(problem: Problem, params: Parameters, x: InputState, lam: float,
                      with_residuals: bool = True):
    """
    Linearise TLS at (x, φ): the damped reduced system with priors, cost and residuals.

    The structured path (``normal_equations.applies``) and the generic one give the same
    system.

    Parameters
    ----------
    problem : Problem
        The whitened problem (no pair weights: TLS takes subsets).
    params : Parameters
        φ at the linearisation point.
    x : InputState
        The input estimates at the linearisation point.
    lam : float
        The damping λ (0: the undamped posterior information).
    with_residuals : bool
        Also return the residuals (False: None, for the steps of a fit, which needs them only
        at its solution: ``tls_residuals``).

    Returns
    -------
    S : ndarray, shape (P, P)
        Damped Schur complement (undamped when λ = 0: the posterior information).
    b : ndarray, shape (P,)
    cost : float
    residuals : tuple of ndarray or None
        Whitened output (N, m) and input (N, 6) residuals.
    factors
        For ``back_substitute``.
    damping_share : float
        Largest share of the φ damping in a diagonal element of S, max_j λ·V_jj / S_jj.

    """
    if problem.weights is not None:
        raise ValueError('TLS takes subsets of the pairs, not pair weights (Problem.weights)')
    residuals = (pair_last(problem.n, problem.spec.n_res), pair_last(problem.n, 6)
                 ) if with_residuals else None
    schur = normal_equations_tls.tls_schur if normal_equations.applies(problem) else _tls_schur
    S, b, v_diag, cost, factors = schur(problem, params, x, lam, residuals)
    r_prior, j_prior = prior_rows(problem, params)
    # Marquardt's scale: the data's and the user's prior's diagonal, not the gauge's pins
    damping = lam * (v_diag + np.einsum('ij,ij->j', j_prior, j_prior)
                     - gauge_diagonal(problem, params))
    S = S + j_prior.T @ j_prior + np.diag(damping)
    b = b - j_prior.T @ r_prior
    share = float(np.max(damping / np.diag(S))) if lam > 0 else 0.0
    return S, b, cost + float(r_prior @ r_prior), residuals, factors, share


def solve_tls(problem: Problem, params: Parameters, max_iterations: int = 100,
              xtol: Optional[float] = None, ftol: float = 1e-12,
              inputs: Optional[InputState] = None, damping: float = 1e-6,
              seed: Optional[TlsSeed] = None, pause_at: Optional[int] = None,
              residuals: bool = True) -> Solution:
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
        of nearly the same pairs (``refit.carried_inputs``) start a refit next to its
        solution; the minimum and the stopping rule are the same from any start.
    damping : float
        First λ. A start next to the minimum (a refit) needs little: with λ small the
        linearisation at the solution is also the posterior information (``DAMPING_SHARE``)
        instead of needing one more pass at λ = 0.
    seed : TlsSeed, optional
        The linearisation at ``params`` (e.g. a fit's sums less the removed pairs' terms,
        ``refit.without_pairs``): the fit starts from its inputs with its damping (instead of
        ``inputs`` and ``damping``), and its first step needs no pass over the pairs.
    pause_at : int, optional
        Stop before trying the step of this iteration (``lm.levenberg_marquardt``): the
        Solution has status ``lm.PAUSED`` and that step and the linearisation in its resume
        state, from which a refit (``seed``) goes on without a new pass.
    residuals : bool
        Make the residuals at the solution (False: None, for a fit whose caller may refit
        before reading them; ``tls_residuals`` makes them later from the resume's inputs).

    Returns
    -------
    Solution
        Its resume state (``TlsResume``) holds the estimated inputs and, on the structured
        path, the last linearisation with its factors.

    """
    def linearize(state, lam: float) -> Linearization:
        phi, x = state
        # without residuals: the fit needs them at its solution only (tls_residuals)
        S, b, cost, _, factors, share = tls_linearization(problem, phi, x, lam,
                                                          with_residuals=False)

        def propose(delta, lam_next):
            trial = phi.stepped(delta)
            if not trial.valid:
                return state, np.inf, None
            step = back_substitute(problem.n, factors, delta)
            factors.clear()  # spent: freed before the trial's inputs and factors are made
            trial = (trial.recharted(), x.stepped(step))
            step = None
            lin = linearize(trial, lam_next)
            return trial, lin.cost, lin

        return Linearization(S, b, cost, propose, share, factors)

    def seeded(phi: Parameters, x: InputState, seed: TlsSeed) -> Linearization:
        def propose(delta, lam_next):
            trial = phi.stepped(delta)
            if not trial.valid:
                return (phi, x), np.inf, None
            step = back_substitute(seed.n_factored, seed.factors, delta, seed.kept)
            # spent, with the inputs of the fit they came from: freed before the trial's
            # inputs and factors are made
            seed.factors.clear()
            trial = (trial.recharted(), x.stepped(step))
            step = None
            lin = linearize(trial, lam_next)
            return trial, lin.cost, lin

        # not made here (fresh False): if this very state is returned, the posterior is made
        # afresh
        return Linearization(seed.sums.S, seed.sums.b, seed.sums.cost, propose, fresh=False)

    if seed is not None:
        if inputs is not None:
            raise ValueError('a seed brings its own inputs')
        inputs, damping = seed.inputs, seed.sums.lam
    cold = inputs is None  # inputs at their measured values: they must move at least once
    if cold:
        inputs = InputState(problem.pos_a, problem.quat_a)
    elif inputs.n != problem.n:
        raise ValueError(f'inputs for {inputs.n} pairs, problem has {problem.n}')
    xtol = XTOL if xtol is None else xtol
    # handed over: the driver alone holds the start, whose inputs go once it moves on
    start = [(params, inputs), None if seed is None else seeded(params, inputs, seed)]
    inputs = seed = None
    (params, x), status, it, last, lam = levenberg_marquardt(
        start.pop(0), linearize, max_iterations, xtol, ftol, damping, start.pop(),
        min_steps=int(cold), pause_at=pause_at)
    # linearize calls itself through its trials: a reference cycle that would hold the
    # problem (its pairs) until the cyclic collector ran; emptied, the cycle is gone now
    linearize = None
    paused = status == PAUSED  # the linearisation where it stopped is what goes on
    if paused or (status > 0 and last.fresh and last.damping_share <= DAMPING_SHARE):
        # Paused (the caller goes on from this linearisation), or converged within xtol·σ
        # (or on a flat cost) with the linearisation at the solution almost undamped: its
        # Schur complement is the posterior information (relative change of the covariance
        # below DAMPING_SHARE), which saves a pass over the pairs; the residuals there take
        # a light one (a paused fit goes on before anything reads them: none).
        info, chi2 = last.info, last.cost
        sums, factors = TlsSums(last.info, last.rhs, last.cost, lam), last.factors
        res_y, res_x = (None, None) if paused or not residuals else tls_residuals(
            problem, params, x)
    else:
        last = None
        info, b, chi2, made, factors, _ = tls_linearization(
            problem, params, x, 0.0, with_residuals=residuals)
        res_y, res_x = made if residuals else (None, None)
        sums = TlsSums(info, b, chi2, 0.0)
    if not (isinstance(factors, normal_equations_tls.TlsFactors) and factors.chunks):
        # a refit from sums needs the structured factors (back-substitution by n), intact
        # (a rejected last trial spent them)
        sums = factors = None
    n_prior = len(prior_rows(problem, params)[0])
    return Solution(params, covariance(info), info, chi2,
                    problem.n * problem.spec.n_res + n_prior, res_y, res_x, it, status,
                    status_message(status, it, xtol),
                    TlsResume(x, sums, factors, last.step if paused else None))
