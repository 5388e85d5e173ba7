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

OLS is run with device A noise-free (where OLS is the maximum-likelihood estimator, as in
bench/montecarlo.py); TLS with A's noise. The turntable's rotation family is curved (a circle of
the lever's radius, 0.2-0.4 m): its prior is 0.5 mm (the posterior along the circle is Gaussian
to well below the data's σ only while σ_prior ≪ √(2 σ_data r); 2 mm already gives NEES ~16).
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
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
#: Trials per rig, method and case (the issue asks for at least 200).
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

    Returns ``move(theta) -> (p0, q0, p1, q1)`` and the number of parameters k.
    """
    R0, Rm = quat.to_matrix(truth.q0), quat.to_matrix(motion.q_mean)
    p0, p1, q0, q1 = truth.p0, truth.markers[0], truth.q0, truth.q1
    u = Rm.T @ Z  # the tool axis the yaw turns about (the base's z, in the tool frame)
    if rig == 'gantry':  # T1's position against T0's translation, any vector
        return (lambda th: (p0 - R0 @ Rm @ th, q0, p1 + th, q1)), 3
    if rig in ('scara', 'planar'):  # T1's offset along the axis against T0's along R0 z
        return (lambda th: (p0 - th[0] * (R0 @ Z), q0, p1 + th[0] * u, q1)), 1
    pivot, v = motion.pivot, motion.centre - motion.pivot

    def move(th):  # the axis shift, then the turn of everything about the axis by th[1]
        Rz = _rot(Z, th[1])
        a0, a1 = p0 - th[0] * (R0 @ Z), p1 + th[0] * u
        R0n = R0 @ Rz
        p0n = a0 - R0 @ (Rz @ pivot - pivot)
        p1n = Rm.T @ (Rz.T @ (v + Rm @ a1) - v)
        q0n = quat.from_matrix(R0n)
        q1n = quat.from_matrix(Rm.T @ Rz.T @ Rm @ quat.to_matrix(q1))
        return p0n, q0n, p1n, q1n

    return move, 2


def errors12(p0, q0, p1, q1, result) -> np.ndarray:
    """(T0, T1) errors in the ROS layout: the given pose minus the estimate."""
    e0 = pose_error(p0, q0, result.base_to_base.position, result.base_to_base.quat_wxyz)
    e1 = pose_error(p1, q1, result.tool_to_marker.position, result.tool_to_marker.quat_wxyz)
    return np.concatenate([e0, e1])


def gauged_nees(move, k, result) -> tuple:
    """
    NEES of the error left after moving the truth along its family (module docstring).

    Returns the NEES and the family parameters that move the truth to the estimate's gauge.
    """
    params = Parameters(SPECS['full_pose'], result.params, list(result.charts))
    cov = joint_pose_covariance(params, result.param_cov)  # the gauge-fixed covariance
    L = np.linalg.cholesky(np.linalg.inv(cov)).T
    fit = optimize.least_squares(lambda th: L @ errors12(*move(th), result), np.zeros(k),
                                 x_scale=np.full(k, 1e-2), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return float(2.0 * fit.cost), fit.x


def null_space(move, k, at) -> np.ndarray:
    """
    Return the family's tangent at ``move(at)`` in the (T0, T1) layout, orthonormal (12, k).

    Where the family turns (a turntable), its tangent depends on the point of it: the held
    directions are compared with the tangent at the truth moved to the estimate's gauge.
    """
    cols = []
    for i in range(k):
        h = np.zeros(k)
        h[i] = 1e-6
        a, b = move(at + h), move(at - h)
        cols.append(np.concatenate([pose_error(a[0], a[1], b[0], b[1]),
                                    pose_error(a[2], a[3], b[2], b[3])]) / 2e-6)
    return np.linalg.qr(np.array(cols).T)[0]


def band(dim: int, n: int) -> tuple:
    """99 % band of the mean of n χ²(dim) draws."""
    half = stats.norm.ppf(0.995) * np.sqrt(2.0 * dim / n)
    return dim - half, dim + half


def _rig(rig):
    motion = make_motion(np.random.default_rng(10), rig)
    truth = random_truth(np.random.default_rng(11), 'full_pose')
    return motion, truth


@pytest.mark.slow
@pytest.mark.parametrize('method', ['ols', 'tls'])
@pytest.mark.parametrize('rig', RIGS)
def test_without_a_prior_the_null_space_is_held_and_the_rest_is_consistent(rig, method):
    motion, truth = _rig(rig)
    move, k = family(rig, motion, truth)
    # the family is exact: the measurements do not change along it
    from coreg_ros.core.models import predict
    pos, q = motion.pose(np.linspace(0.0, 60.0, 50))
    ref = predict(Parameters.from_transforms(SPECS['full_pose'], truth.p0, truth.q0,
                                             truth.markers, truth.q1), pos, q)
    moved = move(np.full(k, 0.05))
    got = predict(Parameters.from_transforms(SPECS['full_pose'], moved[0], moved[1],
                                             moved[2][None], moved[3]), pos, q)
    assert np.abs(got[0] - ref[0]).max() < 1e-12
    assert quat.angle_between(got[1], ref[1]).max() < 1e-12
    rng = np.random.default_rng(12)
    sa = SIGMA_A[method]
    settings = Settings(method=method, sigma_a=sa, sigma_b=SIGMA_B, robust=False)
    nees, worst_angle = [], 0.0
    for _ in range(TRIALS):
        noisy, _, _ = simulate_pairs(rng, PAIRS, 'full_pose', sigma_a=sa, sigma_b=SIGMA_B,
                                     truth=truth, motion=motion)
        result = calibrate(noisy, settings)
        assert result.success and len(result.held) == k
        value, at = gauged_nees(move, k, result)
        nees.append(value)
        held = np.linalg.qr(np.array([u.direction for u in result.held]).T)[0]
        cosines = np.linalg.svd(held.T @ null_space(move, k, at), compute_uv=False)
        worst_angle = max(worst_angle, np.degrees(np.arccos(min(1.0, cosines.min()))))
    assert worst_angle < 1.0
    lo, hi = band(12 - k, TRIALS)
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)


@pytest.mark.slow
@pytest.mark.parametrize('method', ['ols', 'tls'])
@pytest.mark.parametrize('rig', RIGS)
def test_a_partial_prior_determines_the_held_directions_consistently(rig, method):
    motion, truth = _rig(rig)
    rng = np.random.default_rng(13)
    sa, sp = SIGMA_A[method], PRIOR_SIGMA[rig]
    settings = Settings(method=method, sigma_a=sa, sigma_b=SIGMA_B, robust=False)
    cov = np.diag([sp ** 2] * 3 + [np.inf] * 3)
    nees = []
    for _ in range(TRIALS):
        noisy, _, _ = simulate_pairs(rng, PAIRS, 'full_pose', sigma_a=sa, sigma_b=SIGMA_B,
                                     truth=truth, motion=motion)
        drawn = truth.markers[0] + rng.normal(scale=sp, size=3)  # the prior's own error
        prior = Prior(tool_to_marker=UncertainPose(drawn, truth.q1, cov))
        result = calibrate(noisy, settings, prior)
        assert result.success and not result.held
        assert result.unobservable and all(u.by == 'prior' for u in result.unobservable)
        e = errors12(truth.p0, truth.q0, truth.markers[0], truth.q1, result)
        nees.append(float(e @ np.linalg.solve(result.cov_joint, e)))
    lo, hi = band(12, TRIALS)
    assert lo < np.mean(nees) < hi, (np.mean(nees), lo, hi)
