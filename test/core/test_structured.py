"""
The structured normal equations (core/estimator/normal_equations.py) against the generic path.

The generic path forms every pair's Jacobian blocks and eliminates 6×6 input blocks; the
structured one works in channels, eliminates the input position in closed form and keeps a
3×3 block per pair. Both must give the same linear systems, damped and undamped, for either
whitening branch (isotropic closed forms and general matrices), in every chart, and the same
solutions. A problem with ``a_scale`` set to ones is the same problem, solved generically.
"""

import contextlib
import dataclasses

from coreg_ros.core import estimator as est
from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.initialize import initialize
from coreg_ros.core.estimator import lm, ols, pair_algebra, tls, whitening
from coreg_ros.core.estimator import normal_equations as structured
from coreg_ros.core.estimator.normal_equations_tls import TlsFactors
from coreg_ros.core.models import SPECS
from coreg_ros.core.so3 import skew
from coreg_ros.sim import simulate_pairs, Truth
import numpy as np
import pytest

N = 400
ISOTROPIC = (np.diag([1e-6] * 3 + [4e-5] * 3), np.diag([4e-6] * 3 + [3e-4] * 3))
ANISOTROPIC = (np.diag([1e-6, 4e-6, 9e-6, 1e-5, 4e-5, 2e-5]),
               np.diag([4e-6, 1e-6, 2e-6, 1e-4, 3e-4, 2e-4]))


def _problem(model, noise, seed, truth=None):
    rng = np.random.default_rng(seed)
    noisy, _, truth = simulate_pairs(rng, N, model, sigma_a=(1e-3, 6e-3), sigma_b=(2e-3, 1.5e-2),
                                     truth=truth)
    spec = SPECS[model]
    cov_a, cov_b = noise
    cov_a = cov_a.copy()
    # a full (non-diagonal) rotation block exercises the general whitening branch
    if noise is ANISOTROPIC:
        cov_a[3:6, 3:6] += 0.5e-5 * (np.ones((3, 3)) - np.eye(3))
    return est.Problem(spec, noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b,
                       whitening(cov_b, spec, 'b'), whitening(cov_a, None, 'a')), rng


@contextlib.contextmanager
def generic(monkeypatch):
    """Within the block, every problem takes the generic path."""
    with monkeypatch.context() as m:
        m.setattr(structured, 'applies', lambda problem, inputs=True: False)
        yield


def _weighted(problem, seed=0):
    """Return the problem with per-pair weights on A's noise as pairing makes them (0.5 to 1)."""
    alpha = np.random.default_rng(seed).uniform(0.0, 1.0, problem.n)
    return dataclasses.replace(problem, a_scale=alpha ** 2 + (1.0 - alpha) ** 2)


def _perturbed_state(problem, rng):
    spec = problem.spec
    start = initialize(spec, problem.pos_a, problem.quat_a, problem.pos_b, problem.quat_b)
    params = start.stepped(rng.normal(0.0, 2e-3, spec.n_params)).recharted()
    x = est.InputState(problem.pos_a + rng.normal(0.0, 1e-3, (problem.n, 3)),
                       quat.multiply(quat.exp(rng.normal(0.0, 5e-3, (problem.n, 3))),
                                     problem.quat_a))
    return params, x


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


CASES = [(m, w) for m in ('full_pose', 'position_only') for w in ('isotropic', 'anisotropic')]


@pytest.mark.parametrize('model, kind', CASES)
def test_ols_normal_equations_match_the_generic_path(model, kind, monkeypatch):
    problem, rng = _problem(model, ISOTROPIC if kind == 'isotropic' else ANISOTROPIC, 1)
    params, _ = _perturbed_state(problem, rng)
    assert structured.applies(problem, inputs=False)
    r1, r2 = np.empty((N, problem.spec.n_res)), np.empty((N, problem.spec.n_res))
    H1, g1, c1 = ols._ols_normal(problem, params, r1)
    with generic(monkeypatch):
        H2, g2, c2 = ols._ols_normal(problem, params, r2)
    assert _rel(H1, H2) < 1e-12
    assert _rel(g1, g2) < 1e-10
    assert c1 == pytest.approx(c2, rel=1e-12)
    assert np.abs(r1 - r2).max() < 1e-10


WEIGHTED = [(m, w, a) for m, w in CASES for a in (False, True) if not (a and w == 'anisotropic')]


@pytest.mark.parametrize('model, kind, weighted', WEIGHTED)
@pytest.mark.parametrize('lam', [0.0, 1e-3, 0.5])
def test_tls_schur_complement_matches_the_generic_path(model, kind, weighted, lam, monkeypatch):
    problem, rng = _problem(model, ISOTROPIC if kind == 'isotropic' else ANISOTROPIC, 2)
    if weighted:
        problem = _weighted(problem)
    params, x = _perturbed_state(problem, rng)
    assert structured.applies(problem)
    S1, b1, c1, (ry1, rx1), f1, _ = est.tls_linearization(problem, params, x, lam)
    with generic(monkeypatch):
        S2, b2, c2, (ry2, rx2), f2, _ = est.tls_linearization(problem, params, x, lam)
    assert isinstance(f1, TlsFactors) and not isinstance(f2, TlsFactors)
    assert _rel(S1, S2) < 1e-11
    assert _rel(b1, b2) < 1e-10
    assert c1 == pytest.approx(c2, rel=1e-12)
    assert np.abs(ry1 - ry2).max() < 1e-10 and np.abs(rx1 - rx2).max() < 1e-10
    # the input corrections of one step agree to the float32 storage of the factors
    delta = np.linalg.solve(S1, b1)
    dx1 = est.back_substitute(problem.n, f1, delta)
    dx2 = est.back_substitute(problem.n, f2, delta)
    assert dx1.shape == (6, N)
    assert _rel(dx1, dx2) < 1e-5
    # the corrections of some pairs only (a refit's): those of all, taken, to the bit
    kept = np.flatnonzero(rng.random(N) < 0.8)
    for factors, dx in ((f1, dx1), (f2, dx2)):
        assert np.array_equal(est.back_substitute(problem.n, factors, delta, kept),
                              np.take(dx, kept, axis=1))
    # the residuals made at the solution alone (a light pass) are the linearisation's
    for path, (ry, rx) in (('structured', (ry1, rx1)), ('generic', (ry2, rx2))):
        with generic(monkeypatch) if path == 'generic' else contextlib.nullcontext():
            got_y, got_x = est.tls_residuals(problem, params, x)
        assert np.array_equal(got_y, ry) and np.array_equal(got_x, rx), path


def test_a_lazily_taken_state_steps_as_the_taken_copy():
    rng = np.random.default_rng(8)
    n = 3 * 8192 + 17  # several chunks of the step
    x = est.InputState(rng.normal(size=(n, 3)),
                       quat.exp(rng.normal(size=(n, 3))))
    idx = np.flatnonzero(rng.random(n) < 0.9)
    dx = rng.normal(0.0, 1e-3, (6, idx.size))
    copied, lazy = x.take(idx), x.take(idx, lazy=True)
    assert lazy.n == copied.n == idx.size
    stepped = lazy.stepped(dx)  # gathered a chunk at a time, not kept
    assert np.array_equal(stepped.pos_t, copied.stepped(dx).pos_t)
    assert np.array_equal(stepped.quat_t, copied.stepped(dx).quat_t)
    # read, it is gathered once: the same arrays as the copy
    assert np.array_equal(lazy.quat_t, copied.quat_t) and np.array_equal(lazy.pos, copied.pos)


def _half_turn(axis):
    axis = np.asarray(axis, dtype=float)
    return np.concatenate([[0.0], axis / np.linalg.norm(axis)])


@pytest.mark.parametrize('q0, q1', [
    (_half_turn([1, 0, 0]), _half_turn([0, 1, 1])),
    ([1.0, 0.0, 0.0, 0.0], quat.exp(np.array([0.0, 0.0, np.pi - 1e-3]))),
    (quat.exp(np.array([0.3, -2.0, 1.0])), quat.exp(np.array([-1.0, 0.5, 2.5]))),
])
def test_tls_matches_in_every_chart(q0, q1, monkeypatch):
    truth = Truth(p0=[0.4, -0.6, 0.3], q0=q0, p1=[0.05, -0.08, 0.12], q1=q1,
                  markers=np.array([[0.05, -0.08, 0.12]]), model='full_pose')
    problem, rng = _problem('full_pose', ISOTROPIC, 3, truth=truth)
    params, x = _perturbed_state(problem, rng)
    S1, b1, *_ = est.tls_linearization(problem, params, x, 1e-2)
    with generic(monkeypatch):
        S2, b2, *_ = est.tls_linearization(problem, params, x, 1e-2)
    assert _rel(S1, S2) < 1e-11
    assert _rel(b1, b2) < 1e-10


@pytest.mark.parametrize('model', ['full_pose', 'position_only'])
def test_solutions_match_the_generic_path(model, monkeypatch):
    problem, _ = _problem(model, ISOTROPIC, 4)
    problem = _weighted(problem, 4)
    start = initialize(problem.spec, problem.pos_a, problem.quat_a, problem.pos_b,
                       problem.quat_b)
    for solve in (est.solve_ols, est.solve_tls):
        fast = solve(problem, start)
        with generic(monkeypatch):
            slow = solve(problem, start)
        assert fast.status > 0 and slow.status > 0
        sigma = np.sqrt(np.diag(slow.cov))
        # both stop within 1e-5 σ of the optimum
        assert np.all(np.abs(fast.params.phi - slow.params.phi) <= 3e-5 * sigma)
        assert fast.chi2 == pytest.approx(slow.chi2, rel=1e-9)
        assert _rel(fast.cov, slow.cov) < 1e-4


def test_applies_only_where_the_structure_holds():
    problem, _ = _problem('full_pose', ISOTROPIC, 5)
    assert structured.applies(problem)
    Lb = problem.whiten_b.copy()
    Lb[4, 1] = 0.3 * Lb[4, 4]  # position-rotation correlation in B's noise
    assert not structured.applies(dataclasses.replace(problem, whiten_b=Lb))
    La = problem.whiten_a.copy()
    La[0, 5] = 0.1 * La[0, 0]
    assert not structured.applies(dataclasses.replace(problem, whiten_a=La))
    three, _ = _problem('three_marker', ISOTROPIC, 5)
    assert not structured.applies(three)
    # per-pair input weights: TLS needs isotropic position noise, OLS does not use them
    assert structured.applies(_weighted(problem))
    aniso, _ = _problem('full_pose', ANISOTROPIC, 5)
    assert not structured.applies(_weighted(aniso))
    assert structured.applies(_weighted(aniso), inputs=False)


def test_rotated_input_step():
    rng = np.random.default_rng(6)
    q = quat.exp(rng.normal(size=(50, 3)))
    d = np.concatenate([rng.normal(0.0, 1e-8, (10, 3)), rng.normal(0.0, 1.0, (40, 3))])
    want = quat.multiply(quat.exp(d), q)
    got = pair_algebra.rotated(np.ascontiguousarray(q.T), np.ascontiguousarray(d.T)).T
    assert np.abs(got - want).max() < 1e-14
    assert np.abs(np.linalg.norm(got, axis=1) - 1.0).max() < 1e-15


def test_input_state_views_and_step():
    rng = np.random.default_rng(7)
    pos, q = rng.normal(size=(20, 3)), quat.exp(rng.normal(size=(20, 3)))
    x = est.InputState(pos, q)
    assert np.array_equal(x.pos, pos) and np.array_equal(x.quat, q)
    dx = rng.normal(0.0, 0.1, (6, 20))
    y = x.stepped(dx)
    assert np.allclose(y.pos, pos + dx[0:3].T, atol=1e-15)
    assert np.allclose(y.quat, quat.multiply(quat.exp(dx[3:6].T), q), atol=1e-14)
    assert np.array_equal(x.pos, pos)  # stepping returns a new state


# ---------------------------------------------------------------------------------------------
# The LM driver (shared by both paths), on a one-parameter problem with injected faults
# ---------------------------------------------------------------------------------------------

class _Curve:
    """r(θ) = (exp(θ) - 2, θ - 0.5): a small nonlinear least-squares problem for the driver."""

    def __init__(self, faults=()):
        self.faults = list(faults)  # trial costs to report instead of the true ones, in order
        self.passes = 0

    @staticmethod
    def cost(theta):
        return float((np.exp(theta) - 2.0) ** 2 + (theta - 0.5) ** 2)

    def linearize(self, theta, lam):
        self.passes += 1
        r = np.array([np.exp(theta) - 2.0, theta - 0.5])
        J = np.array([[np.exp(theta)], [1.0]])
        H = J.T @ J

        def propose(delta, lam_next):
            trial = theta + float(delta[0])
            lin = self.linearize(trial, lam_next)
            cost = self.faults.pop(0) if self.faults else lin.cost
            return trial, cost, lin

        lin = lm.Linearization(H + lam * np.diag(np.diag(H)), -(J.T @ r), self.cost(theta),
                               propose)
        lin.made_at = (theta, lam)
        return lin


def _optimum():
    from scipy.optimize import minimize_scalar
    return minimize_scalar(_Curve.cost, bounds=(-2, 2), method='bounded',
                           options={'xatol': 1e-12}).x


def test_driver_converges_and_returns_the_linearisation_at_the_solution():
    curve = _Curve()
    theta, status, it, last, lam = lm.levenberg_marquardt(3.0, curve.linearize, 100, 1e-5,
                                                          1e-12)
    assert status > 0
    assert theta == pytest.approx(_optimum(), abs=1e-6)
    assert last.made_at == (theta, lam)
    assert curve.passes == it + 1 - (status == 1)  # one pass per step, plus the start


@pytest.mark.parametrize('fault', [np.inf, np.nan, 1e300])
def test_driver_rejects_bad_trials_and_raises_the_damping(fault):
    curve = _Curve(faults=[fault, fault])
    theta, status, _, last, lam = lm.levenberg_marquardt(3.0, curve.linearize, 100, 1e-5,
                                                         1e-12)
    assert status > 0
    assert theta == pytest.approx(_optimum(), abs=1e-6)
    assert last.made_at == (theta, lam)


def test_driver_gives_up_with_the_damping_of_its_last_linearisation():
    curve = _Curve(faults=[1e300] * 100)
    theta, status, _, last, lam = lm.levenberg_marquardt(3.0, curve.linearize, 100, 1e-5,
                                                         1e-12)
    assert status == -1 and theta == 3.0
    assert last.made_at == (3.0, lam)


# ---------------------------------------------------------------------------------------------
# Posterior information and input validation
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('model', ['full_pose', 'position_only'])
def test_posterior_is_undamped_when_a_is_far_noisier_than_b(model, monkeypatch):
    # With σ_A ≫ σ_B the Schur complement S is far smaller than V = Σ BᵀB, so even a tiny λ·V
    # is a large share of S: the solver must then re-linearise without damping.
    rng = np.random.default_rng(8)
    noisy, _, _ = simulate_pairs(rng, N, model, sigma_a=(2e-2, 5e-2), sigma_b=(2e-5, 5e-5))
    spec = SPECS[model]
    cov_a = np.diag([4e-4] * 3 + [2.5e-3] * 3)
    cov_b = np.diag([4e-10] * 3 + [2.5e-9] * 3)
    problem = est.Problem(spec, noisy.pos_a, noisy.quat_a, noisy.pos_b, noisy.quat_b,
                          whitening(cov_b, spec, 'b'), whitening(cov_a, None, 'a'))
    start = est.solve_ols(problem, initialize(spec, problem.pos_a, problem.quat_a,
                                              problem.pos_b, problem.quat_b)).params
    sol = est.solve_tls(problem, start)
    monkeypatch.setattr(tls, 'DAMPING_SHARE', -1.0)  # always re-linearise at λ = 0
    exact = est.solve_tls(problem, start)
    assert sol.status > 0
    assert _rel(sol.cov, exact.cov) < 1e-5


def test_infinite_input_weights_are_refused():
    from coreg_ros.core.calibration.calibrate import calibrate
    from coreg_ros.core.errors import InputError
    from coreg_ros.core.settings import Settings
    noisy, _, _ = simulate_pairs(np.random.default_rng(9), 200, 'full_pose')
    scale = np.ones(200)
    scale[17] = np.inf
    with pytest.raises(InputError, match='finite'):
        calibrate(dataclasses.replace(noisy, a_var_scale=scale), Settings(method='tls'))


def test_pair_last_rotation_algebra_is_the_one_of_so3_and_quaternion():
    """normal_equations uses so3.skew and quaternion.to_matrix in their pair-last layout."""
    rng = np.random.default_rng(4)
    v = rng.normal(size=(7, 3))
    q = rng.normal(size=(7, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_array_equal(skew(v.T, pair_last=True), skew(v).transpose(1, 2, 0))
    np.testing.assert_array_equal(quat.to_matrix(q.T, pair_last=True),
                                  quat.to_matrix(q).transpose(1, 2, 0))
    np.testing.assert_allclose(skew(v[0]) @ v[1], np.cross(v[0], v[1]), rtol=0, atol=1e-15)
