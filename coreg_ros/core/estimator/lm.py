"""
The Levenberg-Marquardt driver shared by OLS (B.1) and TLS (B.2).

The driver sees a problem only through its linearisations (``Linearization``): a damped
normal matrix, its right-hand side, the cost, and how to try a step. The stopping rule is in
posterior standard deviations of φ (``XTOL``); ``MESSAGES`` is the one table of the status
codes and what they say (``types.STATUS`` is its short form for users).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Optional, TYPE_CHECKING, Union

from coreg_ros.core.estimator.posterior import covariance
import numpy as np

if TYPE_CHECKING:
    from coreg_ros.core.estimator.normal_equations_tls import TlsFactors

#: Default convergence tolerance: stop when the next step would move every parameter by at
#: most this many of its posterior standard deviations. 1e-5 σ is far below anything a
#: statistic can see (scipy's default, 1e-8 relative to |φ|, is ~1e-2 σ at 100k pairs) and
#: lets TLS stop at the linearisation that proves convergence instead of taking one more
#: step of ~1e-7 σ and a whole pass over the pairs to evaluate it.
XTOL = 1e-5

#: How the iterations ended: status -> message (formatted with ``iterations`` and ``xtol``).
MESSAGES = {
    1: 'converged in {iterations} iterations: steps below {xtol:g} standard deviations',
    2: 'converged in {iterations} iterations: cost no longer decreases',
    0: 'stopped at the iteration limit ({iterations}) before converging; raise '
       'max_iterations or check the noise settings',
    -1: 'no step reduced the cost after {iterations} iterations; the model does not '
        'fit the data (check stream directions and units)',
}

#: Not a final status: the driver stopped before trying the step of iteration ``pause_at``
#: (its linearisation and that step are returned), so that the caller can continue the fit
#: from there, e.g. after screening the pairs where the step leads (``calibrate``).
PAUSED = 3


def status_message(status: int, iterations: int, xtol: float) -> str:
    """Return the message of ``status`` (``MESSAGES``) after ``iterations`` iterations."""
    if status == PAUSED:
        return f'paused before the step of iteration {iterations}'
    return MESSAGES[status].format(iterations=iterations, xtol=xtol)


@dataclass
class Linearization:
    """
    One linearisation of the problem for the LM driver.

    ``info`` is the (damped) normal matrix of φ, ``rhs`` its right-hand side (the step solves
    ``info δ = rhs``), ``cost`` the cost at the linearisation point. ``propose(δ, λ')``
    returns the trial state, its cost and the linearisation at the trial made with damping λ'
    (or None): when the trial is accepted that linearisation is the next one, so evaluating a
    trial and linearising there is one pass over the pairs, not two.

    ``factors`` (TLS only) are this linearisation's per-pair factors, from which
    ``tls.back_substitute`` gives the inputs' step of a parameter step: per-chunk Cholesky
    factors ``(L, Z)`` on the generic path, ``normal_equations_tls.TlsFactors`` on the
    structured one. A fit keeps the structured ones with its sums, for a refit's first step.
    """

    info: np.ndarray
    rhs: np.ndarray
    cost: float
    propose: Callable
    damping_share: float = 0.0  # largest λ·V_jj / info_jj: how far info is from undamped
    factors: Union[list, TlsFactors, None] = None
    step: Optional[np.ndarray] = None  # set by the driver when it pauses before this step
    fresh: bool = True  # made at its state (not sums carried over from another fit's)


def levenberg_marquardt(state, linearize: Callable, max_iterations: int, xtol: float,
                        ftol: float, damping: float = 1e-6, first=None, min_steps: int = 0,
                        pause_at: Optional[int] = None):
    """
    Levenberg-Marquardt iterations shared by OLS and TLS.

    Convergence: status 1 when the step is below ``xtol`` posterior standard deviations on
    every component (tested before a step is tried, so rounding noise at the optimum is never
    mistaken for a misfit, and after an accepted step); status 2 when the cost stops
    decreasing by more than ``ftol`` relative; 0 at the iteration limit; -1 when no damping
    gives a decrease although the step is not small (the model does not fit).

    Parameters
    ----------
    state
        The starting state (φ, or φ with the TLS inputs).
    linearize : callable
        ``linearize(state, λ)`` -> ``Linearization``.
    max_iterations : int
        Largest number of iterations.
    xtol, ftol : float
        Step (posterior σ) and relative cost-change tolerances.
    damping : float
        The first λ (lower for a start next to the minimum).
    first : Linearization, optional
        The linearisation at ``state`` with that damping (made by the caller without a pass).
    min_steps : int
        Accepted steps before a small step may prove convergence: TLS from the measured
        inputs must move them at least once, since a small step of φ says nothing about the
        inputs (whose adjustment lowers the cost by about the input noise's share of chi2).
    pause_at : int, optional
        Return with status ``PAUSED`` before trying the step of this iteration (unless that
        step proves convergence or follows a rejection), with the step in ``last.step``.

    Returns
    -------
    state, status, iterations, last : Linearization or None, lam : float
        ``last`` is the linearisation at the returned state, made with damping ``lam``
        (None if there is none).

    """
    lam = damping
    # ``first`` and, once it moves on, the last state are held by nothing here: a TLS state
    # holds every pair's input estimates (107 MB at 2M pairs)
    lin, first = (linearize(state, lam) if first is None else first), None
    for it in range(1, max_iterations + 1):
        rejected = False
        while True:
            delta = np.linalg.lstsq(lin.info, lin.rhs, rcond=None)[0]
            # Only a step damped as little as the last accepted one may prove convergence: a
            # damping raised by rejections shrinks any step below xtol·σ eventually.
            if not rejected and it > min_steps and step_is_small(delta, lin.info, xtol):
                return state, 1, it, lin, lam
            if not rejected and it == pause_at:
                lin.step = delta
                return state, PAUSED, it, lin, lam
            lam_next = max(lam / 10.0, 1e-12)
            trial, new_cost, trial_lin = lin.propose(delta, lam_next)
            if np.isfinite(new_cost) and new_cost <= lin.cost:
                break
            trial_lin = None  # release the rejected trial's per-pair factors
            if new_cost - lin.cost <= ftol * max(lin.cost, 1.0):
                return state, 2, it, lin, lam
            if lam * 10.0 > 1e16:
                return state, -1, it, lin, lam
            rejected = True
            # from the floor, not from 0: a start at λ = 0 (a seed's sums made undamped)
            # would otherwise stay undamped and retry the same step forever
            lam = max(lam, 1e-12) * 10.0
            lin = None
            lin = linearize(state, lam)
        state, lam, old_info, old_cost = trial, lam_next, lin.info, lin.cost
        lin = trial = None  # the last state's linearisation (its closures hold that state)
        lin, trial_lin = (trial_lin if trial_lin is not None else linearize(state, lam)), None
        if step_is_small(delta, old_info, xtol):
            return state, 1, it, lin, lam
        if old_cost - new_cost <= ftol * max(new_cost, 1.0):
            return state, 2, it, lin, lam
    return state, 0, max_iterations, lin, lam


def step_is_small(delta: np.ndarray, info: np.ndarray, xtol: float) -> bool:
    """Tell whether every |δ_j| <= xtol · σ_j, σ from the inverse of ``info``."""
    cov = covariance(info)
    return cov is not None and bool(np.all(np.abs(delta) <= xtol * np.sqrt(np.diag(cov))))
