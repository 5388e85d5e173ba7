"""The χ² and normal functions of ``core.distributions`` are scipy.stats' to the last bit."""

from coreg_ros.core import distributions as dist
import numpy as np
import pytest
from scipy import stats

#: Statistics and probabilities of every kind the tests use, and the edges of the support.
XS = np.concatenate([[0.0, -0.0, -1.0, 1e-300, np.inf, -np.inf, np.nan],
                     np.random.default_rng(0).gamma(2.0, 5.0, 400),
                     np.geomspace(1e-8, 1e4, 60)])
PS = np.concatenate([[0.0, 1.0, -0.1, 1.1, np.nan, 1e-300, 1.0 - 1e-16, 0.5, 0.25, 1e-4, 1e-6],
                     np.random.default_rng(1).uniform(size=300),
                     np.geomspace(1e-15, 0.5, 40)])
DFS = [1, 2, 3, 5, 6, 9, 12, 13, 60, 1000, 2.5, 0, -1, np.nan]


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize('df', DFS)
def test_chi2_matches_scipy_stats_bit_for_bit(df):
    with np.errstate(all='ignore'):
        assert _same(dist.chi2_sf(XS, df), stats.chi2.sf(XS, df))
        assert _same(dist.chi2_cdf(XS, df), stats.chi2.cdf(XS, df))
        assert _same(dist.chi2_ppf(PS, df), stats.chi2.ppf(PS, df))
        assert _same(dist.chi2_isf(PS, df), stats.chi2.isf(PS, df))


def test_scalars_give_numpy_scalars_as_scipy_stats_does():
    for mine, theirs, arg in [(dist.chi2_sf, stats.chi2.sf, 7.5),
                              (dist.chi2_cdf, stats.chi2.cdf, 7.5),
                              (dist.chi2_ppf, stats.chi2.ppf, 0.3),
                              (dist.chi2_isf, stats.chi2.isf, 1e-4)]:
        got, want = mine(arg, 6), theirs(arg, 6)
        assert type(got) is type(want) and got == want
    assert dist.norm_sf(4.0) == stats.norm.sf(4.0)
    assert _same(dist.norm_sf(XS), stats.norm.sf(XS))
    # arrays of degrees of freedom broadcast against the values
    dfs = np.array([1, 3, 12])
    assert _same(dist.chi2_sf(np.array([[2.0], [9.0]]), dfs),
                 stats.chi2.sf(np.array([[2.0], [9.0]]), dfs))
    assert _same(dist.chi2_ppf([0.005, 0.995], 12 * 40), stats.chi2.ppf([0.005, 0.995], 12 * 40))


def test_the_quantiles_invert_the_tails():
    p = np.array([1e-6, 0.01, 0.25, 0.5, 0.9])
    for df in (1, 6, 12):
        assert np.allclose(dist.chi2_sf(dist.chi2_isf(p, df), df), p, rtol=1e-9)
        assert np.allclose(dist.chi2_cdf(dist.chi2_ppf(p, df), df), p, rtol=1e-9)
