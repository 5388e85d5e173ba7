"""Consistency measures: pose errors in the covariance tangent, NEES, k-sigma coverage."""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
from coreg_ros.core.distributions import chi2_cdf, chi2_ppf
import numpy as np


def pose_error(p_true, q_true, p_est, q_est) -> np.ndarray:
    """
    Error of estimates in the ROS layout: the δ with ``truth = Exp(δ) ⊞ estimate``.

    Parameters
    ----------
    p_true, p_est : array_like, shape (..., 3)
        Positions, m.
    q_true, q_est : array_like, shape (..., 4)
        Orientations (w, x, y, z).

    Returns
    -------
    ndarray, shape (..., 6)
        ``(p_true - p_est, Log(R_true R_estᵀ))``: m, then rad about the fixed axes.

    """
    dp = np.asarray(p_true, dtype=float) - np.asarray(p_est, dtype=float)
    dth = quat.log(quat.multiply(q_true, quat.conjugate(q_est)))
    return np.concatenate([dp, dth], axis=-1)


def nees(errors: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """
    Normalised estimation error squared ``eᵀ C⁻¹ e`` (χ² with dim(e) degrees of freedom).

    Parameters
    ----------
    errors : array_like, shape (..., n)
        Estimation errors.
    cov : array_like, shape (..., n, n)
        Positive definite.

    Returns
    -------
    ndarray, shape (...)

    """
    e = np.asarray(errors, dtype=float)
    sol = np.linalg.solve(np.asarray(cov, dtype=float), e[..., None])[..., 0]
    return np.sum(e * sol, axis=-1)


def coverage_probability(n_sigma: float, dim: int) -> float:
    """
    Probability that a Gaussian error lies inside its ``n_sigma`` ellipsoid in ``dim`` dimensions.

    The ellipsoid is ``eᵀ C⁻¹ e ≤ n_sigma²``; in 3-D, 3σ holds about 97 % (Hoff eq. 8, note 3);
    in 2-D (an axis cone) about 98.9 %.
    """
    return float(chi2_cdf(float(n_sigma) ** 2, int(dim)))


def sigma_for_probability(probability: float, dim: int) -> float:
    """Scale k of the ellipsoid ``eᵀ C⁻¹ e ≤ k²`` that holds ``probability`` in ``dim`` dims."""
    return float(np.sqrt(chi2_ppf(float(probability), int(dim))))
