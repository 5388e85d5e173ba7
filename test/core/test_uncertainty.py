"""
Tests of coreg_ros.core.uncertainty.

Jacobians against finite differences, exact identities, and every propagated or fused
covariance against the spread of a Monte Carlo.

Monte Carlo tolerances: with N = 20 000 trials of a d-dimensional error, the mean NEES has a
standard deviation of sqrt(2d / N) (0.024 for d = 6, 1 % of 6 at three sigma) and the coverage
of a 95 % ellipsoid one of sqrt(0.95 · 0.05 / N) = 0.0015; the checks (NEES within 5 % of d,
coverage within 93-97 %) therefore fail only for a real mismatch, the noise being kept small
enough (≤ 0.05 rad) for first-order propagation to hold.
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.errors import InputError
from coreg_ros.core.types import CalibrationResult, UncertainPose
import numpy as np
import pytest
from scipy import stats
from strategies import random_cov, random_rotation

N_MC = 20_000


def perturb(rng, p, q, cov, n):
    """Truths around an estimate: p + δp, Exp(δθ) q with δ ~ N(0, cov); shape (n, ...)."""
    d = rng.multivariate_normal(np.zeros(cov.shape[0]), cov, size=n)
    return p + d[:, 0:3], quat.multiply(quat.exp(d[:, 3:6]), q)


def check_consistent(err, cov, dim):
    """NEES within 5 % of dim and 95 % ellipsoid coverage in [0.93, 0.97]."""
    cov = np.broadcast_to(cov, err.shape + (err.shape[-1],))
    e = unc.nees(err, cov)
    mean = float(np.mean(e))
    coverage = float(np.mean(e <= stats.chi2.ppf(0.95, dim)))
    assert abs(mean - dim) <= 0.05 * dim, f'NEES {mean:.3f} vs {dim}'
    assert 0.93 <= coverage <= 0.97, f'coverage {coverage:.4f}'
    print(f'MC d={dim}: NEES {mean:.3f}, 95 % coverage {coverage:.4f}')
    return mean, coverage


def numeric_jacobian(f, x0, h=1e-6):
    x0 = np.asarray(x0, dtype=float)
    cols = []
    for i in range(x0.size):
        d = np.zeros_like(x0)
        d[i] = h
        cols.append((f(x0 + d) - f(x0 - d)) / (2 * h))
    return np.stack(cols, axis=-1)


def boxplus(p, q, d):
    return p + d[0:3], quat.multiply(quat.exp(d[3:6]), q)


# --------------------------------------------------------------------------- Jacobians

def test_compose_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    pa, qa = rng.normal(size=3), random_rotation(rng)
    pb, qb = rng.normal(size=3), random_rotation(rng)
    p0, q0, _ = unc.compose_arrays(pa, qa, np.zeros((6, 6)), pb, qb, np.zeros((6, 6)))

    def f_a(d):
        p, q = boxplus(pa, qa, d)
        pc, qc, _ = unc.compose_arrays(p, q, np.zeros((6, 6)), pb, qb, np.zeros((6, 6)))
        return unc.pose_error(pc, qc, p0, q0)

    def f_b(d):
        p, q = boxplus(pb, qb, d)
        pc, qc, _ = unc.compose_arrays(pa, qa, np.zeros((6, 6)), p, q, np.zeros((6, 6)))
        return unc.pose_error(pc, qc, p0, q0)

    J_a, J_b = unc.compose_jacobians(pa, qa, pb)
    np.testing.assert_allclose(numeric_jacobian(f_a, np.zeros(6)), J_a, atol=1e-7)
    np.testing.assert_allclose(numeric_jacobian(f_b, np.zeros(6)), J_b, atol=1e-7)


def test_inverse_jacobian_matches_finite_differences():
    rng = np.random.default_rng(2)
    p, q = rng.normal(size=3), random_rotation(rng)
    pi, qi, _ = unc.invert_arrays(p, q, np.zeros((6, 6)))

    def f(d):
        pp, qq = boxplus(p, q, d)
        a, b, _ = unc.invert_arrays(pp, qq, np.zeros((6, 6)))
        return unc.pose_error(a, b, pi, qi)

    np.testing.assert_allclose(numeric_jacobian(f, np.zeros(6)), unc.inverse_jacobian(p, q),
                               atol=1e-7)


def test_left_jacobian_definition():
    rng = np.random.default_rng(3)
    for phi in (rng.normal(size=3), 1e-7 * rng.normal(size=3), np.array([3.0, 0.1, -0.1])):
        def f(d, phi=phi):
            return quat.log(quat.multiply(quat.exp(phi + d), quat.conjugate(quat.exp(phi))))
        np.testing.assert_allclose(numeric_jacobian(f, np.zeros(3), h=1e-7),
                                   unc.left_jacobian(phi), atol=1e-6)


# --------------------------------------------------------------------------- identities

def test_compose_with_inverse_is_identity_and_inverse_is_involution():
    rng = np.random.default_rng(4)
    a = UncertainPose(rng.normal(size=3), random_rotation(rng), random_cov(rng, 1e-3, 1e-2))
    inv = unc.invert(a)
    back = unc.invert(inv)
    np.testing.assert_allclose(back.position, a.position, atol=1e-12)
    np.testing.assert_allclose(back.covariance, a.covariance, atol=1e-15)
    # T · T⁻¹ = I exactly, and with full correlation (it is one pose) the error cancels
    J = unc.inverse_jacobian(a.position, a.quat_wxyz)
    ident = unc.compose(a, inv, cross_cov=a.covariance @ J.T)
    np.testing.assert_allclose(ident.position, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(ident.quat_wxyz), [1, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(ident.covariance, 0.0, atol=1e-15)


def test_chain_equals_pairwise_compose():
    rng = np.random.default_rng(5)
    poses = [UncertainPose(rng.normal(size=3), random_rotation(rng), random_cov(rng, 1e-3, 1e-2))
             for _ in range(3)]
    pairwise = unc.compose(unc.compose(poses[0], poses[1]), poses[2])
    chained = unc.chain(poses)
    np.testing.assert_allclose(chained.position, pairwise.position, atol=1e-12)
    np.testing.assert_allclose(chained.covariance, pairwise.covariance, rtol=1e-10, atol=1e-18)


def test_fuse_identical_estimates_halves_covariance_and_is_symmetric():
    rng = np.random.default_rng(6)
    a = UncertainPose(rng.normal(size=3), random_rotation(rng), random_cov(rng, 1e-3, 1e-2))
    f = unc.fuse(a, a)
    np.testing.assert_allclose(f.covariance, a.covariance / 2, rtol=1e-9)
    np.testing.assert_allclose(f.position, a.position, atol=1e-12)
    b = UncertainPose(a.position + 1e-3, quat.multiply(quat.exp([0.02, 0, 0.01]), a.quat_wxyz),
                      random_cov(rng, 2e-3, 5e-3))
    ab, ba = unc.fuse(a, b), unc.fuse(b, a)
    np.testing.assert_allclose(ab.position, ba.position, atol=1e-12)
    np.testing.assert_allclose(ab.covariance, ba.covariance, rtol=1e-9)
    # fused never worse than either input (Loewner order)
    for c in (a.covariance, b.covariance):
        assert np.linalg.eigvalsh(c - ab.covariance).min() > -1e-18


def test_fuse_mean_settles_at_stationary_point():
    """At the fused mean, the weighted tangent residuals of both inputs cancel."""
    rng = np.random.default_rng(7)
    p, q = rng.normal(size=3), random_rotation(rng)
    c1, c2 = random_cov(rng, 1e-3, 0.2), random_cov(rng, 5e-2, 1e-3)
    q2 = quat.multiply(quat.exp([0.4, -0.3, 0.2]), q)  # far apart: several re-centrings
    pf, qf, cf, it = unc.fuse_arrays(p, q, c1, p + 0.05, q2, c2)
    assert it >= 2
    total = np.zeros(6)
    for pi, qi, ci in ((p, q, c1), (p + 0.05, q2, c2)):
        xi = unc.pose_error(pi, qi, pf, qf)
        Jinv = np.eye(6)
        Jinv[3:6, 3:6] = unc.left_jacobian(xi[3:6])
        total += Jinv.T @ np.linalg.solve(ci, Jinv @ xi)
    np.testing.assert_allclose(total, 0.0, atol=1e-6 * np.abs(np.linalg.inv(cf)).max() * 1e-6)


def test_unknown_components_propagate_and_carry_no_information():
    rng = np.random.default_rng(8)
    c = random_cov(rng, 1e-3, 1e-2)
    c[3:6, :] = 0.0
    c[:, 3:6] = 0.0
    c[3, 3] = c[4, 4] = c[5, 5] = unc.UNKNOWN
    a = UncertainPose(rng.normal(size=3), random_rotation(rng), c)
    # the position of a point at the frame's origin does not depend on the rotation
    _, cp = unc.propagate_point(a, np.zeros(3))
    np.testing.assert_allclose(cp, c[0:3, 0:3])
    # a lever arm makes it unknown
    _, cp = unc.propagate_point(a, [0.1, 0, 0])
    assert (np.diag(cp) < 0).any()
    # fused with a full estimate: the rotation comes from the other one only
    b = UncertainPose(a.position, a.quat_wxyz, random_cov(rng, 1e-3, 1e-2))
    f = unc.fuse(a, b)
    assert np.all(np.diag(f.covariance) > 0)
    assert np.linalg.eigvalsh(b.covariance - f.covariance).min() > -1e-18
    with pytest.raises(InputError):
        unc.fuse(a, a)
    with pytest.raises(InputError):
        unc.axis_cones(a)


def test_ellipsoid_axes_and_cone_geometry():
    C = np.diag([4.0, 1.0, 9.0]) * 1e-6
    e = unc.ellipsoid_axes(C, 3.0)
    np.testing.assert_allclose(e.semi_axes, [9e-3, 6e-3, 3e-3])
    np.testing.assert_allclose(np.abs(e.axes), np.eye(3)[:, [2, 0, 1]], atol=1e-12)
    assert np.linalg.det(e.axes) > 0
    assert abs(e.probability - 0.9707) < 1e-3
    X, Y, Z = e.surface(n=8)
    pts = np.stack([X, Y, Z], -1).reshape(-1, 3)
    np.testing.assert_allclose(np.einsum('ni,ij,nj->n', pts, np.linalg.inv(C), pts), 9.0)
    # rotation uncertainty only about z: the x and y axes wobble in the xy plane, z is fixed
    cov = np.zeros((6, 6))
    cov[5, 5] = 1e-4
    cones = unc.axis_cones(UncertainPose(np.zeros(3), np.array([1.0, 0, 0, 0]), cov))
    np.testing.assert_allclose([c.half_angles[0] for c in cones],
                               [np.arctan(0.03), np.arctan(0.03), 0.0], atol=1e-12)
    np.testing.assert_allclose(np.abs(cones[0].ellipse_axes[:, 0]), [0, 1, 0], atol=1e-12)
    assert np.all([c.half_angles[1] == 0 for c in cones])
    assert abs(unc.sigma_for_probability(unc.coverage_probability(2.5, 3), 3) - 2.5) < 1e-9


# --------------------------------------------------------------------------- Monte Carlo

@pytest.fixture(scope='module')
def mc_rng():
    return np.random.default_rng(20001)


def test_compose_matches_monte_carlo(mc_rng):
    rng = mc_rng
    a = UncertainPose(rng.normal(size=3) * 0.5, random_rotation(rng), random_cov(rng, 1e-3, 0.02))
    b = UncertainPose(rng.normal(size=3) * 0.3, random_rotation(rng), random_cov(rng, 2e-3, 0.01))
    c = unc.compose(a, b)
    pa, qa = perturb(rng, a.position, a.quat_wxyz, a.covariance, N_MC)
    pb, qb = perturb(rng, b.position, b.quat_wxyz, b.covariance, N_MC)
    R = quat.to_matrix(qa)
    pc = pa + np.einsum('nij,nj->ni', R, pb)
    qc = quat.multiply(qa, qb)
    check_consistent(unc.pose_error(pc, qc, c.position, c.quat_wxyz), c.covariance, 6)


def test_correlated_chain_matches_monte_carlo(mc_rng):
    """T0 · T_A · T1 with a correlated (T0, T1) and independent T_A, as through_calibration."""
    rng = mc_rng
    A = rng.normal(size=(12, 12))
    joint = A @ A.T + 3 * np.eye(12)
    d = np.sqrt(np.diag(joint))
    s = np.array([1e-3] * 3 + [0.01] * 3 + [1e-3] * 3 + [0.02] * 3)
    joint = joint / np.outer(d, d) * np.outer(s, s)
    t0 = UncertainPose(rng.normal(size=3) * 0.5, random_rotation(rng), joint[0:6, 0:6])
    t1 = UncertainPose(rng.normal(size=3) * 0.1, random_rotation(rng), joint[6:12, 6:12])
    cov_a = random_cov(rng, 5e-4, 0.01)
    ta = UncertainPose(rng.normal(size=3) * 0.3, random_rotation(rng), cov_a)
    result = CalibrationResult(
        success=True, status=1, message='', model='full_pose', method='tls', n_pairs=0,
        base_to_base=t0, tool_to_marker=t1, markers=t1.position[None], params=np.zeros(12),
        param_cov=None, chi2=0.0, dof=1, p_value=0.5, residuals=np.zeros((0, 6)),
        iterations=0, cov_joint=joint)
    y = unc.through_calibration(result, ta)
    full = np.zeros((18, 18))
    full[0:6, 0:6], full[0:6, 12:18] = joint[0:6, 0:6], joint[0:6, 6:12]
    full[12:18, 0:6], full[12:18, 12:18] = joint[6:12, 0:6], joint[6:12, 6:12]
    full[6:12, 6:12] = cov_a
    np.testing.assert_allclose(unc.chain([t0, ta, t1], full).covariance, y.covariance,
                               rtol=1e-9, atol=1e-20)
    dd = rng.multivariate_normal(np.zeros(18), full, size=N_MC)
    p0, q0 = t0.position + dd[:, 0:3], quat.multiply(quat.exp(dd[:, 3:6]), t0.quat_wxyz)
    pa, qa = ta.position + dd[:, 6:9], quat.multiply(quat.exp(dd[:, 9:12]), ta.quat_wxyz)
    p1, q1 = t1.position + dd[:, 12:15], quat.multiply(quat.exp(dd[:, 15:18]), t1.quat_wxyz)
    R0, Ra = quat.to_matrix(q0), quat.to_matrix(qa)
    py = p0 + np.einsum('nij,nj->ni', R0, pa + np.einsum('nij,nj->ni', Ra, p1))
    qy = quat.multiply(quat.multiply(q0, qa), q1)
    check_consistent(unc.pose_error(py, qy, y.position, y.quat_wxyz), y.covariance, 6)


def test_invert_matches_monte_carlo(mc_rng):
    rng = mc_rng
    # second-order terms |p| δθ² / 2 must stay well below the position noise
    a = UncertainPose(0.3 * rng.normal(size=3), random_rotation(rng), random_cov(rng, 1e-3, 0.01))
    inv = unc.invert(a)
    p, q = perturb(rng, a.position, a.quat_wxyz, a.covariance, N_MC)
    Rt = np.swapaxes(quat.to_matrix(q), -1, -2)
    pi = -np.einsum('nij,nj->ni', Rt, p)
    qi = quat.conjugate(q)
    check_consistent(unc.pose_error(pi, qi, inv.position, inv.quat_wxyz), inv.covariance, 6)


def test_point_ellipsoid_matches_monte_carlo(mc_rng):
    """A stylus tip 15 cm from the tracked frame: 3-D ellipsoid, 95 % and 3σ coverage."""
    rng = mc_rng
    a = UncertainPose(rng.normal(size=3), random_rotation(rng), random_cov(rng, 2e-4, 0.01))
    tip = np.array([0.0, 0.0, 0.15])
    y, cy = unc.propagate_point(a, tip)
    p, q = perturb(rng, a.position, a.quat_wxyz, a.covariance, N_MC)
    ys = p + np.einsum('nij,j->ni', quat.to_matrix(q), tip)
    err = ys - y
    check_consistent(err, cy, 3)
    e = unc.ellipsoid_axes(cy, 3.0)
    local = err @ e.axes / e.semi_axes
    inside = float(np.mean(np.sum(local ** 2, axis=1) <= 1.0))
    assert abs(inside - e.probability) < 0.01
    # Hoff's ΔP = d Δθ: the lever arm dominates here
    assert e.semi_axes[0] > 3 * np.sqrt(np.max(np.diag(a.covariance)[0:3]))


def test_axis_cones_match_monte_carlo(mc_rng):
    rng = mc_rng
    a = UncertainPose(np.zeros(3), random_rotation(rng), random_cov(rng, 1e-3, 0.02))
    cones = unc.axis_cones(a, n_sigma=2.0)
    _, q = perturb(rng, a.position, a.quat_wxyz, a.covariance, N_MC)
    R = quat.to_matrix(q)
    for cone in cones:
        tips = R[:, :, cone.index]
        dev = tips - cone.direction
        local = dev @ cone.ellipse_axes  # (N, 2) in the plane perpendicular to the axis
        cov2 = cone.ellipse_axes.T @ cone.covariance @ cone.ellipse_axes
        check_consistent(local, cov2, 2)
        angles = np.arctan(local / np.tan(cone.half_angles))  # scaled to the cone
        inside = float(np.mean(np.sum(np.tan(angles) ** 2, axis=1) <= 1.0))
        assert abs(inside - cone.probability) < 0.01


@pytest.mark.parametrize('case', ['hoff_complementary', 'generic'])
def test_fusion_matches_monte_carlo(mc_rng, case):
    rng = mc_rng
    p, q = rng.normal(size=3), random_rotation(rng)
    if case == 'hoff_complementary':
        # one estimate with good position and weak orientation, the other the opposite, and
        # a lever-arm correlation as a pose carried through a transform has
        c1 = random_cov(rng, 2e-4, 0.04, corr=2.0)
        c2 = random_cov(rng, 5e-3, 2e-3, corr=2.0)
    else:
        c1, c2 = random_cov(rng, 1e-3, 0.02), random_cov(rng, 2e-3, 0.01)
    d1 = rng.multivariate_normal(np.zeros(6), c1, size=N_MC)
    d2 = rng.multivariate_normal(np.zeros(6), c2, size=N_MC)
    # estimates such that truth = estimate ⊞ δ
    p1, q1 = p - d1[:, 0:3], quat.multiply(quat.exp(-d1[:, 3:6]), q)
    p2, q2 = p - d2[:, 0:3], quat.multiply(quat.exp(-d2[:, 3:6]), q)
    pf, qf, cf, _ = unc.fuse_arrays(p1, q1, c1, p2, q2, c2)
    err = unc.pose_error(p, q, pf, qf)
    check_consistent(err, cf, 6)
    # and better than either input on every axis, as predicted
    for c in (c1, c2):
        assert np.all(np.diag(cf[0]) <= np.diag(c) + 1e-18)
    emp = np.cov(err.T)
    np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(cf[0])), rtol=0.03)


def test_display_geometry():
    rng = np.random.default_rng(9)
    C = random_cov(rng, 1e-3, 1e-2)[0:3, 0:3]
    e = unc.ellipsoid_axes(C)
    R = quat.to_matrix(unc.ellipsoid_orientation(e))
    np.testing.assert_allclose(R, e.axes, atol=1e-12)
    np.testing.assert_allclose(R @ np.diag(e.semi_axes ** 2) @ R.T, 9 * C, rtol=1e-9)
    pose = UncertainPose(np.zeros(3), random_rotation(rng), random_cov(rng, 1e-3, 1e-2))
    cone = unc.axis_cones(pose)[0]
    tri = unc.cone_mesh(cone, length=0.2, gain=5.0, n=16, origin=[1.0, 0, 0])
    assert tri.shape == (16, 3, 3)
    np.testing.assert_allclose(tri[:, 0], [[1.0, 0, 0]] * 16)
    rim = tri[:, 1] - [1.0, 0, 0]
    # rim points lie at axis length along the axis, inside the magnified cone
    np.testing.assert_allclose(rim @ cone.direction, 0.2, atol=1e-12)
    off = np.linalg.norm(rim - 0.2 * cone.direction, axis=1) / 0.2
    assert np.all(off <= 5.0 * np.tan(cone.half_angles[0]) + 1e-12)
    assert off.max() == pytest.approx(5.0 * np.tan(cone.half_angles[0]), rel=1e-3)


def test_fusing_a_through_a_real_calibration_with_b_beats_both():
    """Hoff's experiment in small (bench/hoff_experiment.py runs it at full size)."""
    from coreg_ros.core.calibration.calibrate import calibrate
    from coreg_ros.core.estimator import noise_covariance
    from coreg_ros.core.settings import Settings
    from coreg_ros.sim import simulate_pairs

    sa, sb = (1e-4, 2e-3), (2e-3, 8e-4)
    rng = np.random.default_rng(12)
    cal, _, truth = simulate_pairs(rng, 800, sigma_a=sa, sigma_b=sb)
    result = calibrate(cal, Settings(sigma_a=sa, sigma_b=sb))
    test, clean, _ = simulate_pairs(rng, 3000, sigma_a=sa, sigma_b=sb, truth=truth)
    pa, qa, ca = unc.through_calibration_arrays(result, test.pos_a, test.quat_a,
                                                noise_covariance(sa))
    cb = np.broadcast_to(noise_covariance(sb), ca.shape)
    pf, qf, cf, _ = unc.fuse_arrays(pa, qa, ca, test.pos_b, test.quat_b, cb)
    rms = {name: np.sqrt(np.mean(unc.pose_error(clean.pos_b, clean.quat_b, p, q) ** 2, axis=0))
           for name, (p, q) in {'a': (pa, qa), 'b': (test.pos_b, test.quat_b),
                                'f': (pf, qf)}.items()}
    assert np.all(rms['f'] < np.minimum(rms['a'], rms['b']))
    # B's orientation removes the lever-arm part of A's position error (not the calibration's)
    assert np.all(rms['f'][0:3] < 0.9 * rms['a'][0:3])
    # one calibration's error is shared by every sample, so one rig only checks the scale;
    # bench/hoff_experiment.py checks NEES and coverage over 100 calibrations
    ratio = rms['f'] / np.sqrt(np.mean(np.diagonal(cf, 0, 1, 2), axis=0))
    assert np.all((ratio > 0.5) & (ratio < 2.0))
