"""
The fast paths of ``calibrate`` give the answers of the plain ones.

Fast: the start from a subsample, TLS refits from the last fit's inputs (the first one
screened where its step leads, before the pass that proves it converged), OLS refits from the
last fit's normal equations (0/1 weights), the robust statistic in one light pass
(``screening``), the motion check from a 3×3 moment, the stopping rule at
``calibrate.XTOL`` = 5e-3 σ.
Plain: everything on all pairs, the statistic from ``linearized``, and the stopping rule of
before (1e-5 σ). The estimates must agree within a small fraction of σ, the covariances
within 1 %, the rejected pairs exactly, on random draws with realistic noise (0.5° rotation
noise on A) and with outliers.
"""

from __future__ import annotations

from dataclasses import replace

from coreg_ros.core import estimator as est
from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration import calibrate as cal
from coreg_ros.core.calibration import screening
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.initialize import initialize
from coreg_ros.core.calibration.observability import rotation_spread
from coreg_ros.core.estimator import linearized, noise_covariance, ols
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.models import SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import UncertainPose
from coreg_ros.sim import simulate_pairs
import numpy as np
import pytest

SIGMA_A = (2e-4, np.radians(0.5))
SIGMA_B = (5e-4, 2e-3)


def _plain(monkeypatch):
    """Restore the stopping rule of before (every fast path is switched off by ``cal.PLAIN``)."""
    monkeypatch.setattr(cal, 'XTOL', 1e-5)


def _with_outliers(pairs, rng, share=0.01):
    """Move a share of B's positions by 2-5 cm (gross errors the robust fit must drop)."""
    n = len(pairs)
    idx = rng.choice(n, size=int(share * n), replace=False)
    pos_b = np.array(pairs.pos_b, dtype=float)
    pos_b[idx] += rng.uniform(0.02, 0.05, size=(len(idx), 3)) * rng.choice([-1, 1], (len(idx), 3))
    return replace(pairs, pos_b=pos_b)


def _fit_both(monkeypatch, pairs, settings):
    fast = calibrate(pairs, settings)
    with monkeypatch.context() as m:
        _plain(m)
        plain = calibrate(pairs, settings, paths=cal.PLAIN)
    return fast, plain


@pytest.mark.parametrize('model', ['full_pose', 'position_only'])
@pytest.mark.parametrize('method', ['tls', 'ols'])
@pytest.mark.parametrize('seed', [1, 2, 3])
def test_fast_and_plain_paths_agree(monkeypatch, model, method, seed):
    rng = np.random.default_rng([seed, 11])
    n = 6000
    noisy, _, _ = simulate_pairs(rng, n, model, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    noisy = _with_outliers(noisy, rng)
    # a subsample start at this size (every 4th pair), as for 1M pairs with the default
    monkeypatch.setattr(cal, 'SUBSAMPLE', n // 4)
    monkeypatch.setattr(cal, 'SUBSAMPLE_TLS', n // 8)
    settings = Settings(model=model, method=method, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    fast, plain = _fit_both(monkeypatch, noisy, settings)
    assert fast.success and plain.success
    np.testing.assert_array_equal(fast.inliers, plain.inliers)
    assert (~fast.inliers).sum() >= int(0.01 * n)  # the outliers went
    sd = np.sqrt(np.diag(plain.param_cov))
    assert np.max(np.abs(fast.params - plain.params) / sd) < 0.02
    np.testing.assert_allclose(np.diag(fast.param_cov), np.diag(plain.param_cov), rtol=1e-2)
    # the whole covariance, in correlation units (position-only: T1's rotation is NaN)
    d = np.sqrt(np.diag(plain.param_cov))
    np.testing.assert_allclose(fast.param_cov / np.outer(d, d), plain.param_cov / np.outer(d, d),
                               rtol=0, atol=1e-2)
    assert fast.chi2 == pytest.approx(plain.chi2, rel=1e-6)
    assert fast.dof == plain.dof
    assert fast.residuals.shape == plain.residuals.shape


def test_fast_and_plain_paths_agree_with_a_prior(monkeypatch):
    rng = np.random.default_rng(5)
    noisy, _, truth = simulate_pairs(rng, 4000, 'full_pose', sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    noisy = _with_outliers(noisy, rng)
    monkeypatch.setattr(cal, 'SUBSAMPLE', 1000)
    monkeypatch.setattr(cal, 'SUBSAMPLE_TLS', 1000)
    prior = Prior(base_to_base=UncertainPose(truth.p0, truth.q0, np.diag([1e-4] * 3 + [1e-5] * 3)))
    settings = Settings(model='full_pose', method='tls', sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    fast = calibrate(noisy, settings, prior=prior)
    with monkeypatch.context() as m:
        _plain(m)
        plain = calibrate(noisy, settings, prior=prior, paths=cal.PLAIN)
    np.testing.assert_array_equal(fast.inliers, plain.inliers)
    sd = np.sqrt(np.diag(plain.param_cov))
    assert np.max(np.abs(fast.params - plain.params) / sd) < 0.02
    np.testing.assert_allclose(np.diag(fast.param_cov), np.diag(plain.param_cov), rtol=1e-2)


@pytest.mark.parametrize('seed', [1, 3])
@pytest.mark.parametrize('outliers', [True, False])
def test_the_first_robust_tls_fit_is_screened_before_its_last_pass(monkeypatch, seed, outliers):
    """
    Save one pass over all pairs where pairs are rejected, and change nothing where not.

    ``FastPaths.screen`` leaves out the pass that proves the fit of all pairs converged, makes
    no d² pass more, and when no pair is rejected the paused fit goes on exactly as the plain
    one.
    """
    rng = np.random.default_rng([seed, outliers])
    n = 6000
    noisy, _, _ = simulate_pairs(rng, n, 'full_pose', sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    # the tail of the model's own d² (as the ~1e-4·N pairs of a long recording), or no pair
    monkeypatch.setattr(cal, 'OUTLIER_ALPHA', 3e-3 if outliers else 1e-15)
    monkeypatch.setattr(cal, 'SUBSAMPLE_TLS', n // 8)
    settings = Settings(model='full_pose', method='tls', sigma_a=SIGMA_A, sigma_b=SIGMA_B)

    def counted(screen: bool):
        passes, squares = [], []
        schur, normalised = est.normal_equations_tls.tls_schur, screening.normalised_squares
        with monkeypatch.context() as m:
            m.setattr(est.normal_equations_tls, 'tls_schur',
                      lambda problem, *a, **k: passes.append(problem.n) or schur(problem, *a, **k))
            m.setattr(screening, 'normalised_squares',
                      lambda *a, **k: squares.append(1) or normalised(*a, **k))
            result = calibrate(noisy, settings, paths=cal.FastPaths(screen=screen))
        return result, sum(size > n // 2 for size in passes), len(squares)

    fast, passes, squares = counted(True)
    plain, plain_passes, plain_squares = counted(False)
    assert fast.success and plain.success
    assert (~fast.inliers).any() == outliers
    assert passes == plain_passes - outliers
    assert squares == plain_squares
    np.testing.assert_array_equal(fast.inliers, plain.inliers)
    if not outliers:  # the paused fit goes on exactly as the plain one
        np.testing.assert_array_equal(fast.params, plain.params)
    sd = np.sqrt(np.diag(plain.param_cov))
    assert np.max(np.abs(fast.params - plain.params) / sd) < 0.02


def _problem_and_data(model, pairs, cov_a, cov_b, tls, scale=None):
    spec = SPECS[model]
    qa = quat.validate_quaternions(pairs.quat_a)
    qb = None if pairs.quat_b is None else quat.validate_quaternions(pairs.quat_b)
    pos_a, pos_b = np.asarray(pairs.pos_a, float), np.asarray(pairs.pos_b, float)
    problem = est.Problem(spec, pos_a, qa, pos_b, qb, cal.whitening(cov_b, spec, 'b'),
                          cal.whitening(cov_a, None, 'a'), scale)
    data = linearized.PairData(pos_a, qa, pos_b, qb, cov_a, cal.output_covariance(cov_b, spec),
                               scale, tls)
    return problem, data


@pytest.mark.parametrize('model', ['full_pose', 'position_only'])
@pytest.mark.parametrize('tls', [True, False])
@pytest.mark.parametrize('case', ['isotropic', 'anisotropic', 'scaled'])
def test_screening_equals_the_linearized_statistic(model, tls, case):
    rng = np.random.default_rng(17)
    n = 3000
    noisy, _, _ = simulate_pairs(rng, n, model, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    cov_a, cov_b = noise_covariance(SIGMA_A), noise_covariance(SIGMA_B)
    scale = None
    if case == 'anisotropic':
        cov_a = np.diag([3e-4, 1e-4, 2e-4, 1e-2, 4e-3, 6e-3]) ** 2
        cov_b = np.diag([5e-4, 8e-4, 3e-4, 2e-3, 1e-3, 3e-3]) ** 2
    elif case == 'scaled':
        scale = rng.uniform(0.5, 2.0, n)
    problem, data = _problem_and_data(model, noisy, cov_a, cov_b, tls, scale)
    assert screening.exact_for(problem, tls)
    # at a start a little off the truth, where the statistic of every pair is non-trivial
    params = initialize(problem.spec, problem.pos_a, problem.quat_a, problem.pos_b,
                        problem.quat_b)
    ref = linearized.reference_squares(params, data)
    got = screening.normalised_squares(problem, params, tls)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-9)


def test_screening_refuses_a_problem_it_does_not_cover():
    rng = np.random.default_rng(3)
    noisy, _, _ = simulate_pairs(rng, 200, 'full_pose', sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    cov_a = noise_covariance(SIGMA_A)
    cov_a[0, 3] = cov_a[3, 0] = 0.5 * np.sqrt(cov_a[0, 0] * cov_a[3, 3])  # position-rotation
    problem, _ = _problem_and_data('full_pose', noisy, cov_a, noise_covariance(SIGMA_B), True)
    assert not screening.exact_for(problem, True)
    assert screening.exact_for(problem, False)  # OLS: A's noise does not enter
    params = initialize(problem.spec, problem.pos_a, problem.quat_a, problem.pos_b,
                        problem.quat_b)
    with pytest.raises(ValueError, match='exact_for'):
        screening.normalised_squares(problem, params, True)


@pytest.mark.parametrize('scales', [(1.0, 0.5, 0.2), (1.0, 0.01, 0.001), (1e-12, 1e-12, 1e-12),
                                    (3.0, 3.0, 3.0)])
def test_rotation_spread_is_the_svd_of_the_rotation_vectors(scales):
    rng = np.random.default_rng(8)
    base = quat.exp(rng.normal(size=3))
    q = quat.multiply(base, quat.exp(rng.normal(size=(2000, 3)) * scales))
    q[::3] *= -1.0  # signs must not matter
    spread, axes = rotation_spread(q)
    ref = quat.chordal_mean(q)
    v = quat.log(quat.multiply(quat.conjugate(ref), q))
    v -= v.mean(axis=0)
    _, sv, vt = np.linalg.svd(v / np.sqrt(len(v)), full_matrices=False)
    np.testing.assert_allclose(spread, sv, rtol=1e-9, atol=1e-15)
    if sv[0] > 1e-6:  # axes are defined where the spread is not rounding
        np.testing.assert_allclose(np.abs(np.sum(axes * vt, axis=1)), 1.0, atol=1e-9)
    assert np.all(axes[np.arange(3), np.abs(axes).argmax(axis=1)] > 0)


def test_ols_weights_leave_pairs_out_but_give_their_residuals():
    rng = np.random.default_rng(4)
    noisy, _, _ = simulate_pairs(rng, 3000, 'full_pose', sigma_a=(0.0, 0.0),
                                 sigma_b=SIGMA_B)
    problem, _ = _problem_and_data('full_pose', noisy, noise_covariance(SIGMA_A),
                                   noise_covariance(SIGMA_B), False)
    keep = rng.random(problem.n) > 0.1
    params = initialize(problem.spec, problem.pos_a, problem.quat_a, problem.pos_b,
                        problem.quat_b)
    sub = est.Problem(problem.spec, problem.pos_a[keep], problem.quat_a[keep],
                      problem.pos_b[keep], problem.quat_b[keep], problem.whiten_b,
                      problem.whiten_a)
    a = est.solve_ols(sub, params)
    b = est.solve_ols(replace(problem, weights=keep.astype(float)), params)
    np.testing.assert_allclose(b.params.phi, a.params.phi, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.cov, a.cov, rtol=1e-9)
    assert b.n_rows == a.n_rows and b.chi2 == pytest.approx(a.chi2, rel=1e-12)
    np.testing.assert_allclose(b.residuals[keep], a.residuals, rtol=1e-9, atol=1e-12)
    # the left-out pairs' residuals are those at the solution too
    e = cal.screening.normalised_squares(problem, b.params, False)
    np.testing.assert_allclose(np.sum(b.residuals ** 2, axis=1), e, rtol=1e-9)
    # TLS takes subsets, not weights
    weighted = replace(problem, weights=keep.astype(float))
    with pytest.raises(ValueError, match='weights'):
        est.tls_linearization(weighted, params, est.InputState(problem.pos_a, problem.quat_a),
                              0.0)
    # a weighted problem needs the structured path
    generic = est.Problem(SPECS['three_marker'], problem.pos_a,
                          problem.quat_a, np.repeat(problem.pos_b[:, None], 3, axis=1), None,
                          np.eye(9), problem.whiten_a, weights=keep.astype(float))
    with pytest.raises(ValueError, match='structured'):
        ols._ols_normal(generic, initialize(SPECS['three_marker'], generic.pos_a,
                                            generic.quat_a, generic.pos_b))
