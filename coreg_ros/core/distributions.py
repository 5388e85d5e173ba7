"""
The χ² and normal tail probabilities and quantiles of the tests, from ``scipy.special``.

Why not ``scipy.stats``: importing it (with the scipy.optimize, spatial and ndimage it pulls in)
costs about 0.5 s of CPU, more than a ``coreg`` command needs to start without it, and every
command and node tests a χ². These functions are what ``scipy.stats.chi2`` and ``norm`` compute
(the same special functions, the same arithmetic, so the same numbers to the last bit, checked
against scipy.stats in test/core/test_distributions.py), with scipy's values at the edges of
the support (x <= 0, x = inf, p = 0 or 1) and NaN for an invalid argument. What the core needs
from scipy.stats beyond these (rank correlations, a kurtosis, discrete tails) it takes from
``scipy_stats()``, which imports the module on first use only.

Inputs broadcast as NumPy arrays; a scalar gives a NumPy scalar, as scipy.stats does.
"""

from __future__ import annotations

import numpy as np
from scipy import special


def _out(values: np.ndarray):
    return values[()] if values.ndim == 0 else values


def _invalid(df: np.ndarray) -> np.ndarray:
    return ~(df > 0)  # NaN degrees of freedom are invalid too


def _of_statistic(f, x, df, at_zero: float, at_inf: float):
    """
    Return ``f(df, x)`` on χ²'s support (0, inf), scipy.stats' values at its edges.

    ``at_zero`` where x <= 0, ``at_inf`` where x = inf, NaN for a NaN x or an invalid df.
    """
    x, df = np.asarray(x, dtype=float), np.asarray(df)
    inside = (x > 0.0) & (x < np.inf)
    value = f(df, np.where(inside, x, 1.0))
    out = np.where(inside, value, np.where(x <= 0.0, at_zero, at_inf))
    return _out(np.where(np.isnan(x) | _invalid(df), np.nan, out))


def _of_probability(f, p, df, at_zero: float, at_one: float):
    """
    Return ``f(df, p)`` for p in (0, 1), scipy.stats' values at 0 and 1.

    ``* 1.0 + 0.0`` is scipy's ``* scale + loc`` (the same bits); NaN outside [0, 1] or for
    an invalid df.
    """
    p, df = np.asarray(p, dtype=float), np.asarray(df)
    inside = (p > 0.0) & (p < 1.0)
    value = f(df, np.where(inside, p, 0.5)) * 1.0 + 0.0
    out = np.where(inside, value, np.where(p == 0.0, at_zero, at_one))
    return _out(np.where(~((p >= 0.0) & (p <= 1.0)) | _invalid(df), np.nan, out))


def chi2_sf(x, df):
    """
    Return P(X > x) for X ~ χ²(df) (``scipy.stats.chi2.sf``).

    Parameters
    ----------
    x : array_like
        Values of the statistic, shape broadcast with ``df``.
    df : array_like
        Degrees of freedom (> 0).

    """
    return _of_statistic(special.chdtrc, x, df, 1.0, 0.0)


def chi2_cdf(x, df):
    """Return P(X <= x) for X ~ χ²(df) (``scipy.stats.chi2.cdf``); shapes as ``chi2_sf``."""
    return _of_statistic(special.chdtr, x, df, 0.0, 1.0)


def chi2_ppf(p, df):
    """
    Return the p-quantile of χ²(df) (``scipy.stats.chi2.ppf``): 0 at p = 0, inf at p = 1.

    Parameters
    ----------
    p : array_like
        Probabilities in [0, 1], shape broadcast with ``df``.
    df : array_like
        Degrees of freedom (> 0).

    """
    return _of_probability(lambda d, q: 2 * special.gammaincinv(d / 2, q), p, df, 0.0, np.inf)


def chi2_isf(p, df):
    """Return the value χ²(df) exceeds with probability p (``scipy.stats.chi2.isf``)."""
    return _of_probability(special.chdtri, p, df, np.inf, 0.0)


def norm_sf(x):
    """Return P(Z > x) for a standard normal Z (``scipy.stats.norm.sf``)."""
    x = np.asarray(x, dtype=float)
    return _out(np.asarray(special.ndtr(-x)))


def scipy_stats():
    """Return ``scipy.stats``, imported on first use (the module docstring says why)."""
    from scipy import stats
    return stats
