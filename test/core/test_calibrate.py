"""
Tests of calibrate(), of the stream pipeline and of the result's dict layout.

calibrate(): closed-form start, OLS / TLS, priors, chi-square, covariance.

Errors are measured as ``p_true - p_est`` and ``δθ = log(q_true ⊗ q_est*)``
(``R_true = Exp(δθ) R_est``, the ROS layout of docs/design.md §3). Accuracy is judged against the
reported covariance with a Mahalanobis (NEES) bound from the chi-square distribution, with a
Bonferroni correction over the seeds of a test, never per axis.
"""

import json

from coreg_ros.core import estimator as est
from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.estimator import noise_covariance, tls, whitening
from coreg_ros.core.estimator.posterior import joint_pose_covariance
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import UncertainPose
from coreg_ros.files.results import result_to_dict
from coreg_ros.sim import simulate_pairs, simulate_recording
import numpy as np
import pytest
from scipy import stats
from strategies import scipy_rotation, WXYZ

MODELS = tuple(SPECS)
ZERO = (0.0, 0.0)
SIGMA_A = (0.0002, 0.0005)  # the defaults of Settings and the simulator
SIGMA_B = (0.0005, 0.002)
N_SEEDS = 20
#: Two-sided 3σ probability, split over the seeds of a test (Bonferroni).
P_3SIGMA = 2 * stats.norm.sf(3.0)


def pose_error(truth_p, truth_q, pose):
    """(p_true - p_est, log(q_true ⊗ q_est*)), shape (6,)."""
    dtheta = quat.log(quat.multiply(truth_q, quat.conjugate(pose.quat_wxyz)))
    return np.concatenate([truth_p - pose.position, dtheta])


def nees(err, cov):
    return float(err @ np.linalg.solve(cov, err))


def simulate(model, method, seed, n=200):
    """Pairs whose noise matches the estimator's assumptions (OLS: A noise-free)."""
    sigma_a = ZERO if method == 'ols' else SIGMA_A
    return simulate_pairs(np.random.default_rng(seed), n, model, sigma_a=sigma_a,
                          sigma_b=SIGMA_B)


def settings_for(model, method, **kw):
    return Settings(model=model, method=method, sigma_a=SIGMA_A, sigma_b=SIGMA_B, **kw)


# ---------------------------------------------------------------------------------------------
# Convergence from no guess and accuracy within the reported covariance
# ---------------------------------------------------------------------------------------------

def _recovery(model, method):
    bound = stats.chi2.isf(P_3SIGMA / N_SEEDS, df=6)
    spec = SPECS[model]
    total, total_dof = 0.0, 0
    chi2_sum, dof_sum = 0.0, 0
    for seed in range(N_SEEDS):
        noisy, _, truth = simulate(model, method, seed)
        r = calibrate(noisy, settings_for(model, method))
        assert r.success, f'seed {seed}: {r.message}'
        assert r.status in (1, 2) and 1 <= r.iterations <= 100
        assert r.model == model and r.method == method and r.n_pairs == len(noisy)
        e0 = pose_error(truth.p0, truth.q0, r.base_to_base)
        n0 = nees(e0, r.base_to_base.covariance)
        assert n0 < bound, f'seed {seed}: T0 NEES {n0:.1f} > {bound:.1f}'
        total, total_dof = total + n0, total_dof + 6
        if spec.has_q1:
            e1 = pose_error(truth.p1, truth.q1, r.tool_to_marker)
            n1 = nees(e1, r.tool_to_marker.covariance)
        else:
            e1 = truth.p1 - r.tool_to_marker.position
            n1 = nees(e1, r.tool_to_marker.covariance[:3, :3])
        assert n1 < bound, f'seed {seed}: T1 NEES {n1:.1f} > {bound:.1f}'
        total, total_dof = total + n1, total_dof + len(e1)
        # all marker positions, from the parameter covariance
        em = (truth.markers - r.markers).ravel()
        cm = np.zeros((em.size, em.size))
        for i in range(spec.n_markers):
            for j in range(spec.n_markers):
                cm[3 * i:3 * i + 3, 3 * j:3 * j + 3] = r.param_cov[spec.marker_slice(i),
                                                                   spec.marker_slice(j)]
        assert nees(em, cm) < stats.chi2.isf(P_3SIGMA / N_SEEDS, df=em.size)
        chi2_sum, dof_sum = chi2_sum + r.chi2, dof_sum + r.dof
    # Aggregate: the sum of the NEES is chi-square distributed (the T0 and T1 errors of one fit
    # are correlated, which only widens the spread; the 0.1 % / 99.9 % band is generous).
    assert stats.chi2.ppf(1e-3, total_dof) / 2 < total < 2 * stats.chi2.isf(1e-3, total_dof)
    # Goodness of fit: Σ chi2 over the seeds ~ χ²(Σ dof) when the noise model holds.
    z = (chi2_sum - dof_sum) / np.sqrt(2 * dof_sum)
    assert abs(z) < 4.0, f'Σchi2 = {chi2_sum:.0f} for Σdof = {dof_sum}: z = {z:.1f}'


@pytest.mark.parametrize('model', MODELS)
def test_calibrate_ols_recovers_random_truths_within_covariance(model):
    _recovery(model, 'ols')


@pytest.mark.parametrize('model', MODELS)
def test_calibrate_tls_recovers_random_truths_within_covariance(model):
    _recovery(model, 'tls')


def _tls_reference_covariance(result, noisy, settings):
    """Rebuild the undamped Schur complement at the solution from the result."""
    spec = SPECS[result.model]
    qa = quat.validate_quaternions(noisy.quat_a)
    qb = None if noisy.quat_b is None else quat.validate_quaternions(noisy.quat_b)
    problem = est.Problem(spec, noisy.pos_a, qa, noisy.pos_b, qb,
                          whitening(noise_covariance(settings.sigma_b), spec, 'b'),
                          whitening(noise_covariance(settings.sigma_a), None, 'a'))
    params = Parameters.from_transforms(spec, result.base_to_base.position,
                                        result.base_to_base.quat_wxyz, result.markers,
                                        result.tool_to_marker.quat_wxyz)
    # adjusted inputs from the whitened input residuals (isotropic A noise)
    e_pos = result.input_residuals[:, 0:3] * settings.sigma_a[0]
    e_rot = result.input_residuals[:, 3:6] * settings.sigma_a[1] / 2
    w = np.sqrt(1 - np.sum(e_rot ** 2, axis=1))
    xq = quat.multiply(np.concatenate([w[:, None], e_rot], axis=1), qa)
    S = tls._tls_schur(problem, params, est.InputState(noisy.pos_a + e_pos, xq), 0.0)[0]
    return joint_pose_covariance(params, np.linalg.inv(S))[0:6, 0:6]


@pytest.mark.parametrize('model, seed', [('full_pose', 29), ('position_only', 39)])
def test_tls_covariance_is_not_damped(model, seed):
    noisy, _, truth = simulate(model, 'tls', seed, n=100)
    s = settings_for(model, 'tls')
    r = calibrate(noisy, s)
    assert r.success
    ref = _tls_reference_covariance(r, noisy, s)
    # with the undamped covariance this truth is an ordinary draw
    assert nees(pose_error(truth.p0, truth.q0, r.base_to_base), ref) < 30
    np.testing.assert_allclose(np.diag(r.base_to_base.covariance), np.diag(ref), rtol=1e-3)


def test_converged_calibration_is_not_reported_as_a_misfit():
    noisy, _, truth = simulate_pairs(np.random.default_rng(37), 30, 'position_only')
    r = calibrate(noisy, Settings(model='position_only', method='ols'))
    # the estimate itself is fine
    assert nees(pose_error(truth.p0, truth.q0, r.base_to_base), r.base_to_base.covariance) < 20
    assert r.success, r.message


# ---------------------------------------------------------------------------------------------
# Chi-square, degrees of freedom, residuals
# ---------------------------------------------------------------------------------------------

def independent_output_residuals(result, pairs):
    """Whitened residuals from the result's transforms, with scipy rotations only."""
    R0 = scipy_rotation(result.base_to_base.quat_wxyz)
    Ra = scipy_rotation(pairs.quat_a)
    cols = []
    for m in np.atleast_2d(result.markers):
        pred = result.base_to_base.position + R0.apply(pairs.pos_a + Ra.apply(m))
        cols.append(pred)
    pos_b = pairs.pos_b if pairs.pos_b.ndim == 3 else pairs.pos_b[:, None, :]
    e = (np.stack(cols, axis=1) - pos_b).reshape(len(pairs), -1) / SIGMA_B[0]
    if result.model == 'full_pose':
        q_pred = (R0 * Ra * scipy_rotation(result.tool_to_marker.quat_wxyz)).as_quat()[..., WXYZ]
        E = quat.canonical(quat.multiply(q_pred, quat.conjugate(pairs.quat_b)))
        e = np.concatenate([e, E[:, 1:] * 2.0 / SIGMA_B[1]], axis=1)
    return e


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('method', ['ols', 'tls'])
def test_chi2_dof_and_residuals(model, method):
    spec = SPECS[model]
    n = 120
    noisy, _, _ = simulate(model, method, 100, n=n)
    r = calibrate(noisy, settings_for(model, method))
    assert r.success, r.message
    assert r.dof == n * spec.n_res - spec.n_params
    assert r.residuals.shape == (n, spec.n_res)
    assert r.params.shape == (spec.n_params,) and r.param_cov.shape == (spec.n_params,) * 2
    if method == 'ols':
        assert r.input_residuals is None
        np.testing.assert_allclose(r.chi2, np.sum(r.residuals ** 2), rtol=1e-10)
        np.testing.assert_allclose(r.residuals, independent_output_residuals(r, noisy),
                                   rtol=1e-6, atol=1e-9)
    else:
        assert r.input_residuals.shape == (n, 6)
        np.testing.assert_allclose(
            r.chi2, np.sum(r.residuals ** 2) + np.sum(r.input_residuals ** 2), rtol=1e-10)
    assert r.p_value == pytest.approx(stats.chi2.sf(r.chi2, r.dof), rel=1e-12)
    assert 0.0 < r.p_value < 1.0


def test_tls_with_negligible_a_noise_matches_ols():
    for model in MODELS:
        noisy, _, _ = simulate_pairs(np.random.default_rng(5), 150, model, sigma_a=ZERO,
                                     sigma_b=SIGMA_B)
        s = {'model': model, 'sigma_a': (1e-8, 1e-8), 'sigma_b': SIGMA_B}
        ols = calibrate(noisy, Settings(method='ols', **s))
        tls = calibrate(noisy, Settings(method='tls', **s))
        sd = np.sqrt(np.diag(ols.param_cov))
        assert np.all(np.abs(tls.params - ols.params) < 1e-3 * sd)
        np.testing.assert_allclose(np.diag(tls.param_cov), np.diag(ols.param_cov), rtol=1e-3)
        assert tls.dof == ols.dof
        assert tls.chi2 == pytest.approx(ols.chi2, rel=1e-3)


def test_tls_beats_ols_when_a_is_noisy():
    """With A as noisy as B, OLS's covariance is too small; TLS's is honest (Ikits §5)."""
    model = 'full_pose'
    s = {'model': model, 'sigma_a': SIGMA_B, 'sigma_b': SIGMA_B}
    chi2 = {'ols': [], 'tls': []}
    for seed in range(6):
        noisy, _, _ = simulate_pairs(np.random.default_rng(seed), 150, model, sigma_a=SIGMA_B,
                                     sigma_b=SIGMA_B)
        for method in chi2:
            r = calibrate(noisy, Settings(method=method, **s))
            chi2[method].append(r.chi2 / r.dof)
    assert np.mean(chi2['ols']) > 1.5  # OLS attributes A's noise to B: a misfit
    assert abs(np.mean(chi2['tls']) - 1.0) < 0.1


# ---------------------------------------------------------------------------------------------
# A priori estimates (Ikits B.3)
# ---------------------------------------------------------------------------------------------

def _with_prior(model, method, prior):
    noisy, _, truth = simulate(model, method, 21, n=150)
    s = settings_for(model, method)
    return calibrate(noisy, s), calibrate(noisy, s, prior=prior), truth


def _shifted_pose(pose, z):
    """Move the pose by the tangent vector z = (δp, δθ): p + δp, Exp(δθ) ⊗ q."""
    return pose.position + z[:3], quat.canonical(quat.multiply(quat.exp(z[3:]), pose.quat_wxyz))


@pytest.mark.parametrize('model, method', [(m, k) for m in MODELS for k in ('ols', 'tls')])
def test_prior_fuses_like_inverse_covariance_weighting(model, method):
    base, _, _ = _with_prior(model, method, None)
    cd = base.base_to_base.covariance
    z_p = 2.0 * np.sqrt(np.diag(cd)) * np.array([1, -1, 1, -1, 1, 1])
    cp = 0.5 * cd + np.diag(np.diag(cd)) * 0.5  # same order as the data, a different shape
    p_hat, q_hat = _shifted_pose(base.base_to_base, z_p)
    prior = Prior(base_to_base=UncertainPose(p_hat, q_hat, cp))
    _, r, _ = _with_prior(model, method, prior)
    c_post = np.linalg.inv(np.linalg.inv(cd) + np.linalg.inv(cp))
    np.testing.assert_allclose(r.base_to_base.covariance, c_post, rtol=2e-3,
                               atol=2e-3 * np.sqrt(np.outer(np.diag(c_post),
                                                            np.diag(c_post))).max())
    z_post = c_post @ np.linalg.solve(cp, z_p)  # fused tangent offset from the data estimate
    want_p, want_q = _shifted_pose(base.base_to_base, z_post)
    got = np.concatenate([r.base_to_base.position - want_p,
                          quat.log(quat.multiply(r.base_to_base.quat_wxyz,
                                                 quat.conjugate(want_q)))])
    assert np.all(np.abs(got) < 0.02 * np.sqrt(np.diag(c_post))), got / np.sqrt(np.diag(c_post))
    assert r.dof == base.dof + 6


@pytest.mark.parametrize('model', MODELS)
def test_tight_prior_pulls_and_loose_prior_does_not(model):
    base, _, truth = _with_prior(model, 'ols', None)
    cd = base.base_to_base.covariance
    z = 5.0 * np.sqrt(np.diag(cd)) * np.array([1, 1, -1, 1, -1, 1])
    p_hat, q_hat = _shifted_pose(base.base_to_base, z)
    tight = Prior(base_to_base=UncertainPose(p_hat, q_hat, 1e-6 * cd))
    _, r, _ = _with_prior(model, 'ols', tight)
    err = np.concatenate([r.base_to_base.position - p_hat,
                          quat.log(quat.multiply(r.base_to_base.quat_wxyz,
                                                 quat.conjugate(q_hat)))])
    assert np.all(np.abs(err) < 0.01 * np.sqrt(np.diag(cd)))
    assert np.all(np.diag(r.base_to_base.covariance) < 2e-6 * np.diag(cd))
    assert r.dof == base.dof + 6
    loose = Prior(base_to_base=UncertainPose(truth.p0 + 0.3, truth.q0, np.diag([1.0] * 6)))
    _, r, _ = _with_prior(model, 'ols', loose)
    assert np.all(np.abs(r.params - base.params) < 1e-3 * np.sqrt(np.diag(base.param_cov)))
    np.testing.assert_allclose(np.diag(r.param_cov), np.diag(base.param_cov), rtol=1e-3)
    assert r.dof == base.dof + 6


@pytest.mark.parametrize('model', MODELS)
def test_tool_to_marker_prior_rows(model):
    """A T1 prior adds 6 rows with q1 estimated, 3 (position only) otherwise."""
    base, _, truth = _with_prior(model, 'ols', None)
    c1 = np.diag([1e-8] * 3 + [1e-6] * 3)
    prior = Prior(tool_to_marker=UncertainPose(truth.p1, truth.q1, c1))
    _, r, _ = _with_prior(model, 'ols', prior)
    assert r.dof == base.dof + (6 if SPECS[model].has_q1 else 3)
    assert np.linalg.norm(r.tool_to_marker.position - truth.p1) < 5 * np.sqrt(1e-8)
    assert np.all(np.diag(r.tool_to_marker.covariance)[:3] < 1.01e-8)


# ---------------------------------------------------------------------------------------------
# Pipeline and result layout
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('model', MODELS)
def test_calibrate_streams_on_a_simulated_recording(model):
    rec = simulate_recording(4, 30.0, model)
    s = Settings(model=model, method='tls')
    result, report = calibrate_streams(rec.stream_a, list(rec.streams_b), s)
    assert result.success, result.message
    assert report.n_paired == result.n_pairs
    assert report.n_paired + sum(report.unpaired.values()) == report.n_b
    assert report.n_paired > 0.95 * len(rec.streams_b[0])
    t = rec.truth
    # interpolated A: slightly more noise than modelled, so allow the 99.99 % point
    assert nees(pose_error(t.p0, t.q0, result.base_to_base), result.base_to_base.covariance) \
        < stats.chi2.isf(1e-4, 6)
    assert np.abs(result.markers - t.markers).max() < 5e-3


def test_result_to_dict_layout():
    noisy, _, _ = simulate('full_pose', 'tls', 3, n=80)
    r = calibrate(noisy, settings_for('full_pose', 'tls'))
    d = result_to_dict(r)
    assert set(d) == {'success', 'status', 'message', 'method', 'model', 'n_pairs', 'chi2',
                      'dof', 'p_value', 'iterations', 'base_to_base', 'tool_to_marker',
                      'markers', 'fit_consistent', 'verdict', 'rejected_pairs', 'cov_joint',
                      'unobservable'}
    assert d['unobservable'] == []  # free motion determines everything
    json.dumps(d, allow_nan=False)  # plain JSON
    for key, pose in (('base_to_base', r.base_to_base), ('tool_to_marker', r.tool_to_marker)):
        p = d[key]
        assert set(p) == {'position', 'orientation', 'covariance'}
        assert p['position'] == pytest.approx(list(pose.position))
        o = p['orientation']
        assert [o['w'], o['x'], o['y'], o['z']] == pytest.approx(list(pose.quat_wxyz))
        assert len(p['covariance']) == 36 and all(isinstance(v, float) for v in p['covariance'])
        np.testing.assert_array_equal(np.reshape(p['covariance'], (6, 6)), pose.covariance)
    assert d['markers'] == [pytest.approx(list(r.markers[0]))]
    assert d['dof'] == r.dof and d['chi2'] == pytest.approx(r.chi2)
    assert d['model'] == 'full_pose' and d['method'] == 'tls' and d['n_pairs'] == 80


def test_result_to_dict_marks_unestimated_q1():
    noisy, _, _ = simulate('three_marker', 'ols', 3, n=80)
    d = result_to_dict(calibrate(noisy, settings_for('three_marker', 'ols')))
    cov = np.reshape(d['tool_to_marker']['covariance'], (6, 6))
    np.testing.assert_array_equal(np.diag(cov)[3:], [-1.0, -1.0, -1.0])
    assert len(d['markers']) == 3
