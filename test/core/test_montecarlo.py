"""
Monte Carlo evidence for OLS/TLS (bench/montecarlo.py) at a reduced but honest size.

The slow tests run every scenario of ``montecarlo.SCENARIOS`` with TEST_FRACTION of its
full-size trials (times the environment variable COREG_MC_SCALE, default 1; 1/TEST_FRACTION is
the full size of ``make bench``). Their tolerances widen with fewer trials by the sampling
spread (chi-square / binomial / trial standard errors, see ``montecarlo.tolerances``), so a
correct estimator passes at any size and the test is deterministic (fixed seeds).
COREG_MC_WORKERS (default 1) runs the trials in that many processes.
"""

import os

from bench import montecarlo as mc
from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.estimator import noise_covariance
from coreg_ros.core.planning.crlb import cramer_rao_bound, CRLB_DIMENSION, model_jacobians
from coreg_ros.core.settings import Settings
from coreg_ros.sim import make_motion, random_truth, simulate_pairs
import numpy as np
import pytest

TEST_FRACTION = 0.2
SCALE = float(os.environ.get('COREG_MC_SCALE', '1'))
WORKERS = int(os.environ.get('COREG_MC_WORKERS', '1'))


# ----------------------------------------------------------------------------------------------
# The Cramér-Rao bound itself (fast)
# ----------------------------------------------------------------------------------------------

def _device_b(model, p0, R0, markers, R1, pos_a, Ra):
    """Predict B with a reference model written with rotation matrices: (positions (k*3,), R_B)."""
    pos = [p0 + R0 @ (pos_a + Ra @ p) for p in markers]
    return np.concatenate(pos), R0 @ Ra @ R1


def _rot(v):
    return quat.to_matrix(quat.exp(np.asarray(v, dtype=float)))


def _log_matrix(R):
    return quat.log(quat.from_matrix(R))


@pytest.mark.parametrize('model', ['full_pose', 'position_only', 'three_marker'])
def test_crlb_jacobians_match_finite_differences(model):
    rng = np.random.default_rng(11)
    truth = random_truth(rng, model)
    pos_a = rng.normal(size=(4, 3)) * 0.2
    quat_a = quat.exp(rng.normal(size=(4, 3)))
    f_psi, f_x = model_jacobians(model, truth.p0, truth.q0, truth.markers, pos_a, quat_a)
    R0, R1 = quat.to_matrix(truth.q0), quat.to_matrix(truth.q1)
    full = model == 'full_pose'
    k = len(truth.markers)
    h = 1e-6

    def y(psi, x, i):
        """Measurement of pair i with ψ and x (left) perturbations, ROS tangent around truth."""
        markers = truth.markers + psi[6:6 + 3 * k].reshape(k, 3)
        R0p = _rot(psi[3:6]) @ R0
        R1p = _rot(psi[9:12]) @ R1 if full else R1
        Ra = _rot(x[3:6]) @ quat.to_matrix(quat_a[i])
        pos, RB = _device_b(model, truth.p0 + psi[0:3], R0p, markers, R1p, pos_a[i] + x[0:3],
                            Ra)
        _, RB0 = _device_b(model, truth.p0, R0, truth.markers, R1, pos_a[i],
                           quat.to_matrix(quat_a[i]))
        return np.concatenate([pos, _log_matrix(RB @ RB0.T)]) if full else pos

    d = CRLB_DIMENSION[model]
    for i in range(len(pos_a)):
        for j in range(d):
            e = np.zeros(d)
            e[j] = h
            num = (y(e, np.zeros(6), i) - y(-e, np.zeros(6), i)) / (2 * h)
            np.testing.assert_allclose(f_psi[i, :, j], num, atol=1e-7)
        for j in range(6):
            e = np.zeros(6)
            e[j] = h
            num = (y(np.zeros(d), e, i) - y(np.zeros(d), -e, i)) / (2 * h)
            np.testing.assert_allclose(f_x[i, :, j], num, atol=1e-7)


def test_crlb_reduces_to_ols_bound_without_input_noise():
    rng = np.random.default_rng(5)
    truth = random_truth(rng)
    _, clean, _ = simulate_pairs(rng, 200, truth=truth)
    cov_b = noise_covariance((5e-4, 2e-3))
    crlb, info = cramer_rao_bound('full_pose', truth.p0, truth.q0, truth.markers, clean.pos_a,
                                  clean.quat_a, np.zeros((6, 6)), cov_b)
    f_psi, _ = model_jacobians('full_pose', truth.p0, truth.q0, truth.markers, clean.pos_a,
                               clean.quat_a)
    ols_info = np.einsum('nmi,mk,nkj->ij', f_psi, np.linalg.inv(cov_b), f_psi)
    np.testing.assert_allclose(info, ols_info, rtol=1e-10, atol=1e-12 * np.abs(info).max())
    with_a, _ = cramer_rao_bound('full_pose', truth.p0, truth.q0, truth.markers, clean.pos_a,
                                 clean.quat_a, noise_covariance((2e-4, 5e-4)), cov_b)
    assert np.all(np.diag(with_a) > np.diag(crlb))  # input noise costs information


@pytest.mark.parametrize('model', ['full_pose', 'position_only'])
def test_reported_tls_covariance_is_the_crlb(model):
    """The estimator's Schur complement at its estimate matches the independent bound."""
    rng = np.random.default_rng(9)
    truth, motion = random_truth(rng, model), make_motion(rng)
    sigma_a, sigma_b = (2e-4, 5e-4), (5e-4, 2e-3)
    noisy, clean, _ = simulate_pairs(rng, 1000, model, sigma_a=sigma_a, sigma_b=sigma_b,
                                     truth=truth, motion=motion)
    r = calibrate(noisy, Settings(model=model, method='tls', sigma_a=sigma_a, sigma_b=sigma_b))
    d = mc.dimension(model)
    crlb, _ = cramer_rao_bound(model, truth.p0, truth.q0, truth.markers, clean.pos_a,
                               clean.quat_a, noise_covariance(sigma_a), noise_covariance(sigma_b))
    np.testing.assert_allclose(np.diag(r.cov_joint[:d, :d]), np.diag(crlb), rtol=0.01)


# ----------------------------------------------------------------------------------------------
# Statistics helpers (fast)
# ----------------------------------------------------------------------------------------------

def test_statistics_on_known_gaussian_samples():
    rng = np.random.default_rng(0)
    C = np.diag([1.0, 4.0, 9.0])
    e = rng.multivariate_normal(np.zeros(3), C, size=4000)
    assert mc.bias_test(e)['hotelling_p'] > 1e-3
    assert mc.bias_test(e + [0.0, 0.3, 0.0])['hotelling_p'] < 1e-6
    eff = mc.efficiency(e, C)
    assert abs(eff['trace_ratio'] - 1) < 4 * eff['trace_ratio_se']
    n = mc.nees(e, np.broadcast_to(C, (4000, 3, 3)))
    assert abs(n['mean_nees'] - 3) < 0.2 and abs(n['coverage95'] - 0.95) < 0.015
    assert mc.chi2_calibration(rng.uniform(size=1000))['ks_p'] > 0.01
    assert mc.chi2_calibration(rng.uniform(size=1000) ** 2)['ks_p'] < 1e-6


# ----------------------------------------------------------------------------------------------
# Monte Carlo (slow)
# ----------------------------------------------------------------------------------------------

BUG_DAMPED_COV = ('known BUG (test_calibrate.py BUG_DAMPED_COV): solve_tls returns the last '
                  'damped Schur complement as the covariance when it stops on the flat-cost path')
COV_CHECKS = ('NEES mean', '95% coverage', 'trials whose covariance is off the CRLB')


def _off_trials(report):
    return {m: s['collapsed_cov']['trials'] for m, s in report['methods'].items()
            if s['collapsed_cov']['trials']}


def _only_damped_covariance(report):
    """Tell whether every failed check is a covariance check explained by the off-CRLB trials."""
    for stat in report['methods'].values():
        bad = [c['check'] for c in stat['checks'] if not c['passed']]
        if any(not c.startswith(COV_CHECKS) for c in bad):
            return False
        if bad:
            n = stat.get('nees_on_crlb_trials')
            K = n and stat['n_trials'] - stat['collapsed_cov']['n_off']
            tol = mc.tolerances(K, n['dim']) if n else None
            if not (n and stat['collapsed_cov']['n_off'] and abs(n['mean_nees'] - n['dim'])
                    <= tol['nees'] and abs(n['coverage95'] - 0.95) <= tol['coverage']):
                return False
    return True


@pytest.mark.slow
@pytest.mark.parametrize('scenario', mc.SCENARIOS, ids=[s.name for s in mc.SCENARIOS])
def test_monte_carlo_scenario(scenario):
    n_trials = max(50, round(scenario.n_trials * TEST_FRACTION * SCALE))
    report = mc.run_scenario(scenario, n_trials=n_trials, workers=WORKERS)
    failed = [f'{m.upper()} {c["check"]}: {c["value"]:.4g} not in [{c["lo"]:.4g}, {c["hi"]:.4g}]'
              for m, stat in report['methods'].items() for c in stat['checks']
              if not c['passed']]
    if failed and _only_damped_covariance(report):
        pytest.xfail(f'{BUG_DAMPED_COV}: trials {_off_trials(report)} report a covariance far '
                     f'from the CRLB; all other checks pass\n' + '\n'.join(failed))
    assert not failed, '\n'.join([scenario.note, *failed, mc.markdown_table([report])])
    if scenario.name == 'output_noise_only':
        # with A noise-free, TLS must reproduce OLS (the same ML estimator)
        ols, tls = (report['methods'][m]['efficiency']['trace_ratio'] for m in ('ols', 'tls'))
        assert abs(ols - tls) < 1e-3 * ols
    if scenario.name == 'input_noise_long_lever':
        ols = report['methods']['ols']
        tls = report['methods']['tls']
        assert ols['efficiency']['trace_ratio'] > 3 * tls['efficiency']['trace_ratio']
