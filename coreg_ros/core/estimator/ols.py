"""
Weighted OLS (Ikits B.1): A's poses exact, B's noisy.

The normal equations ``JᵀJ δφ = -Jᵀg`` (eq. 36) are accumulated chunk by chunk, so memory
stays O(chunk) above the O(N) state and time is O(N) per iteration: through the block
structure (``normal_equations.ols_normal``) for full-pose and position-only problems with
block-diagonal noise, through every pair's Jacobian (``models.linearize``) otherwise.
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core.estimator import normal_equations
from coreg_ros.core.estimator.lm import (
    levenberg_marquardt,
    Linearization,
    status_message,
    XTOL,
)
from coreg_ros.core.estimator.posterior import covariance, Solution
from coreg_ros.core.estimator.priors import gauge_diagonal, prior_rows
from coreg_ros.core.estimator.problem import pair_last, Problem
from coreg_ros.core.estimator.state import NormalEquations
from coreg_ros.core.models import linearize, Parameters
import numpy as np


def _ols_normal(problem: Problem, params: Parameters, residuals: Optional[np.ndarray] = None):
    """
    JᵀJ, Jᵀr and the cost at φ (eqs. 32-36), priors included, chunk by chunk.

    ``residuals`` (N, m), if given, is filled with the whitened output residuals.
    """
    if normal_equations.applies(problem, inputs=False):
        H, g, cost = normal_equations.ols_normal(problem, params, residuals)
    elif problem.weights is not None:
        raise ValueError('pair weights need the structured path (normal_equations.applies)')
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
    r_prior, j_prior = prior_rows(problem, params)
    H += j_prior.T @ j_prior
    g += j_prior.T @ r_prior
    cost += float(r_prior @ r_prior)
    return H, g, cost


def ols_information(problem: Problem, params: Parameters) -> np.ndarray:
    """
    Return the whitened JᵀJ of the problem at φ (its priors included), shape (P, P).

    One pass over the pairs (``_ols_normal``): what OLS would take as the posterior information
    at ``params``, e.g. to see which directions the data determine before a fit.
    """
    return _ols_normal(problem, params)[0]


def ols_cost(problem: Problem, params: Parameters) -> float:
    """Return the whitened OLS cost at φ (its priors included): one pass over the pairs."""
    return _ols_normal(problem, params)[2]


def solve_ols(problem: Problem, params: Parameters, max_iterations: int = 100,
              xtol: Optional[float] = None, ftol: float = 1e-12,
              normal: Optional[NormalEquations] = None) -> Solution:
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
    normal : NormalEquations, optional
        The normal equations of this problem at ``params``, when the caller has them (e.g. a
        robust refit: the last fit's less the pairs it now leaves out, ``refit.reweighted``),
        which saves the first pass over the pairs.

    Returns
    -------
    Solution
        With ``problem.weights``, ``residuals`` holds every pair's residuals. Its resume
        state is the normal equations at the solution.

    """
    xtol = XTOL if xtol is None else xtol
    # (state, H, g, cost, residuals) of the current state and the last trial
    normals = [] if normal is None else [(params, normal.info, normal.gradient, normal.cost,
                                          normal.residuals)]

    def normal_at(state: Parameters):
        for entry in normals:
            if entry[0] is state:  # re-damping needs no new pass over the pairs
                normals.remove(entry)
                normals.append(entry)  # the most recently used stays when a trial is added
                return entry
        res = pair_last(problem.n, problem.spec.n_res)
        entry = (state, *_ols_normal(problem, state, res), res)
        normals[:] = normals[-1:] + [entry]
        return entry

    def linearize(state: Parameters, lam: float) -> Linearization:
        _, H, g, cost, res = normal_at(state)

        def propose(delta, lam_next):
            trial = state.stepped(delta)
            if not trial.valid:
                return trial, np.inf, None
            trial = trial.recharted()
            lin = linearize(trial, lam_next)
            return trial, lin.cost, lin

        # Marquardt's scale: the data's and the user's prior's diagonal, not the gauge's pins
        scale = np.diag(H) - gauge_diagonal(problem, state)
        return Linearization(H + lam * np.diag(scale), -g, cost, propose)

    params, status, it, _, _ = levenberg_marquardt(params, linearize, max_iterations, xtol,
                                                   ftol)
    linearize = None  # it calls itself through its trials: a cycle holding the problem (tls)
    # JᵀJ does not depend on the damping: the linearisation at the solution gives the
    # posterior information and the residuals (Ikits B.4.2)
    _, H, g, cost, res = normal_at(params)
    n_prior = len(prior_rows(problem, params)[0])
    return Solution(params, covariance(H), H, cost,
                    problem.n_fitted * problem.spec.n_res + n_prior,
                    res, None, it, status, status_message(status, it, xtol),
                    NormalEquations(H, g, cost, res))
