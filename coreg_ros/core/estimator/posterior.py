"""
The solution and its posterior covariance (Ikits B.4.2, eq. 58).

At the minimum the covariance of φ is the inverse of the information: JᵀJ for OLS, the Schur
complement S of the TLS normal equations (the φ block of the inverse of the whole normal
matrix) for TLS, priors included in both. The chi-square ``Σ r²`` and its degrees of freedom
(``n_rows - P``) give the goodness of fit (B.4.1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, TYPE_CHECKING

from coreg_ros.core.models import Parameters
import numpy as np

if TYPE_CHECKING:  # annotations only: tls imports this module
    from coreg_ros.core.estimator.tls import InputState, TlsSums


def covariance(info: np.ndarray) -> Optional[np.ndarray]:
    """
    Inverse of a symmetric information matrix, None if it is singular.

    Parameters
    ----------
    info : ndarray, shape (P, P)
        JᵀJ (OLS) or the Schur complement S (TLS).

    """
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(cov).all() or (np.diag(cov) <= 0).any():
        return None
    return 0.5 * (cov + cov.T)


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
        How the iterations ended (``lm.MESSAGES``): 1 step small, 2 cost change small,
        0 iteration limit, -1 no acceptable step; ``lm.PAUSED`` (3) a fit stopped before
        its step ``step``, to be continued by the caller.
    message : str
    inputs : InputState or None
        TLS: the estimated inputs at the solution (a warm start for a refit of nearly the
        same pairs).
    gradient : ndarray, shape (P,) or None
        OLS: Jᵀr at the solution (with ``info`` and ``chi2``, the normal equations there).
    sums : TlsSums or None
        TLS on the structured path: the last linearisation, for a refit of fewer pairs.
    step : ndarray, shape (P,) or None
        A paused fit: the step its last linearisation gives (where the fit goes next).

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
    step: Optional[np.ndarray] = None
