"""
Tests of coreg_ros.core.quaternion against scipy's Rotation and finite differences.

Quaternions are (w, x, y, z) in the package; scipy's Rotation takes and gives (x, y, z, w)
(``strategies.scipy_rotation`` and ``WXYZ`` reorder: the package supports scipy 1.11, whose
Rotation has no ``scalar_first``). Property tests sample all of SO(3), with extra weight near
the identity and near 180° (jaxlie style), where conversions are most fragile.
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import CoregError, InputError
from hypothesis import given, settings
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp
from strategies import quaternions, rotvecs, scipy_rotation, unit, WXYZ

PROPERTY = settings(max_examples=60, deadline=None)


def rot(q):
    """Scipy rotation of (w, x, y, z) quaternion(s)."""
    return scipy_rotation(np.asarray(q))


def assert_same_rotation(q, r, atol=1e-12):
    """Quaternions equal up to sign (q and -q are one rotation)."""
    q, r = np.asarray(q), np.asarray(r)
    d = np.minimum(np.abs(q - r).max(axis=-1), np.abs(q + r).max(axis=-1))
    assert np.max(d) <= atol, f'quaternions differ by {np.max(d):.3g} (up to sign)'


# ---------------------------------------------------------------------------------------------
# Products and conversions against scipy
# ---------------------------------------------------------------------------------------------

@PROPERTY
@given(quaternions(), quaternions())
def test_multiply_composes_rotations_like_scipy(p, q):
    expected = (rot(p) * rot(q)).as_quat()[..., WXYZ]
    assert_same_rotation(quat.multiply(p, q), expected, atol=1e-12)
    # Hamilton product, exactly (not only up to sign): R(p ⊗ q) = R(p) R(q).
    np.testing.assert_allclose(quat.to_matrix(quat.multiply(p, q)),
                               rot(p).as_matrix() @ rot(q).as_matrix(), atol=1e-12)


def test_multiply_left_and_right_matrices():
    rng = np.random.default_rng(0)
    p, q = rng.normal(size=(2, 50, 4))
    prod = quat.multiply(p, q)
    np.testing.assert_allclose(np.einsum('nij,nj->ni', quat.left_matrix(p), q), prod, atol=1e-12)
    np.testing.assert_allclose(np.einsum('nij,nj->ni', quat.right_matrix(q), p), prod, atol=1e-12)


def test_multiply_broadcasts_and_conjugate_inverts():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(5, 7, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    ident = quat.multiply(q, quat.conjugate(q))
    np.testing.assert_allclose(ident, np.broadcast_to([1.0, 0, 0, 0], q.shape), atol=1e-12)
    one = quat.multiply(q[0, 0], q)  # (4,) with (5, 7, 4)
    assert one.shape == (5, 7, 4)
    np.testing.assert_allclose(one[2, 3], quat.multiply(q[0, 0], q[2, 3]))


@PROPERTY
@given(quaternions())
def test_to_matrix_matches_scipy(q):
    np.testing.assert_allclose(quat.to_matrix(q), rot(q).as_matrix(), atol=1e-12)


@PROPERTY
@given(quaternions())
def test_from_matrix_matches_scipy_and_is_canonical(q):
    R = rot(q).as_matrix()
    got = quat.from_matrix(R)
    assert got[0] >= 0.0
    assert abs(np.linalg.norm(got) - 1.0) < 1e-12
    assert_same_rotation(got, q, atol=1e-9)
    assert_same_rotation(got, Rotation.from_matrix(R).as_quat()[..., WXYZ], atol=1e-9)


@pytest.mark.parametrize('eps', [0.0, 1e-12, 1e-8, 1e-5, 1e-2])
def test_from_matrix_near_180_degrees(eps):
    rng = np.random.default_rng(2)
    axis = rng.normal(size=(200, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    R = Rotation.from_rotvec((np.pi - eps) * axis).as_matrix()
    got = quat.from_matrix(R)
    assert np.all(got[:, 0] >= 0.0)
    np.testing.assert_allclose(quat.to_matrix(got), R, atol=1e-12)
    assert_same_rotation(got, Rotation.from_matrix(R).as_quat()[..., WXYZ], atol=1e-9)


def test_from_matrix_vectorised_over_leading_axes():
    rng = np.random.default_rng(3)
    R = Rotation.random(24, random_state=4).as_matrix().reshape(2, 3, 4, 3, 3)
    got = quat.from_matrix(R)
    assert got.shape == (2, 3, 4, 4)
    np.testing.assert_allclose(quat.to_matrix(got), R, atol=1e-12)
    del rng


# ---------------------------------------------------------------------------------------------
# Exp / Log
# ---------------------------------------------------------------------------------------------

@PROPERTY
@given(rotvecs())
def test_exp_matches_scipy(v):
    q = quat.exp(v)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    assert_same_rotation(q, Rotation.from_rotvec(v).as_quat()[..., WXYZ], atol=1e-12)


@PROPERTY
@given(rotvecs(max_angle=np.pi))
def test_log_exp_round_trip(v):
    back = quat.log(quat.exp(v))
    angle = np.linalg.norm(v)
    if angle < np.pi - 1e-6:
        # Away from π the rotation vector is unique.
        np.testing.assert_allclose(back, v, rtol=1e-9, atol=1e-15)
    else:
        # At π, v and -v are the same rotation; the angle and the rotation must survive.
        assert abs(np.linalg.norm(back) - angle) < 1e-8
        assert_same_rotation(quat.exp(back), quat.exp(v), atol=1e-8)


@pytest.mark.parametrize('angle', [0.0, 1e-15, 1e-10, 1e-7, 1e-6, 1.0000001e-6, 1e-3])
def test_exp_log_accurate_at_tiny_angles(angle):
    v = angle * unit([1.0, -2.0, 0.5])
    q = quat.exp(v)
    # Exact: (cos θ/2, sin(θ/2) v/θ); for tiny θ the vector part is v/2 to relative O(θ²).
    np.testing.assert_allclose(q[1:], 0.5 * v * (1 - angle ** 2 / 24), rtol=1e-14, atol=0)
    assert abs(q[0] - np.cos(angle / 2)) < 1e-16
    np.testing.assert_allclose(quat.log(q), v, rtol=1e-12, atol=0)


@PROPERTY
@given(quaternions())
def test_log_matches_scipy_and_ignores_sign(q):
    v = quat.log(q)
    assert np.linalg.norm(v) <= np.pi + 1e-12
    if abs(q[0]) > 1e-12:
        np.testing.assert_allclose(quat.log(-q), v, atol=1e-12)
    else:  # exactly 180°: +v and -v are one rotation, either is a correct answer
        assert_same_rotation(quat.exp(quat.log(-q)), q, atol=1e-12)
    ref = rot(q).as_rotvec()
    if np.linalg.norm(ref) < np.pi - 1e-6:
        np.testing.assert_allclose(v, ref, atol=1e-9)
    assert_same_rotation(quat.exp(v), q, atol=1e-9)


def test_log_near_pi_keeps_angle():
    rng = np.random.default_rng(5)
    axis = rng.normal(size=(100, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    for eps in (0.0, 1e-12, 1e-9, 1e-6):
        v = (np.pi - eps) * axis
        back = quat.log(quat.exp(v))
        np.testing.assert_allclose(np.linalg.norm(back, axis=1), np.pi - eps, atol=1e-9)
        np.testing.assert_allclose(np.abs(np.einsum('ij,ij->i', back, axis)), np.pi - eps,
                                   atol=1e-9)


@pytest.mark.parametrize('spread', [1.0, 1e-3, 1e-9, 0.0])
def test_relative_log_is_log_of_the_relative_rotation_to_the_bit(spread):
    # random signs, neighbours (a velocity's window), identical pairs and w = 0 exactly
    rng = np.random.default_rng(11)
    q1 = rng.normal(size=(20000, 4))
    q0 = q1 + spread * rng.normal(size=q1.shape)
    q1 /= np.linalg.norm(q1, axis=1, keepdims=True)
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    q0[rng.random(len(q0)) < 0.5] *= -1.0
    q1[:50, 0] = 0.0
    composed = quat.log(quat.multiply(q1, quat.conjugate(q0)))
    fused = quat.relative_log(q1, q0)
    assert fused.shape == composed.shape
    assert np.array_equal(fused.view(np.int64), composed.view(np.int64))


# ---------------------------------------------------------------------------------------------
# Slerp and canonical sign
# ---------------------------------------------------------------------------------------------

@PROPERTY
@given(quaternions(), quaternions())
def test_slerp_endpoints_and_midpoint(q0, q1):
    assert_same_rotation(quat.slerp(q0, q1, 0.0), q0, atol=1e-12)
    assert_same_rotation(quat.slerp(q0, q1, 1.0), q1, atol=1e-9)
    mid = quat.slerp(q0, q1, 0.5)
    total = quat.angle_between(q0, q1)
    if total < np.pi - 1e-6:  # at exactly 180° the shorter arc is not unique
        np.testing.assert_allclose(quat.angle_between(q0, mid), total / 2, atol=1e-7)
        np.testing.assert_allclose(quat.angle_between(mid, q1), total / 2, atol=1e-7)
        ref = Slerp([0.0, 1.0], rot(np.stack([q0, q1])))([0.5]).as_quat()[..., WXYZ][0]
        assert_same_rotation(mid, ref, atol=1e-9)


def test_slerp_takes_the_shorter_arc_and_is_vectorised():
    rng = np.random.default_rng(6)
    q0 = Rotation.random(40, random_state=7).as_quat()[..., WXYZ]
    q1 = Rotation.random(40, random_state=8).as_quat()[..., WXYZ]
    t = rng.uniform(0.0, 1.0, 40)
    a = quat.slerp(q0, q1, t)
    b = quat.slerp(q0, -q1, t)  # same endpoints as rotations
    assert_same_rotation(a, b, atol=1e-12)
    ref = np.stack([Slerp([0.0, 1.0], rot(np.stack([q0[i], q1[i]])))([t[i]])
                    .as_quat()[..., WXYZ][0] for i in range(40)])
    assert_same_rotation(a, ref, atol=1e-9)
    # Angle from q0 grows linearly in t along the shorter arc.
    np.testing.assert_allclose(quat.angle_between(q0, a), t * quat.angle_between(q0, q1),
                               atol=1e-8)


@PROPERTY
@given(quaternions())
def test_canonical_sign(q):
    c = quat.canonical(q)
    assert c[0] >= 0.0
    assert_same_rotation(c, q, atol=0.0)
    np.testing.assert_array_equal(quat.canonical(c), c)


def test_canonical_is_vectorised():
    q = np.array([[-0.5, 0.5, 0.5, 0.5], [0.5, -0.5, 0.5, 0.5], [-1.0, 0.0, 0.0, 0.0]])
    c = quat.canonical(q)
    np.testing.assert_array_equal(c, [[0.5, -0.5, -0.5, -0.5], [0.5, -0.5, 0.5, 0.5],
                                      [1.0, 0.0, 0.0, 0.0]])


# ---------------------------------------------------------------------------------------------
# Validation of measured quaternions
# ---------------------------------------------------------------------------------------------

def test_validate_normalises_and_canonicalises():
    q = np.array([[-0.5, 0.5, 0.5, 0.5], [0.0, 0.0, 0.0, 1.004]])
    out = quat.validate_quaternions(q)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-15)
    assert np.all(out[:, 0] >= 0)
    assert_same_rotation(out[0], q[0], atol=1e-15)


@pytest.mark.parametrize('bad, words', [
    ([np.nan, 0.0, 0.0, 1.0], ['NaN', 'index 1']),
    ([np.inf, 0.0, 0.0, 1.0], ['inf', 'index 1']),
    ([0.0, 0.0, 0.0, 0.0], ['not unit length', 'norm 0', 'index 1', 'zero']),
    ([1.5, 0.0, 0.0, 0.0], ['not unit length', 'norm 1.5', 'index 1']),
    ([0.0, 0.0, 0.0, 0.95], ['not unit length', 'norm 0.95', 'field order']),
])
def test_validate_refuses_bad_quaternions(bad, words):
    q = np.array([[1.0, 0.0, 0.0, 0.0], bad, [0.0, 1.0, 0.0, 0.0]])
    with pytest.raises(InputError) as info:
        quat.validate_quaternions(q, 'device A orientation')
    msg = str(info.value)
    assert 'device A orientation' in msg
    assert '\n' not in msg
    for w in words:
        assert w in msg, f'{w!r} not in {msg!r}'
    assert isinstance(info.value, CoregError) and isinstance(info.value, ValueError)


@pytest.mark.parametrize('shape', [(4, 3), (3,), (), (2, 5)])
def test_validate_refuses_wrong_shapes(shape):
    with pytest.raises(InputError, match=r'expected shape \(\.\.\., 4\)'):
        quat.validate_quaternions(np.ones(shape), 'q')


def test_validate_tolerance_is_one_percent():
    ok = np.array([1.0 + 0.9 * quat.UNIT_NORM_TOLERANCE, 0.0, 0.0, 0.0])
    quat.validate_quaternions(ok)
    with pytest.raises(InputError):
        quat.validate_quaternions(np.array([1.0 + 1.1 * quat.UNIT_NORM_TOLERANCE, 0, 0, 0]))


# ---------------------------------------------------------------------------------------------
# Reduced quaternion (Ikits §3.1, eqs. 7-10)
# ---------------------------------------------------------------------------------------------

def quaternion_in_chart(rng, k, sign, margin=0.0):
    """Draw a random unit quaternion whose largest-magnitude component is index k, that sign."""
    while True:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        a = np.abs(q)
        j = int(np.argmax(a))
        q[[j, k]] = q[[k, j]]
        q[k] = sign * abs(q[k])
        others = np.delete(np.abs(q), k)
        if abs(q[k]) - others.max() >= margin:
            return q


CHARTS = [(k, s) for k in range(4) for s in (1.0, -1.0)]


@pytest.mark.parametrize('k, sign', CHARTS)
def test_reduce_expand_round_trip_in_every_chart(k, sign):
    rng = np.random.default_rng(10 + k)
    for _ in range(50):
        q = quaternion_in_chart(rng, k, sign, margin=1e-6)
        s, chart, sg = quat.reduce(q)
        assert int(chart) == k and float(sg) == sign
        np.testing.assert_array_equal(s, np.delete(q, k))  # eq. 7: the other three, in order
        back, _ = quat.expand(s, chart, sg)
        np.testing.assert_allclose(back, q, atol=1e-15)  # exactly q, sign included (eq. 9)


def test_reduce_expand_vectorised():
    rng = np.random.default_rng(11)
    q = rng.normal(size=(6, 5, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    s, chart, sign = quat.reduce(q)
    assert s.shape == (6, 5, 3) and chart.shape == (6, 5) and sign.shape == (6, 5)
    back, jac = quat.expand(s, chart, sign)
    assert jac.shape == (6, 5, 4, 3)
    np.testing.assert_allclose(back, q, atol=1e-15)


@pytest.mark.parametrize('k, sign', CHARTS)
def test_expand_jacobian_matches_ikits_eq10_and_finite_differences(k, sign):
    rng = np.random.default_rng(20 + k)
    h = 1e-6
    for _ in range(20):
        q = quaternion_in_chart(rng, k, sign, margin=0.05)
        s = np.delete(q, k)
        _, jac = quat.expand(s, k, sign)
        # Eq. 10, with row k the derivative of the computed component, the rest the identity.
        expected = np.zeros((4, 3))
        expected[np.delete(np.arange(4), k), :] = np.eye(3)
        expected[k, :] = -s / q[k]
        np.testing.assert_allclose(jac, expected, atol=1e-14)
        fd = np.empty((4, 3))
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            fd[:, i] = (quat.expand(s + e, k, sign)[0] - quat.expand(s - e, k, sign)[0]) / (2 * h)
        np.testing.assert_allclose(jac, fd, atol=1e-8)


def test_expand_outside_the_chart_is_nan():
    q, _ = quat.expand(np.array([0.8, 0.7, 0.1]), 0, 1.0)
    assert np.isnan(q).any()
    q, _ = quat.expand(np.array([0.6, 0.6, 0.5]), 2, -1.0)  # |s|² = 0.97: inside
    assert np.isfinite(q).all() and abs(np.linalg.norm(q) - 1) < 1e-15 and q[2] < 0


@pytest.mark.parametrize('k, sign', CHARTS)
def test_needs_rechart(k, sign):
    rng = np.random.default_rng(30 + k)
    for _ in range(20):
        q = quaternion_in_chart(rng, k, sign, margin=1e-3)
        assert not quat.needs_rechart(np.delete(q, k), k, sign)
        # Use another chart whose component is smaller than the largest: re-chart is needed.
        other = (k + 1 + int(rng.integers(3))) % 4
        if abs(q[other]) < 1e-3:
            continue
        sg = 1.0 if q[other] > 0 else -1.0
        assert quat.needs_rechart(np.delete(q, other), other, sg)


# ---------------------------------------------------------------------------------------------
# Error metric (Ikits §3.2, eqs. 11-15)
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('angle', [1e-8, 1e-5, 1e-3, 1e-2])
def test_rotation_error_is_minus_half_the_small_rotation(angle):
    rng = np.random.default_rng(40)
    q_model = Rotation.random(30, random_state=41).as_quat()[..., WXYZ]
    d = rng.normal(size=(30, 3))
    dtheta = angle * d / np.linalg.norm(d, axis=1, keepdims=True)
    q_meas = quat.multiply(quat.exp(dtheta), q_model)
    e, _ = quat.rotation_error(q_model, q_meas)
    # ≈ -δθ/2, with the relative error of the sine's second-order term.
    # (atol: rounding of the unit-quaternion product, a few ulp of 1)
    np.testing.assert_allclose(e, -dtheta / 2, rtol=angle ** 2 / 24 * 1.01, atol=1e-15)
    # exact: -sin(|δθ|/2) δθ/|δθ|
    np.testing.assert_allclose(e, -np.sin(angle / 2) * dtheta / angle, rtol=1e-12, atol=1e-15)


@PROPERTY
@given(quaternions(), quaternions())
def test_rotation_error_invariant_to_quaternion_sign(q_model, q_meas):
    e, _ = quat.rotation_error(q_model, q_meas)
    for a, b in ((q_model, -q_meas), (-q_model, q_meas), (-q_model, -q_meas)):
        e2, _ = quat.rotation_error(a, b)
        if abs(np.dot(q_model, q_meas)) > 1e-9:  # away from the 180° ambiguity
            np.testing.assert_allclose(e2, e, atol=1e-15)
    # |e| is sin of half the angle between them
    half = quat.angle_between(q_model, q_meas) / 2
    np.testing.assert_allclose(np.linalg.norm(e), np.sin(half), atol=1e-7)


def test_rotation_error_jacobian_matches_finite_differences():
    rng = np.random.default_rng(42)
    h = 1e-7
    q_model = Rotation.random(25, random_state=43).as_quat()[..., WXYZ]
    q_meas = quat.multiply(quat.exp(rng.normal(scale=0.5, size=(25, 3))), q_model)
    q_meas[::2] *= -1  # either sign of the measurement
    _, de_dq = quat.rotation_error(q_model, q_meas)
    for i in range(4):
        step = np.zeros(4)
        step[i] = h
        fd = (quat.rotation_error(q_model + step, q_meas)[0]
              - quat.rotation_error(q_model - step, q_meas)[0]) / (2 * h)
        np.testing.assert_allclose(de_dq[:, :, i], fd, atol=1e-8)


def test_angle_between_matches_scipy():
    a = Rotation.random(50, random_state=44)
    b = Rotation.random(50, random_state=45)
    got = quat.angle_between(a.as_quat()[..., WXYZ], -b.as_quat()[..., WXYZ])
    np.testing.assert_allclose(got, (a.inv() * b).magnitude(), atol=1e-7)
