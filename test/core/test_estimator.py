"""
Tests of the closed-form start (initialize) and the OLS / TLS solvers (Ikits B.1, B.2, B.4).

The TLS solver never forms the dense (6N+P)² system; here, at small N, the dense system is built
independently (by finite differences of a residual function written in this file) to check the
Schur-complement covariance, the stationarity of the solution and the chi-square.
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.initialize import (
    DEGENERATE_RATIO,
    initialize,
    project_to_so3,
    rotations_from_pairs,
)
from coreg_ros.core.errors import InputError
from coreg_ros.core.estimator import (
    lm,
    metric_covariance,
    noise_covariance,
    Problem,
    solve_ols,
    solve_tls,
    whitening,
)
from coreg_ros.core.models import output_error, Parameters, SPECS
from coreg_ros.core.types import STATUS
from coreg_ros.sim import simulate_pairs, Truth
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

MODELS = tuple(SPECS)
ZERO = (0.0, 0.0)


def rotation_gap(q, r):
    """Angle (rad) between two rotations, accurate near zero (unlike arccos of a dot product)."""
    return float(np.linalg.norm(quat.log(quat.multiply(q, quat.conjugate(r)))))


def assert_recovers(params, truth, atol_pos=1e-9, atol_rot=1e-9):
    assert np.abs(params.p0 - truth.p0).max() < atol_pos
    assert np.abs(params.markers - truth.markers).max() < atol_pos
    assert rotation_gap(params.q0, truth.q0) < atol_rot
    if params.spec.has_q1:
        assert rotation_gap(params.q1, truth.q1) < atol_rot


# ---------------------------------------------------------------------------------------------
# Closed-form initialisation
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('model', MODELS)
def test_initialize_is_exact_on_noiseless_data(model):
    for seed in range(25):
        rng = np.random.default_rng(seed)
        _, clean, truth = simulate_pairs(rng, 80, model, sigma_a=ZERO, sigma_b=ZERO)
        params = initialize(SPECS[model], clean.pos_a, clean.quat_a, clean.pos_b, clean.quat_b)
        assert_recovers(params, truth)
        for block, (k, sg) in zip(SPECS[model].rotation_blocks, params.charts, strict=True):
            assert not quat.needs_rechart(params.phi[block], k, sg)


def _half_turn(axis):
    axis = np.asarray(axis, dtype=float)
    return np.concatenate([[0.0], axis / np.linalg.norm(axis)])


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('q0, q1', [
    (_half_turn([1, 0, 0]), _half_turn([0, 1, 1])),
    (_half_turn([0.3, -0.4, 0.8]), [1.0, 0.0, 0.0, 0.0]),
    ([1.0, 0.0, 0.0, 0.0], _half_turn([0, 0, 1])),
    (quat.exp(np.array([0.0, np.pi - 1e-7, 0.0])), quat.exp(np.array([1e-9, 0.0, 0.0]))),
])
def test_initialize_exact_near_180_degrees_and_identity(model, q0, q1):
    rng = np.random.default_rng(5)
    k = 3 if model == 'three_marker' else 1
    markers = np.array([[0.1, -0.05, 0.08], [0.0, 0.1, 0.05], [-0.08, 0.02, 0.1]])[:k]
    truth = Truth(p0=[0.5, -0.7, 0.2], q0=q0, p1=markers[0], q1=q1, markers=markers,
                  model=model)
    _, clean, _ = simulate_pairs(rng, 60, model, sigma_a=ZERO, sigma_b=ZERO, truth=truth)
    params = initialize(SPECS[model], clean.pos_a, clean.quat_a, clean.pos_b, clean.quat_b)
    assert_recovers(params, truth)


def test_rotations_from_pairs_exact():
    R0 = Rotation.random(random_state=1).as_matrix()
    R1 = Rotation.random(random_state=2).as_matrix()
    Ra = Rotation.random(30, random_state=3).as_matrix()
    Rb = R0 @ Ra @ R1
    g0, g1, ratio = rotations_from_pairs(Ra, Rb)
    np.testing.assert_allclose(g0, R0, atol=1e-12)
    np.testing.assert_allclose(g1, R1, atol=1e-12)
    assert ratio < DEGENERATE_RATIO


@pytest.mark.parametrize('motion', ['scara', 'planar', 'gantry'])
def test_full_pose_start_of_a_restricted_rig_takes_r0_from_the_positions(motion):
    """Rotation about one axis or none: the rotations leave R0 open, the positions do not."""
    from coreg_ros.sim import simulate_pairs
    noisy, _, truth = simulate_pairs(np.random.default_rng(4), 2000, 'full_pose',
                                     motion=motion)
    Ra, Rb = quat.to_matrix(noisy.quat_a), quat.to_matrix(noisy.quat_b)
    assert rotations_from_pairs(Ra, Rb)[2] > DEGENERATE_RATIO
    start = initialize(SPECS['full_pose'], noisy.pos_a, noisy.quat_a, noisy.pos_b,
                       noisy.quat_b)
    # the Kronecker start alone was off by 20-160°; from 3-D translations R0 is within a
    # degree; a planar base (z constant) leaves R0's tilt to the rotation regressors of the
    # lifting, a few degrees, from which the fit converges
    limit = 10.0 if motion == 'planar' else 1.0
    assert np.degrees(quat.angle_between(start.q0, truth.q0)) < limit


def test_project_to_so3():
    R = Rotation.random(random_state=4).as_matrix()
    np.testing.assert_allclose(project_to_so3(R), R, atol=1e-14)
    noisy = R + 1e-3 * np.random.default_rng(0).normal(size=(3, 3))
    P = project_to_so3(noisy)
    np.testing.assert_allclose(P @ P.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(P) > 0
    # a reflection is projected onto a proper rotation
    P = project_to_so3(R @ np.diag([1.0, 1.0, -1.0]))
    np.testing.assert_allclose(P @ P.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(P) > 0


# ---------------------------------------------------------------------------------------------
# Solvers on a dense reference problem
# ---------------------------------------------------------------------------------------------

SIGMA_A = (3e-4, 1e-3)
SIGMA_B = (5e-4, 2e-3)


def make_problem(model, n, seed, sigma_a=SIGMA_A, sigma_b=SIGMA_B):
    rng = np.random.default_rng(seed)
    noisy, _, truth = simulate_pairs(rng, n, model, sigma_a=sigma_a, sigma_b=sigma_b)
    spec = SPECS[model]
    qa = quat.validate_quaternions(noisy.quat_a)
    qb = None if noisy.quat_b is None else quat.validate_quaternions(noisy.quat_b)
    problem = Problem(spec, noisy.pos_a, qa, noisy.pos_b, qb,
                      whitening(noise_covariance(sigma_b), spec, 'b'),
                      whitening(noise_covariance(sigma_a), None, 'a'))
    return problem, truth


def independent_whitened_output(model, sigma_b, e):
    """Whitened output error for isotropic noise: position / σp, rotation metric / (σr / 2)."""
    w = np.full(e.shape[1], 1.0 / sigma_b[0])
    if model == 'full_pose':
        w[3:6] = 2.0 / sigma_b[1]
    return e * w


def dense_tls_residual(problem, params, x_pos, x_quat, sigma_a, sigma_b, model):
    """All TLS residuals: whitened output errors at the adjusted inputs, then input errors."""
    e_y = output_error(params, x_pos, x_quat, problem.pos_b, problem.quat_b)
    r_y = independent_whitened_output(model, sigma_b, e_y)
    e_rot, _ = quat.rotation_error(x_quat, problem.quat_a)
    r_x = np.concatenate([(x_pos - problem.pos_a) / sigma_a[0], e_rot * 2.0 / sigma_a[1]], 1)
    return np.concatenate([r_y.ravel(), r_x.ravel()])


def reconstruct_inputs(problem, input_residuals, sigma_a):
    """Adjust the inputs by the whitened input residuals: e = x - x̂, rotation metric e_q."""
    e_pos = input_residuals[:, 0:3] * sigma_a[0]
    e_rot = input_residuals[:, 3:6] * sigma_a[1] / 2.0
    w = np.sqrt(1.0 - np.sum(e_rot ** 2, axis=1))
    x_quat = quat.multiply(np.concatenate([w[:, None], e_rot], axis=1), problem.quat_a)
    return problem.pos_a + e_pos, x_quat


def assert_same_covariance(got, want, tol=1e-5):
    """Equal variances (relative) and equal correlations (absolute), to tol."""
    sd = np.sqrt(np.diag(want))
    np.testing.assert_allclose(np.diag(got), np.diag(want), rtol=tol)
    np.testing.assert_allclose(got / np.outer(sd, sd), want / np.outer(sd, sd), atol=tol)


def dense_jacobian(fun, P, n, h=1e-7):
    """Central differences over (δφ (P), then per pair δp (3), δθ (3) with q ← Exp(δθ) ⊗ q)."""
    cols = []
    for j in range(P + 6 * n):
        cols.append((fun(j, h) - fun(j, -h)) / (2 * h))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize('model', ['full_pose', 'position_only', 'three_marker'])
def test_tls_covariance_is_the_phi_block_of_the_dense_inverse(model):
    n = 12
    problem, truth = make_problem(model, n, seed=3)
    spec = SPECS[model]
    P = spec.n_params
    start = initialize(spec, problem.pos_a, problem.quat_a, problem.pos_b, problem.quat_b)
    sol = solve_tls(problem, solve_ols(problem, start).params)
    assert sol.status > 0
    x_pos, x_quat = reconstruct_inputs(problem, sol.input_residuals, SIGMA_A)

    def fun(j, h):
        params, xp, xq = sol.params, x_pos.copy(), x_quat.copy()
        if j < P:
            d = np.zeros(P)
            d[j] = h
            params = params.stepped(d)
        else:
            i, c = divmod(j - P, 6)
            if c < 3:
                xp[i, c] += h
            else:
                v = np.zeros(3)
                v[c - 3] = h
                xq[i] = quat.multiply(quat.exp(v), xq[i])
        return dense_tls_residual(problem, params, xp, xq, SIGMA_A, SIGMA_B, model)

    r = fun(0, 0.0)
    # the reconstructed inputs reproduce the solver's residuals and chi-square
    np.testing.assert_allclose(r[:n * spec.n_res], sol.residuals.ravel(), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(r @ r, sol.chi2, rtol=1e-9)
    J = dense_jacobian(fun, P, n)
    H = J.T @ J
    cov_dense = np.linalg.inv(H)[:P, :P]
    # (1e-3: the covariance is that of the almost undamped last linearisation)
    assert_same_covariance(sol.cov, cov_dense, tol=1e-3)
    # Not the inverse of the φ block alone (that would ignore the input uncertainty).
    assert not np.allclose(np.linalg.inv(H[:P, :P]), cov_dense, rtol=1e-2)
    # Stationary: the dense Gauss-Newton step from the solution is far below one σ.
    step = np.linalg.solve(H, -J.T @ r)
    assert np.all(np.abs(step[:P]) < 1e-3 * np.sqrt(np.diag(cov_dense)))
    # dof bookkeeping: the 6N input residuals and the 6N input parameters cancel
    assert sol.n_rows == n * spec.n_res
    assert len(r) - J.shape[1] == sol.n_rows - P


@pytest.mark.parametrize('model', MODELS)
def test_ols_covariance_and_chi2_against_independent_residuals(model):
    n = 40
    problem, _ = make_problem(model, n, seed=4)
    spec = SPECS[model]
    P = spec.n_params
    start = initialize(spec, problem.pos_a, problem.quat_a, problem.pos_b, problem.quat_b)
    sol = solve_ols(problem, start)
    assert sol.status > 0 and sol.input_residuals is None

    def res(params):
        e = output_error(params, problem.pos_a, problem.quat_a, problem.pos_b, problem.quat_b)
        return independent_whitened_output(model, SIGMA_B, e).ravel()

    r = res(sol.params)
    np.testing.assert_allclose(sol.residuals.ravel(), r, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sol.chi2, r @ r, rtol=1e-12)
    h = 1e-7
    J = np.stack([(res(sol.params.stepped(h * e)) - res(sol.params.stepped(-h * e))) / (2 * h)
                  for e in np.eye(P)], axis=1)
    cov = np.linalg.inv(J.T @ J)
    assert_same_covariance(sol.cov, cov)
    # Stationary: the gradient is far below the parameter noise.
    step = -cov @ (J.T @ r)
    assert np.all(np.abs(step) < 1e-3 * np.sqrt(np.diag(cov)))
    assert sol.n_rows == n * spec.n_res


def _from_perturbed_start(model, solver):
    """Solve from a start 10 cm / 20° off (not the closed form), with 1e-7 noise."""
    problem, truth = make_problem(model, 60, seed=6, sigma_a=(1e-7, 1e-7),
                                  sigma_b=(1e-7, 1e-7))
    spec = SPECS[model]
    rng = np.random.default_rng(8)
    q0 = quat.multiply(quat.exp(0.35 * rng.normal(size=3) / np.sqrt(3)), truth.q0)
    q1 = quat.multiply(quat.exp(0.35 * rng.normal(size=3) / np.sqrt(3)), truth.q1)
    start = Parameters.from_transforms(spec, truth.p0 + 0.1 * rng.normal(size=3) / np.sqrt(3),
                                       q0, truth.markers + 0.05, q1)
    return solver(problem, start), truth


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('solver', [solve_ols, solve_tls])
def test_solvers_reach_the_truth_from_a_perturbed_start(model, solver):
    sol, truth = _from_perturbed_start(model, solver)
    # noise of 1e-7 m and rad: the estimate is within a few 1e-7 of the truth
    assert_recovers(sol.params, truth, atol_pos=3e-6, atol_rot=3e-5)
    assert sol.iterations < 100


@pytest.mark.parametrize('model, solver', [(m, f) for m in MODELS for f in (solve_ols, solve_tls)])
def test_solvers_report_convergence_at_the_truth(model, solver):
    sol, _ = _from_perturbed_start(model, solver)
    assert sol.status > 0, sol.message


def test_rotation_noise_enters_the_metric_as_a_quarter():
    """The one statement of Σθ/4 (estimator.problem): the metric is minus half the angle."""
    cov = noise_covariance((2e-3, 3e-2))
    cov[0, 4] = cov[4, 0] = 1e-5  # a position-rotation cross term enters as -1/2
    metric = metric_covariance(cov)
    np.testing.assert_array_equal(metric[3:6, 3:6], cov[3:6, 3:6] / 4.0)
    np.testing.assert_array_equal(metric[0:3, 0:3], cov[0:3, 0:3])
    assert metric[0, 4] == -0.5 * cov[0, 4]
    # and the whitening is its inverse Cholesky factor
    L = whitening(cov, None, 'a')
    np.testing.assert_allclose(L.T @ L, np.linalg.inv(metric), rtol=1e-10)
    # a small rotation δθ of the measurement moves the metric by -δθ/2 (Ikits eq. 14)
    q = quat.exp(np.array([0.3, -0.2, 0.1]))
    d = np.array([1e-6, -2e-6, 3e-6])
    e, _ = quat.rotation_error(q, quat.multiply(quat.exp(d), q))
    np.testing.assert_allclose(e, -d / 2.0, atol=1e-15)


def test_every_status_has_one_message_and_the_public_table_agrees():
    for status in STATUS:
        text = lm.status_message(status, 7, 5e-3)
        assert text and '{' not in text
    assert set(lm.MESSAGES) == set(STATUS)
    assert '7 iterations' in lm.status_message(1, 7, 5e-3)
    assert '0.005 standard deviations' in lm.status_message(1, 7, 5e-3)


def test_unit_quaternions_fast_path_matches_the_full_check():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= 1.0 + 1e-4 * rng.normal(size=(50, 1))  # within UNIT_NORM_TOLERANCE
    np.testing.assert_allclose(quat.unit_quaternions(q, 'q'), quat.validate_quaternions(q, 'q'),
                               rtol=0, atol=1e-15)
    assert (quat.unit_quaternions(q, 'q')[:, 0] >= 0).all()
    bad = q.copy()
    bad[4] = 0.0
    with pytest.raises(InputError, match='device A orientation'):
        quat.unit_quaternions(bad, 'device A orientation')


def test_lm_from_an_undamped_start_raises_the_damping_after_a_rejected_step():
    # a start at λ = 0 (a seed's undamped sums) whose step is rejected must damp it, not retry
    # the same step forever (a fuzzed recording hung coreg calibrate so): r(x) = x² - 0.5 from
    # x = 0.8 with a normal matrix of a twentieth of JᵀJ, so that the undamped step overshoots
    from coreg_ros.core.estimator.lm import levenberg_marquardt, Linearization
    calls = []

    def cost(x):
        return float((x[0] ** 2 - 0.5) ** 2)

    def linearize(x, lam):
        calls.append(lam)
        assert len(calls) < 10_000, 'the damping never rose'
        j = np.array([[2.0 * x[0]]])
        info = 0.05 * (j.T @ j) * (1.0 + lam)

        def propose(delta, lam_next):
            trial = x + delta
            return trial, cost(trial), linearize(trial, lam_next)

        return Linearization(info, -j.T @ np.array([x[0] ** 2 - 0.5]), cost(x), propose)

    x, status, iterations, _, _ = levenberg_marquardt(np.array([0.8]), linearize, 20, 1e-9,
                                                      1e-15, damping=0.0)
    assert max(calls) > 0.0  # damped after the first rejection
    assert cost(x) < cost(np.array([0.8]))  # and went downhill
