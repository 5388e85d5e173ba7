"""
A priori estimates as extra residual rows (Ikits B.3, eqs. 55-56).

A prior adds ``(φ̂ - φ)ᵀ W_φ (φ̂ - φ)`` to the objective (eqs. 28 and 39): whitened, a few more
residual rows and their Jacobian. Both solvers add them to their normal equations (OLS to JᵀJ,
TLS to the Schur complement); ``covariance.Prior.terms`` makes the terms from a pose prior.
"""

from __future__ import annotations

from collections.abc import Callable

from coreg_ros.core.models import Parameters
import numpy as np

#: A prior term returns whitened residual rows (k,) and their Jacobian (k, P) at φ (Ikits B.3).
PriorTerm = Callable[[Parameters], tuple]


def prior_rows(problem, params: Parameters):
    """
    Stacked prior residuals, Jacobian and count (Ikits eqs. 55-56).

    Parameters
    ----------
    problem : Problem
        Its ``priors`` (a list of ``PriorTerm``) and ``spec``.
    params : Parameters
        The φ the terms are evaluated at.

    Returns
    -------
    r : ndarray, shape (k,)
    J : ndarray, shape (k, P)

    """
    P = problem.spec.n_params
    if not problem.priors:
        return np.zeros(0), np.zeros((0, P))
    parts = [term(params) for term in problem.priors]
    return np.concatenate([r for r, _ in parts]), np.concatenate([j for _, j in parts])
