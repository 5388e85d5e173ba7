"""
The long recording's memory savings give the numbers of the copies they replace, bit for bit.

``Problem.subset(idx, lazy=True)`` (the robust TLS refit's pairs gathered chunk by chunk) and
``pairing.own_rows`` (a round's inliers moved to the front of its own arrays) against
``np.take``, on random draws; the robust ``calibrate`` (its refits on lazy rows, its last fit
handed over) against the same with the lazy rows replaced by copies.
"""

from __future__ import annotations

from coreg_ros.core import estimator as est
from coreg_ros.core.calibration import pairing
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.initialize import initialize
from coreg_ros.core.estimator import problem as problem_module
from coreg_ros.core.estimator.problem import CHUNK, RowsOf
from coreg_ros.core.models import SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_pairs
import numpy as np
import pytest

SIGMA_A = (2e-4, np.radians(0.5))
SIGMA_B = (5e-4, 2e-3)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_rows_of_reads_what_a_copy_holds(seed):
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(int(rng.integers(1, 3 * CHUNK)), 4))
    idx = np.flatnonzero(rng.random(len(base)) < rng.uniform(0.05, 1.0))
    rows, copy = RowsOf(base, idx), np.take(base, idx, axis=0)
    assert len(rows) == len(copy) and rows.shape == copy.shape and rows.ndim == 2
    for lo in range(0, len(idx), 1000):
        np.testing.assert_array_equal(rows[lo:lo + 1000], copy[lo:lo + 1000])
    np.testing.assert_array_equal(np.asarray(rows), copy)
    if len(idx):
        np.testing.assert_array_equal(rows[[0, -1]], copy[[0, -1]])


@pytest.mark.parametrize('seed', [3, 4])
def test_lazy_subset_fits_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2 * CHUNK, 3 * CHUNK))
    pairs, _, _ = simulate_pairs(rng, n, 'full_pose', sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    spec = SPECS['full_pose']
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    everything = est.Problem(spec, pairs.pos_a, pairs.quat_a, pairs.pos_b, pairs.quat_b,
                             est.whitening(settings.cov_b, spec, 'b'),
                             est.whitening(settings.cov_a, None, 'a'), pairs.a_var_scale)
    idx = np.flatnonzero(rng.random(n) < 0.97)
    start = initialize(spec, pairs.pos_a, pairs.quat_a, pairs.pos_b, pairs.quat_b)
    fits = [est.solve_tls(everything.subset(idx, lazy=lazy), start, max_iterations=20)
            for lazy in (False, True)]
    np.testing.assert_array_equal(fits[0].params.phi, fits[1].params.phi)
    np.testing.assert_array_equal(fits[0].cov, fits[1].cov)
    assert fits[0].chi2 == fits[1].chi2 and fits[0].iterations == fits[1].iterations


@pytest.mark.parametrize('seed', [5, 6, 7])
def test_inliers_moved_to_the_front_are_the_inliers(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 4 * pairing._COMPACT_ROWS))
    own = rng.normal(size=(n, 4))
    expected = own.copy()
    keep = np.flatnonzero(rng.random(n) < rng.uniform(0.0, 1.0))
    got = pairing.own_rows(own, keep)
    np.testing.assert_array_equal(got, np.take(expected, keep, axis=0))
    # a view (B's rows of its stream) is copied, never written
    stream = rng.normal(size=(n + 5, 3))
    before = stream.copy()
    view = stream[2:n + 2]
    np.testing.assert_array_equal(pairing.own_rows(view, keep),
                                  np.take(before[2:n + 2], keep, axis=0))
    np.testing.assert_array_equal(stream, before)


def test_robust_refit_on_lazy_rows_is_the_refit_on_copies(monkeypatch):
    rng = np.random.default_rng(8)
    pairs, _, _ = simulate_pairs(rng, 3 * CHUNK, 'full_pose', sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    bad = rng.choice(len(pairs.pos_b), 60, replace=False)
    pairs.pos_b[bad] += rng.normal(scale=0.05, size=(60, 3))
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B, method='tls', robust=True)
    lazy = calibrate(pairs, settings)
    monkeypatch.setattr(problem_module, 'RowsOf', lambda x, idx: np.take(x, idx, axis=0))
    copied = calibrate(pairs, settings)
    assert not lazy.inliers[bad].any() and lazy.inliers.sum() >= len(lazy.inliers) - 70
    np.testing.assert_array_equal(lazy.inliers, copied.inliers)
    np.testing.assert_array_equal(lazy.params, copied.params)
    np.testing.assert_array_equal(lazy.param_cov, copied.param_cov)
    np.testing.assert_array_equal(lazy.residuals, copied.residuals)
