"""
Property tests of the uncertainty algebra (Hoff & Vincent 2000) over random poses and covariances.

Each example draws a seed; the poses are anywhere in SE(3) and the covariances random SPD with
correlations. The identities are exact up to rounding for first-order propagation, because the
Jacobians are the exact derivatives of the same functions.
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.types import UncertainPose
from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np

SEEDS = st.integers(min_value=0, max_value=2 ** 32 - 1)


def _pose(rng) -> UncertainPose:
    q = rng.normal(size=4)
    A = rng.normal(size=(6, 6))
    C = A @ A.T + 0.5 * np.eye(6)
    s = np.array([1e-3] * 3 + [1e-2] * 3) * rng.uniform(0.2, 5.0, 6)
    return UncertainPose(rng.normal(scale=2.0, size=3), quat.canonical(q / np.linalg.norm(q)),
                         C * np.outer(s, s) / np.outer(np.sqrt(np.diag(C)), np.sqrt(np.diag(C))))


def _same_rotation(q0, q1):
    # components, not an angle: acos near 1 resolves only ~1e-8 rad
    np.testing.assert_allclose(quat.canonical(q0), quat.canonical(q1), atol=1e-12)


def _same(a: UncertainPose, b: UncertainPose, rtol=1e-9):
    np.testing.assert_allclose(a.position, b.position, atol=1e-12)
    _same_rotation(a.quat_wxyz, b.quat_wxyz)
    scale = np.max(np.abs(a.covariance))
    np.testing.assert_allclose(a.covariance, b.covariance, rtol=rtol, atol=rtol * scale)


@settings(max_examples=60, deadline=None)
@given(SEEDS)
def test_compose_with_inverse_is_the_identity(seed):
    a = _pose(np.random.default_rng(seed))
    inv = unc.invert(a)
    # T · T⁻¹: one pose, fully correlated with its inverse, so the error cancels exactly
    J = unc.inverse_jacobian(a.position, a.quat_wxyz)
    ident = unc.compose(a, inv, cross_cov=a.covariance @ J.T)
    np.testing.assert_allclose(ident.position, 0.0, atol=1e-12)
    _same_rotation(ident.quat_wxyz, np.array([1.0, 0, 0, 0]))
    np.testing.assert_allclose(ident.covariance, 0.0, atol=1e-12 * np.max(np.abs(a.covariance)))
    _same(unc.invert(inv), a)


@settings(max_examples=60, deadline=None)
@given(SEEDS)
def test_chain_is_associative(seed):
    rng = np.random.default_rng(seed)
    a, b, c = _pose(rng), _pose(rng), _pose(rng)
    left = unc.compose(unc.compose(a, b), c)
    right = unc.compose(a, unc.compose(b, c))
    _same(left, right)
    _same(unc.chain([a, b, c]), left)


@settings(max_examples=60, deadline=None)
@given(SEEDS)
def test_fusing_an_estimate_with_itself_halves_its_covariance(seed):
    a = _pose(np.random.default_rng(seed))
    f = unc.fuse(a, a)
    np.testing.assert_allclose(f.position, a.position, atol=1e-12)
    _same_rotation(f.quat_wxyz, a.quat_wxyz)
    np.testing.assert_allclose(f.covariance, a.covariance / 2, rtol=1e-8,
                               atol=1e-8 * np.max(np.abs(a.covariance)))
