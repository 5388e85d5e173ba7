"""
Tests of the covariance in the ``geometry_msgs/PoseWithCovariance`` layout (docs/design.md §3).

Layout: 6×6 over (x, y, z, δθx, δθy, δθz) with ``R_true = Exp(δθ) R_est`` about the fixed axes
of the header frame. Checked deterministically against a finite-difference conversion from the
reduced-quaternion coordinates, and by Monte Carlo against the empirical covariance of
``(p_true - p_est, log(q_true ⊗ q_est*))`` over repeated simulated datasets.
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.estimator.posterior import joint_pose_covariance, tangent_map, UNKNOWN
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.sim import make_motion, random_truth, simulate_pairs
import numpy as np
import pytest
from scipy import stats

MODELS = tuple(SPECS)


def random_params(spec, rng):
    q0, q1 = rng.normal(size=(2, 4))
    return Parameters.from_transforms(spec, rng.normal(size=3), q0 / np.linalg.norm(q0),
                                      rng.normal(size=(spec.n_markers, 3)),
                                      q1 / np.linalg.norm(q1))


def fd_tangent_map(params, h=1e-7):
    """d(p0, δθ0, p1, δθ1)/dφ by central differences, δθ = log(q(φ + h) ⊗ q(φ)*)."""
    spec = params.spec
    T = np.zeros((12, spec.n_params))
    for j in range(spec.n_params):
        d = np.zeros(spec.n_params)
        d[j] = h
        plus, minus = params.stepped(d), params.stepped(-d)
        T[0:3, j] = (plus.p0 - minus.p0) / (2 * h)
        T[3:6, j] = (quat.log(quat.multiply(plus.q0, quat.conjugate(params.q0)))
                     - quat.log(quat.multiply(minus.q0, quat.conjugate(params.q0)))) / (2 * h)
        T[6:9, j] = (plus.markers[0] - minus.markers[0]) / (2 * h)
        if spec.has_q1:
            T[9:12, j] = (quat.log(quat.multiply(plus.q1, quat.conjugate(params.q1)))
                          - quat.log(quat.multiply(minus.q1, quat.conjugate(params.q1)))) / (2 * h)
    return T


@pytest.mark.parametrize('model', MODELS)
def test_tangent_map_matches_finite_differences(model):
    spec = SPECS[model]
    rng = np.random.default_rng(1)
    for _ in range(20):
        params = random_params(spec, rng)
        T, known = tangent_map(params)
        np.testing.assert_allclose(T, fd_tangent_map(params), atol=1e-8)
        assert known[:9].all() and known[9:].all() == spec.has_q1


@pytest.mark.parametrize('model', MODELS)
def test_joint_pose_covariance_layout(model):
    spec = SPECS[model]
    rng = np.random.default_rng(2)
    params = random_params(spec, rng)
    A = rng.normal(size=(spec.n_params, spec.n_params))
    C_phi = A @ A.T + np.eye(spec.n_params)
    C = joint_pose_covariance(params, C_phi)
    assert C.shape == (12, 12)
    np.testing.assert_array_equal(C, C.T)
    T = fd_tangent_map(params)
    want = T @ C_phi @ T.T
    if spec.has_q1:
        np.testing.assert_allclose(C, want, rtol=1e-6, atol=1e-8 * np.abs(want).max())
        assert np.all(np.linalg.eigvalsh(C) > 0)
    else:
        np.testing.assert_allclose(C[:9, :9], want[:9, :9], rtol=1e-6,
                                   atol=1e-8 * np.abs(want).max())
        # q1 not estimated: UNKNOWN (-1) diagonal and no correlation with anything
        np.testing.assert_array_equal(np.diag(C)[9:], [UNKNOWN] * 3)
        assert UNKNOWN == -1.0
        off = C[9:, :].copy()
        off[:, 9:] -= np.diag([UNKNOWN] * 3)
        np.testing.assert_array_equal(off, 0.0)
        # the position part of T1 keeps its real covariance, marker 1 in φ
        sl = spec.marker_slice(0)
        np.testing.assert_allclose(C[6:9, 6:9], C_phi[sl, sl], rtol=1e-12)


@pytest.mark.parametrize('model', ['position_only', 'three_marker'])
def test_result_marks_unestimated_q1_unknown(model):
    noisy, _, _ = simulate_pairs(np.random.default_rng(3), 100, model)
    r = calibrate(noisy, Settings(model=model))
    c1 = r.tool_to_marker.covariance
    np.testing.assert_array_equal(np.diag(c1)[3:], [-1.0] * 3)
    np.testing.assert_array_equal(c1[3:, :3], 0.0)
    assert np.all(np.diag(c1)[:3] > 0)
    np.testing.assert_array_equal(r.tool_to_marker.quat_wxyz, [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(r.cov_joint[9:, 9:], np.diag([-1.0] * 3))
    assert np.all(np.linalg.eigvalsh(r.base_to_base.covariance) > 0)


# ---------------------------------------------------------------------------------------------
# Monte Carlo
# ---------------------------------------------------------------------------------------------

TRIALS = 150
PAIRS = 300


def monte_carlo(model, method, seed):
    """Errors (TRIALS, 6) of T0 and the reported covariances, one truth and one motion."""
    rng = np.random.default_rng(seed)
    truth = random_truth(rng, model)
    motion = make_motion(rng, 'diverse')
    sigma_a = (0.0002, 0.0005) if method == 'tls' else (0.0, 0.0)
    settings = Settings(model=model, method=method, sigma_a=(0.0002, 0.0005))
    errs, covs = [], []
    for i in range(TRIALS):
        noisy, _, _ = simulate_pairs(np.random.default_rng(10_000 + i), PAIRS, model,
                                     truth=truth, motion=motion, sigma_a=sigma_a)
        r = calibrate(noisy, settings)
        q_est = r.base_to_base.quat_wxyz
        errs.append(np.concatenate([truth.p0 - r.base_to_base.position,
                                    quat.log(quat.multiply(truth.q0, quat.conjugate(q_est)))]))
        covs.append(r.base_to_base.covariance)
    return np.array(errs), np.array(covs)


def check_monte_carlo(errs, covs):
    n = len(errs)
    nees = np.einsum('ni,ni->n', errs, np.linalg.solve(covs, errs[:, :, None])[:, :, 0])
    # Σ NEES ~ χ²(6n) if the covariance is right: a two-sided 0.1 % test on the mean.
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], 6 * n) / n
    assert lo < nees.mean() < hi, f'mean NEES {nees.mean():.2f} outside [{lo:.2f}, {hi:.2f}]'
    # The empirical second moment about the truth against the mean reported covariance.
    C = covs.mean(axis=0)
    E = errs.T @ errs / n
    sd = np.sqrt(np.diag(C))
    # variances: n·E_ii/C_ii ~ χ²(n); six of them, so a 0.1 %/6 band each
    ratio = np.diag(E) / np.diag(C)
    lo, hi = stats.chi2.ppf([1e-3 / 12, 1 - 1e-3 / 12], n) / n
    assert np.all((lo < ratio) & (ratio < hi)), ratio
    # correlations, position-rotation block included: Fisher z within 4 standard errors
    rho_c = C / np.outer(sd, sd)
    rho_e = E / np.sqrt(np.outer(np.diag(E), np.diag(E)))
    z = np.abs(np.arctanh(np.clip(rho_e, -0.999, 0.999))
               - np.arctanh(np.clip(rho_c, -0.999, 0.999))) * np.sqrt(n - 3)
    np.fill_diagonal(z, 0.0)
    assert np.all(z < 4.0), np.round(z, 1)
    # sign of the position-rotation cross-covariance where it is clearly non-zero
    strong = np.abs(rho_c[:3, 3:]) > 0.3
    assert strong.any(), 'the test needs a correlated position-rotation block'
    assert np.all(np.sign(rho_e[:3, 3:][strong]) == np.sign(rho_c[:3, 3:][strong]))
    # and the opposite rotation convention (δθ in the body frame, or a flipped sign) would fail
    flipped = errs * np.array([1, 1, 1, -1, -1, -1])
    rho_f = (flipped.T @ flipped / n) / np.sqrt(np.outer(np.diag(E), np.diag(E)))
    assert np.any(np.sign(rho_f[:3, 3:][strong]) != np.sign(rho_c[:3, 3:][strong]))


@pytest.mark.parametrize('model', MODELS)
def test_monte_carlo_ols(model):
    check_monte_carlo(*monte_carlo(model, 'ols', 7))


@pytest.mark.parametrize('model', MODELS)
def test_monte_carlo_tls(model):
    check_monte_carlo(*monte_carlo(model, 'tls', 7))


def test_base_to_base_covariance_is_the_joint_block():
    noisy, _, _ = simulate_pairs(np.random.default_rng(4), 100, 'full_pose')
    r = calibrate(noisy, Settings())
    np.testing.assert_array_equal(r.cov_joint[:6, :6], r.base_to_base.covariance)
    np.testing.assert_array_equal(r.cov_joint[6:, 6:], r.tool_to_marker.covariance)
