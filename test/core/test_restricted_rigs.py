"""
Rigs that cannot move in every direction (issue 22): Monte Carlo per rig, both methods.

A SCARA arm (yaw about A's base z, translation in x, y, z), a mobile robot on a floor (yaw, x,
y), a Cartesian gantry (translation only) and a turntable (the tool turns about a vertical axis
through a fixed point). Per rig and method, ``TRIALS`` calibrations of one truth and motion
with the noise redrawn (fixed seeds):

- with a partial prior on T1's position (drawn about the truth with the prior's own σ): nothing
  is held, and the mean NEES of (T0, T1) lies in its 99 % band;
- without a prior: success, the held directions within 1° of the analytic null space (the
  tangent of the exact family of calibrations that give the same measurements), and the mean
  NEES of the observable part in its band: the error left after the truth is moved along that
  family to the estimate's gauge (the family parameters minimise the NEES under the fit's
  gauge-fixed covariance, which removes k degrees of freedom: χ²(12 - k)).

Every model: the full pose (the (T0, T1) layout), position only (T0 and p1) and three markers
(T0 and the three marker positions; the NEES on T0 and the first marker, the layout of the
published covariance).

OLS is run with device A noise-free (where OLS is the maximum-likelihood estimator, as in
bench/montecarlo.py); TLS with A's noise. The turntable's rotation family is curved (a circle of
the lever's radius, 0.2-0.4 m): its prior is 0.5 mm (the posterior along the circle is Gaussian
to well below the data's σ only while σ_prior ≪ √(2 σ_data r); 2 mm already gives NEES ~16).
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.verdict import prior_check
from coreg_ros.core.estimator.posterior import joint_pose_covariance
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import UncertainPose
from coreg_ros.core.uncertainty import pose_error
from coreg_ros.sim import make_motion, random_truth, simulate_pairs
import numpy as np
import pytest
from scipy import optimize, stats

RIGS = ('scara', 'planar', 'gantry', 'turntable')
MODELS = ('full_pose', 'position_only', 'three_marker')
#: Trials per rig, model, method and case (the issue asks for at least 200).
TRIALS = 200
#: Pairs per calibration.
PAIRS = 200
SIGMA_B = (2e-4, 1e-3)
SIGMA_A = {'ols': (1e-9, 1e-9), 'tls': (5e-5, 2e-4)}
#: σ of the partial prior on T1's position (m) per rig (module docstring).
PRIOR_SIGMA = {'scara': 5e-3, 'planar': 5e-3, 'gantry': 5e-3, 'turntable': 5e-4}
Z = np.array([0.0, 0.0, 1.0])


def _rot(axis, angle):
    return quat.to_matrix(quat.exp(np.asarray(axis) * angle))


def family(rig: str, motion, truth):
    """
    Return the exact family of calibrations that measure like ``truth`` on ``rig``.

    Returns ``move(theta) -> (p0, q0, markers (k, 3), q1)`` and the number of parameters k.
    """
    R0, Rm = quat.to_matrix(truth.q0), quat.to_matrix(motion.q_mean)
    p0, m1, q0, q1 = truth.p0, truth.markers, truth.q0, truth.q1
    u = Rm.T @ Z  # the tool axis the yaw turns about (the base's z, in the tool frame)
    if rig == 'gantry':  # T1's position against T0's translation, any vector
        return (lambda th: (p0 - R0 @ Rm @ th, q0, m1 + th, q1)), 3
    if rig in ('scara', 'planar'):  # T1's offset along the axis against T0's along R0 z
        return (lambda th: (p0 - th[0] * (R0 @ Z), q0, m1 + th[0] * u, q1)), 1
    pivot, v = motion.pivot, motion.centre - motion.pivot

    def move(th):  # the axis shift, then the turn of everything about the axis by th[1]
        Rz = _rot(Z, th[1])
        a0, a1 = p0 - th[0] * (R0 @ Z), m1 + th[0] * u
        R0n = R0 @ Rz
        p0n = a0 - R0 @ (Rz @ pivot - pivot)
        m1n = (Rz.T @ (v[:, None] + Rm @ a1.T) - v[:, None]).T @ Rm
        q0n = quat.from_matrix(R0n)
        q1n = quat.from_matrix(Rm.T @ Rz.T @ Rm @ quat.to_matrix(q1))
        return p0n, q0n, m1n, q1n

    return move, 2


def errors(model, p0, q0, markers, q1, result) -> np.ndarray:
    """Errors of the published layout's known components: the given poses minus the estimate."""
    e0 = pose_error(p0, q0, result.base_to_base.position, result.base_to_base.quat_wxyz)
    e1 = pose_error(markers[0], q1, result.tool_to_marker.position,
                    result.tool_to_marker.quat_wxyz)
    return np.concatenate([e0, e1])[KNOWN[model]]


#: The components of the published layout each model estimates.
KNOWN = {'full_pose': slice(0, 12), 'position_only': slice(0, 9), 'three_marker': slice(0, 9)}


def gauged_nees(model, move, k, result) -> tuple:
    """
    NEES of the error left after moving the truth along its family (module docstring).

    Returns the NEES and the family parameters that move the truth to the estimate's gauge.
    """
    params = Parameters(SPECS[model], result.params, list(result.charts))
    known = KNOWN[model]
    cov = joint_pose_covariance(params, result.param_cov)[known, known]  # gauge-fixed
    L = np.linalg.cholesky(np.linalg.inv(cov)).T

    def plain(th):
        return errors(model, *move(th), result)

    def whitened(th):
        return L @ plain(th)

    # the nearest member first (the whitened cost is stiff along the held directions, whose
    # gauge is tight): the turn about the axis is periodic, so from the turn about base A's z
    # that takes the truth's T0 nearest the estimate's (move turns R0 into R0 Rz(θ))
    start = np.zeros(k)
    if k == 2:
        rel = quat.to_matrix(move(start)[1]).T @ quat.to_matrix(result.base_to_base.quat_wxyz)
        start[1] = np.arctan2(rel[1, 0] - rel[0, 1], rel[0, 0] + rel[1, 1])
    start = optimize.least_squares(plain, start, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    fit = optimize.least_squares(whitened, start, x_scale=np.full(k, 1e-2), xtol=1e-14,
                                 ftol=1e-14, gtol=1e-14)
    return float(2.0 * fit.cost), fit.x


def tangent_layout(model, a, b) -> np.ndarray:
    """Return the difference of two calibrations: T0, every marker, T1's rotation (full pose)."""
    out = [pose_error(a[0], a[1], b[0], b[1]), (a[2] - b[2]).ravel()]
    if model == 'full_pose':
        out.append(pose_error(a[2][0], a[3], b[2][0], b[3])[3:6])
    return np.concatenate(out)


def held_layout(model, u) -> np.ndarray:
    """Return a held direction in ``tangent_layout``'s layout."""
    if model == 'three_marker':
        return np.concatenate([u.direction[0:6], u.markers])
    return u.direction[0:12] if model == 'full_pose' else u.direction[0:9]


def null_space(model, move, k, at) -> np.ndarray:
    """
    Return the family's tangent at ``move(at)`` in ``tangent_layout``, orthonormal (n, k).

    Where the family turns (a turntable), its tangent depends on the point of it: the held
    directions are compared with the tangent at the truth moved to the estimate's gauge.
    """
    cols = []
    for i in range(k):
        h = np.zeros(k)
        h[i] = 1e-6
        cols.append(tangent_layout(model, move(at + h), move(at - h)) / 2e-6)
    return np.linalg.qr(np.array(cols).T)[0]


def band(dim: int, n: int) -> tuple:
    """99 % band of the mean of n χ²(dim) draws."""
    half = stats.norm.ppf(0.995) * np.sqrt(2.0 * dim / n)
    return dim - half, dim + half


def _rig(rig, model):
    motion = make_motion(np.random.default_rng(10), rig)
    truth = random_truth(np.random.default_rng(11), model)
    return motion, truth


def _dim(model) -> int:
    return KNOWN[model].stop - KNOWN[model].start


@pytest.mark.slow
@pytest.mark.parametrize('method', ['ols', 'tls'])
@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('rig', RIGS)
def test_without_a_prior_the_null_space_is_held_and_the_rest_is_consistent(rig, model, method):
    motion, truth = _rig(rig, model)
    move, k = family(rig, motion, truth)
    # the family is exact: the measurements do not change along it
    from coreg_ros.core.models import predict
    pos, q = motion.pose(np.linspace(0.0, 60.0, 50))
    spec = SPECS[model]
    ref = predict(Parameters.from_transforms(spec, truth.p0, truth.q0, truth.markers,
                                             truth.q1), pos, q)
    moved = move(np.full(k, 0.05))
    got = predict(Parameters.from_transforms(spec, *moved), pos, q)
    assert np.abs(got[0] - ref[0]).max() < 1e-12
    if spec.has_q1:
        assert quat.angle_between(got[1], ref[1]).max() < 1e-12
    rng = np.random.default_rng(12)
    sa = SIGMA_A[method]
    settings = Settings(model=model, method=method, sigma_a=sa, sigma_b=SIGMA_B, robust=False)
    nees, worst_angle = [], 0.0
    for _ in range(TRIALS):
        noisy, _, _ = simulate_pairs(rng, PAIRS, model, sigma_a=sa, sigma_b=SIGMA_B,
                                     truth=truth, motion=motion)
        result = calibrate(noisy, settings)
        assert result.success and len(result.held) == k
        value, at = gauged_nees(model, move, k, result)
        nees.append(value)
        held = np.linalg.qr(np.array([held_layout(model, u) for u in result.held]).T)[0]
        cosines = np.linalg.svd(held.T @ null_space(model, move, k, at), compute_uv=False)
        worst_angle = max(worst_angle, np.degrees(np.arccos(min(1.0, cosines.min()))))
    assert worst_angle < 1.0
    lo, hi = band(_dim(model) - k, TRIALS)
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


@pytest.mark.slow
@pytest.mark.parametrize('method', ['ols', 'tls'])
@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('rig', RIGS)
def test_a_partial_prior_determines_the_held_directions_consistently(rig, model, method):
    motion, truth = _rig(rig, model)
    rng = np.random.default_rng(13)
    sa, sp = SIGMA_A[method], PRIOR_SIGMA[rig]
    settings = Settings(model=model, method=method, sigma_a=sa, sigma_b=SIGMA_B, robust=False)
    cov = np.diag([sp ** 2] * 3 + [np.inf] * 3)
    nees = []
    for _ in range(TRIALS):
        noisy, _, _ = simulate_pairs(rng, PAIRS, model, sigma_a=sa, sigma_b=SIGMA_B,
                                     truth=truth, motion=motion)
        drawn = truth.markers[0] + rng.normal(scale=sp, size=3)  # the prior's own error
        prior = Prior(tool_to_marker=UncertainPose(drawn, truth.q1, cov))
        result = calibrate(noisy, settings, prior)
        assert result.success and not result.held
        assert result.unobservable and all(u.by == 'prior' for u in result.unobservable)
        known = KNOWN[model]
        e = errors(model, truth.p0, truth.q0, truth.markers, truth.q1, result)
        nees.append(float(e @ np.linalg.solve(result.cov_joint[known, known], e)))
    lo, hi = band(_dim(model), TRIALS)
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


# ----------------------------------------------------------------------------- gravity


def _gravity_rig(tilt_rad: float = 0.0):
    """Return a mobile robot (planar motion) whose bases share z up, but ``tilt_rad`` about x."""
    from dataclasses import replace
    motion = make_motion(np.random.default_rng(20), 'planar')
    truth = random_truth(np.random.default_rng(21), 'full_pose')
    yaw = quat.exp(Z * 0.7)
    q0 = quat.multiply(quat.exp(np.array([tilt_rad, 0.0, 0.0])), yaw)
    return motion, replace(truth, q0=q0)


def test_the_gravity_term_jacobian_matches_its_differences():
    from coreg_ros.core.estimator.priors import gravity_term
    spec = SPECS['full_pose']
    _, truth = _gravity_rig(0.05)
    params = Parameters.from_transforms(spec, truth.p0, truth.q0, truth.markers, truth.q1)
    term = gravity_term(spec, 0.01)
    r, J = term(params)
    assert r.shape == (2,) and J.shape == (2, spec.n_params)
    num = np.zeros_like(J)
    for j in range(spec.n_params):
        h = np.zeros(spec.n_params)
        h[j] = 1e-7
        num[:, j] = (term(params.stepped(h))[0] - term(params.stepped(-h))[0]) / 2e-7
    assert np.allclose(J, num, atol=1e-5 * np.abs(J).max())


@pytest.mark.slow
@pytest.mark.parametrize('method', ['ols', 'tls'])
def test_gravity_aligned_with_a_height_prior_determines_everything_consistently(method):
    """The gravity preset and T1's height: a mobile robot's yaw-only alignment, NEES in band."""
    motion, truth = _gravity_rig()
    rng = np.random.default_rng(22)
    sa, sg, sz = SIGMA_A[method], 0.01, 5e-3
    settings = Settings(method=method, sigma_a=sa, sigma_b=SIGMA_B, robust=False)
    cov = np.diag([np.inf, np.inf, sz ** 2] + [np.inf] * 3)
    nees = []
    for _ in range(TRIALS):
        noisy, _, _ = simulate_pairs(rng, PAIRS, 'full_pose', sigma_a=sa, sigma_b=SIGMA_B,
                                     truth=truth, motion=motion)
        drawn = truth.markers[0] + np.array([0.0, 0.0, rng.normal(scale=sz)])
        prior = Prior(tool_to_marker=UncertainPose(drawn, truth.q1, cov), gravity_sigma=sg)
        result = calibrate(noisy, settings, prior)
        assert result.success and not result.held
        assert prior_check(result, prior)['consistent']
        e = errors('full_pose', truth.p0, truth.q0, truth.markers, truth.q1, result)
        nees.append(float(e @ np.linalg.solve(result.cov_joint, e)))
    lo, hi = band(12, TRIALS)
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


def test_a_tilted_base_contradicts_the_gravity_preset():
    """Bases 3° apart in tilt: the prior check (the verdict's) flags the gravity preset."""
    motion, truth = _gravity_rig(np.radians(3.0))
    noisy, _, _ = simulate_pairs(np.random.default_rng(23), 2000, 'full_pose',
                                 sigma_a=SIGMA_A['tls'], sigma_b=SIGMA_B, truth=truth,
                                 motion=motion)
    settings = Settings(sigma_a=SIGMA_A['tls'], sigma_b=SIGMA_B)
    tight, loose = Prior(gravity_sigma=0.01), Prior(gravity_sigma=0.1)  # 0.6°, 6°
    check = prior_check(calibrate(noisy, settings, tight), tight)
    assert check['dof'] == 2 and not check['consistent']
    assert prior_check(calibrate(noisy, settings, loose), loose)['consistent']
