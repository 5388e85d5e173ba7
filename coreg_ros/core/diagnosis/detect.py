"""
Detect a gap between a recording and the fitted model (docs/design.md §5 step 1).

Inputs are the base fit's output errors of every pair: the squared normalized error per pair
(chi-square with m degrees of freedom if the model holds) and the decorrelated errors scaled to
unit variance. Where the gap lies is ``locate.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from coreg_ros.core.diagnosis.record import Record
from coreg_ros.core.distributions import chi2_cdf, chi2_isf, chi2_sf, norm_sf, scipy_stats
import numpy as np

#: Lags of the Ljung-Box whiteness test.
LJUNG_BOX_LAGS = 20
#: A deviation must be at least this large to count as practically relevant.
PRACTICAL_CHI2 = 0.05
PRACTICAL_AUTOCORR = 0.05
#: Significance level of the detection tests (several tests: strict).
ALPHA = 1e-3


@dataclass(frozen=True, kw_only=True)
class LjungBox(Record):
    """
    Whiteness of the decorrelated errors: the Ljung-Box test summed over the channels.

    Attributes
    ----------
    statistic : float
    dof : int
    p_value : float
    max_autocorrelation : float
        The largest |autocorrelation| of any channel at lags 1..h.
    lag1_autocorrelation : float
        The mean over the channels of the autocorrelation at lag 1.

    """

    statistic: float
    dof: int
    p_value: float
    max_autocorrelation: float
    lag1_autocorrelation: float


@dataclass(frozen=True, kw_only=True)
class Tails(Record):
    """
    Tails of the decorrelated errors against the normal.

    Attributes
    ----------
    excess_kurtosis : float
    share_beyond_4sigma, expected_share_beyond_4sigma : float
    gross_pairs : int
        Pairs beyond the 1e-6 quantile of chi-square.
    expected_gross_pairs : float
    p_value : float
        Of that many gross pairs (Poisson).

    """

    excess_kurtosis: float
    share_beyond_4sigma: float
    expected_share_beyond_4sigma: float
    gross_pairs: int
    expected_gross_pairs: float
    p_value: float


@dataclass(frozen=True, kw_only=True)
class GapFlags(Record):
    """Which tests found a practically relevant gap."""

    chi2_high: bool
    chi2_low: bool
    not_white: bool
    heavy_tails: bool

    @property
    def raised(self) -> list:
        """Return the names of the flags raised, in their order."""
        return [f.name for f in fields(self) if getattr(self, f.name)]


@dataclass(frozen=True, kw_only=True)
class Detection(Record):
    """
    Chi-square goodness of fit, whiteness and tails of the base fit.

    Attributes
    ----------
    chi2 : float
    dof : int
    chi2_per_dof : float
    p_value : float
        Upper tail.
    p_value_low : float
        Lower tail: noise smaller than stated.
    ljung_box : LjungBox
    tails : Tails
    flags : GapFlags
    gap : bool
        Some test found a practically relevant gap.

    """

    chi2: float
    dof: int
    chi2_per_dof: float
    p_value: float
    p_value_low: float
    ljung_box: LjungBox
    tails: Tails
    flags: GapFlags
    gap: bool


def ljung_box(x: np.ndarray, lags: int = LJUNG_BOX_LAGS):
    """
    Ljung-Box statistic of a series, its p-value and the autocorrelations at lags 1..h.

    Parameters
    ----------
    x : ndarray, shape (n,)
        The series, in time order.
    lags : int
        Largest lag h.

    Returns
    -------
    q : float
    p_value : float
    rho : ndarray, shape (h,)

    """
    x = np.asarray(x, dtype=float)
    n = len(x)
    h = int(min(lags, max(n // 4, 1)))
    x = x - x.mean()
    den = float(np.dot(x, x))
    if n < 8 or den <= 0:
        return 0.0, 1.0, np.zeros(h)
    rho = np.array([np.dot(x[:-k], x[k:]) / den for k in range(1, h + 1)])
    q = float(n * (n + 2) * np.sum(rho ** 2 / (n - np.arange(1, h + 1))))
    return q, float(chi2_sf(q, h)), rho


def detect(quad: np.ndarray, zstd: np.ndarray, m: int, n_params: int) -> Detection:
    """
    Chi-square goodness of fit, whiteness and tails of the base fit.

    Parameters
    ----------
    quad : ndarray, shape (n,)
        Squared normalized output error per pair (stated noise).
    zstd : ndarray, shape (n, m)
        Decorrelated errors scaled to unit variance (white N(0, 1) if the model holds).
    m : int
        Residuals per pair.
    n_params : int
        Parameters fitted (φ).

    Returns
    -------
    Detection

    """
    n = len(quad)
    chi2 = float(np.sum(quad))
    dof = max(n * m - n_params, 1)
    ratio = chi2 / dof
    p_hi = float(chi2_sf(chi2, dof))
    p_lo = float(chi2_cdf(chi2, dof))
    qs, rhos = [], []
    for j in range(zstd.shape[1]):
        q, _, rho = ljung_box(zstd[:, j])
        qs.append(q)
        rhos.append(rho)
    h = len(rhos[0]) if rhos else 1
    q_total = float(np.sum(qs))
    lb_dof = h * zstd.shape[1]
    p_lb = float(chi2_sf(q_total, lb_dof))
    rho_max = float(np.max(np.abs(np.concatenate(rhos)))) if rhos else 0.0
    rho1 = float(np.mean([r[0] for r in rhos])) if rhos else 0.0
    flat = zstd.reshape(-1)
    kurt = float(scipy_stats().kurtosis(flat)) if flat.size > 3 else 0.0
    beyond4 = float(np.mean(np.abs(flat) > 4.0))
    expected4 = float(2.0 * norm_sf(4.0))
    limit = chi2_isf(1e-6, m)
    gross = int(np.sum(quad > limit))
    expected_gross = 1e-6 * n
    p_tail = float(scipy_stats().poisson.sf(gross - 1, max(expected_gross, 1e-12)))
    flags = GapFlags(chi2_high=bool(p_hi < ALPHA and ratio > 1.0 + PRACTICAL_CHI2),
                     chi2_low=bool(p_lo < ALPHA and ratio < 1.0 - PRACTICAL_CHI2),
                     not_white=bool(p_lb < ALPHA and rho_max > PRACTICAL_AUTOCORR),
                     heavy_tails=bool(p_tail < ALPHA and gross >= max(3, 0.001 * n)))
    return Detection(
        chi2=chi2, dof=int(dof), chi2_per_dof=ratio, p_value=p_hi, p_value_low=p_lo,
        ljung_box=LjungBox(statistic=q_total, dof=int(lb_dof), p_value=p_lb,
                           max_autocorrelation=rho_max, lag1_autocorrelation=rho1),
        tails=Tails(excess_kurtosis=kurt, share_beyond_4sigma=beyond4,
                    expected_share_beyond_4sigma=expected4, gross_pairs=gross,
                    expected_gross_pairs=expected_gross, p_value=p_tail),
        flags=flags, gap=bool(flags.raised))
