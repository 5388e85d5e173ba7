"""
Refits that go on from the last fit instead of starting over (robust fits of B.1 and B.2).

A robust fit rejects the pairs far outside the noise and fits the rest again until the set
settles (``calibration.calibrate``): nearly the same pairs, several times. Each fit's resume
state (``Solution.resume``, ``state.Resume``) says how to go on from it, so that a refit's
first step costs no pass over all pairs:

- OLS, all pairs weighted 0 or 1 (``weighable``): the normal equations of the next subset at
  the last solution are the last ones plus the terms of the pairs let back in, less those of
  the pairs left out (``reweighted``, a pass over the changed pairs only); every fit gives
  every pair's residuals, the robust statistic of the next round.
- TLS: a fit's input estimates start a refit of nearly the same pairs next to its minimum
  (``carried_inputs``). A refit of fewer pairs starts from the last linearisation less the
  removed pairs' terms, the kept pairs' factors giving its first input step
  (``without_pairs``, where ``can_take_out``). A fit paused before its step
  (``solve_tls(pause_at=...)``, ``paused``) is screened where that step leads (``heading``)
  and goes on so, with the rejected pairs taken out.

A subset is a boolean mask over the N pairs of one problem of all pairs, ``everything`` (no
priors): ``fitted`` the pairs of the last fit, ``kept`` those of the refit.
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core.estimator import normal_equations
from coreg_ros.core.estimator.posterior import Solution
from coreg_ros.core.estimator.problem import Problem
from coreg_ros.core.estimator.state import (
    InputState,
    NormalEquations,
    TlsResume,
    TlsSeed,
)
from coreg_ros.core.estimator.tls import tls_linearization
from coreg_ros.core.models import Parameters
import numpy as np


def paused(solution: Solution) -> bool:
    """Tell whether ``solution`` is a TLS fit paused before its step (``lm.PAUSED``)."""
    return isinstance(solution.resume, TlsResume) and solution.resume.step is not None


def heading(solution: Solution) -> Parameters:
    """Return where a fit goes next: its φ, or for a paused fit where its step leads."""
    if paused(solution):
        return solution.params.stepped(solution.resume.step).recharted()
    return solution.params


def carried_inputs(solution: Solution, everything: Problem, fitted: np.ndarray,
                   keep: np.ndarray) -> Optional[InputState]:
    """
    Return a TLS fit's input estimates for a refit of other pairs (None for an OLS fit).

    Parameters
    ----------
    solution : Solution
        A fit of the pairs ``fitted`` of ``everything``.
    everything : Problem
        All N pairs.
    fitted, keep : ndarray of bool, shape (N,)
        The pairs of the fit and of the refit.

    Returns
    -------
    InputState or None
        The inputs of the pairs in ``keep``: the fit's estimates, the measured inputs of pairs
        the fit did not have (those of the fit itself if ``keep`` equals ``fitted``).

    """
    if not isinstance(solution.resume, TlsResume):
        return None
    fit = solution.resume.inputs
    if np.array_equal(fitted, keep):
        return fit
    pos_t = np.ascontiguousarray(everything.pos_a.T)
    quat_t = np.ascontiguousarray(everything.quat_a.T)
    pos_t[:, fitted] = fit.pos_t
    quat_t[:, fitted] = fit.quat_t
    return InputState.of_pair_last(pos_t, quat_t).take(np.flatnonzero(keep))


def can_take_out(solution: Solution, fitted: np.ndarray, kept: np.ndarray) -> bool:
    """
    Tell whether a refit of the pairs ``kept`` can start from ``solution``'s linearisation.

    True for a TLS fit of the pairs ``fitted`` (boolean masks over all pairs) that kept its
    last linearisation (``TlsResume.sums``, the structured path) when ``kept`` only removes
    pairs from ``fitted``.
    """
    resume = solution.resume
    return (isinstance(resume, TlsResume) and resume.sums is not None
            and resume.inputs.n == int(fitted.sum()) and not (kept & ~fitted).any())


def without_pairs(solution: Solution, everything: Problem, fitted: np.ndarray,
                  kept: np.ndarray) -> TlsSeed:
    """
    Take pairs out of a TLS fit: the linearisation of the pairs left, without a pass over them.

    The reduced system (eqs. 42-49) is a sum over pairs, so that of ``kept`` at the fit's state
    is the fit's less the removed pairs' terms (a linearisation of those few pairs at their
    estimated inputs, with the fit's damping); the fit's factors give the kept pairs' first
    input step. ``solve_tls(seed=...)`` goes on from it.

    Parameters
    ----------
    solution : Solution
        A TLS fit of the pairs ``fitted`` with ``can_take_out(solution, fitted, kept)``.
    everything : Problem
        All N pairs (no priors).
    fitted, kept : ndarray of bool, shape (N,)
        The pairs of the fit and of the refit (a subset of ``fitted``; equal: a paused fit
        goes on as it is).

    Returns
    -------
    TlsSeed

    """
    if not can_take_out(solution, fitted, kept):
        raise ValueError('only a TLS fit with its last linearisation can have pairs taken out')
    resume = solution.resume
    fit, sums = resume.inputs, resume.sums
    gone = np.flatnonzero(fitted & ~kept)
    if not gone.size:
        return TlsSeed(sums, fit, resume.factors, fit.n)
    stay = kept[fitted]  # among the pairs of the fit
    S, b, cost, _, _, _ = tls_linearization(everything.subset(gone), solution.params,
                                            fit.take(np.flatnonzero(~stay)), sums.lam)
    stay_idx = np.flatnonzero(stay)
    # the start gathered when read: its first step (back-substitution, then the step) reads
    # the fit's inputs, which the factors hold until then anyway
    return TlsSeed(sums.less(S, b, cost), fit.take(stay_idx, lazy=True), resume.factors, fit.n,
                   stay_idx)


def weighable(solution: Solution, everything: Problem) -> bool:
    """
    Tell whether an OLS fit goes on with the pairs of ``everything`` weighted 0/1.

    True on the structured path (``normal_equations.applies``) when the fit's normal equations
    hold every pair's residuals (a fit of all pairs, or of all pairs weighted).
    """
    resume = solution.resume
    return (isinstance(resume, NormalEquations)
            and normal_equations.applies(everything, inputs=False)
            and resume.residuals.shape[0] == everything.n)


def reweighted(solution: Solution, everything: Problem, fitted: np.ndarray,
               kept: np.ndarray) -> NormalEquations:
    """
    Return the normal equations of the pairs ``kept`` at ``solution``, from the fit's.

    The fit's normal equations (eqs. 32-36) plus the terms of the pairs let back in, less
    those of the pairs left out: a pass over the changed pairs only. ``solve_ols`` goes on
    from them on ``everything`` weighted 1 in ``kept``, 0 elsewhere; the residuals are the
    fit's, of every pair.

    Parameters
    ----------
    solution : Solution
        An OLS fit of the pairs ``fitted`` (weighted 0/1) with ``weighable``.
    everything : Problem
        All N pairs (no priors).
    fitted, kept : ndarray of bool, shape (N,)
        The pairs weighted 1 in the fit and in the refit.

    """
    if not weighable(solution, everything):
        raise ValueError('only an OLS fit with the residuals of every pair can be reweighted')
    idx = np.flatnonzero(kept != fitted)
    changed = everything.subset(idx, weights=np.where(kept[idx], 1.0, -1.0))
    H, g, cost = normal_equations.ols_normal(changed, solution.params)
    fit = solution.resume
    return NormalEquations(fit.info + H, fit.gradient + g, fit.cost + cost, fit.residuals)
