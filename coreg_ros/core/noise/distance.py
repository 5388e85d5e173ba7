"""
How a device's noise grows with the distance from its base's origin (still segments at several).

An electromagnetic tracker is noisier away from its field generator, an optical one in depth
far from the cameras. With still segments at distances ``r_k`` (the norm of the segment's mean
position, m) and noise ``σ_k`` (the RMS over the axes), the law ``σ = σ_ref (r / r_ref)^k`` is
fitted by weighted least squares in logarithms (``σ(log σ_k) = 1/√(2 n_k)`` with ``n_k`` the
segment's effective samples), ``r_ref`` the weighted geometric mean distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Segments must span at least this ratio of distances for a law to be fitted.
MIN_DISTANCE_RATIO = 1.2


@dataclass(frozen=True)
class DistanceLaw:
    """
    ``σ = sigma_ref (r / reference_m)^exponent`` with the segments it was fitted to.

    Attributes
    ----------
    exponent, exponent_se : float
    sigma_ref, sigma_ref_se : float
        σ (RMS over the axes) at ``reference_m``, m or rad.
    reference_m : float
    distances_m, sigma, sigma_se : ndarray, shape (K,)
        Each segment's distance and σ (RMS over the axes) with its standard error.

    """

    exponent: float
    exponent_se: float
    sigma_ref: float
    sigma_ref_se: float
    reference_m: float
    distances_m: np.ndarray
    sigma: np.ndarray
    sigma_se: np.ndarray

    def as_dict(self) -> dict:
        """JSON form."""
        return {'exponent': self.exponent, 'exponent_se': self.exponent_se,
                'sigma_ref': self.sigma_ref, 'sigma_ref_se': self.sigma_ref_se,
                'reference_m': self.reference_m,
                'segments': [{'distance_m': float(r), 'sigma': float(s), 'sigma_se': float(e)}
                             for r, s, e in zip(self.distances_m, self.sigma, self.sigma_se,
                                                strict=True)]}

    def ratio(self, distance_m: float) -> float:
        """σ at ``distance_m`` relative to σ at the reference distance."""
        return float((max(distance_m, 1e-9) / self.reference_m) ** self.exponent)


def distance_law(distances: np.ndarray, sigma: np.ndarray, n_effective: np.ndarray):
    """
    Fit ``σ = σ_ref (r / r_ref)^k`` to still segments; None if they do not span distances.

    Parameters
    ----------
    distances : ndarray, shape (K,)
        m from the base's origin.
    sigma : ndarray, shape (K,)
        Each segment's σ (RMS over the axes).
    n_effective : ndarray, shape (K,)
        Each segment's effective samples of the σ (sets the weights; three axes of white noise
        of n samples count 3n).

    Returns
    -------
    DistanceLaw or None

    """
    r = np.asarray(distances, dtype=float)
    s = np.asarray(sigma, dtype=float)
    n = np.maximum(np.asarray(n_effective, dtype=float), 2.0)
    ok = (r > 0) & (s > 0)
    if ok.sum() < 2 or r[ok].max() < MIN_DISTANCE_RATIO * r[ok].min():
        return None
    r, s, n = r[ok], s[ok], n[ok]
    w = 2.0 * n  # 1 / var(log σ̂)
    r_ref = float(np.exp(np.sum(w * np.log(r)) / np.sum(w)))
    X = np.stack([np.ones_like(r), np.log(r / r_ref)], axis=1)
    info = X.T @ (X * w[:, None])
    cov = np.linalg.inv(info)
    coef = cov @ (X.T @ (w * np.log(s)))
    # the scatter about the law, when larger than the segments' own, widens the errors
    resid = np.log(s) - X @ coef
    dof = len(r) - 2
    scale = max(1.0, float(np.sum(w * resid ** 2)) / dof) if dof > 0 else 1.0
    se = np.sqrt(np.diag(cov) * scale)
    sigma_ref = float(np.exp(coef[0]))
    return DistanceLaw(float(coef[1]), float(se[1]), sigma_ref, sigma_ref * float(se[0]), r_ref,
                       r, s, s / np.sqrt(w))
