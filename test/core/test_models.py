"""
Tests of coreg_ros.core.models.

Analytic Jacobians against central finite differences, and the model equation against an
independent computation with 4×4 homogeneous matrices.

The paper's Jacobians (eqs. 48-49) have index typos, so every Jacobian is checked numerically:
``j_phi`` by stepping φ in its chart (``Parameters.stepped``), ``j_x`` by the input
perturbation ``q_A ← Exp(δ) ⊗ q_A``, ``p_A ← p_A + δp`` (the one ``linearize`` documents).
"""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.models import (
    error_rotation_jacobian,
    linearize,
    output_error,
    Parameters,
    predict,
    S0,
    S1,
    SPECS,
    tangent_of_chart,
)
from hypothesis import given, settings
import hypothesis.strategies as st
import numpy as np
import pytest
from strategies import random_quat, scipy_rotation

MODELS = tuple(SPECS)
CHARTS = [(k, s) for k in range(4) for s in (1.0, -1.0)]


def quaternion_in_chart(rng, k, sign, margin=0.05):
    """Random unit quaternion whose largest component is index k, with the given sign."""
    while True:
        q = random_quat(rng)
        j = int(np.argmax(np.abs(q)))
        q[[j, k]] = q[[k, j]]
        q[k] = sign * abs(q[k])
        if abs(q[k]) - np.delete(np.abs(q), k).max() >= margin:
            return q


def params_in_charts(spec, rng, chart0=None, chart1=None):
    """Random φ of a model with its rotations in the given (k, sign) charts (else random)."""
    phi = np.zeros(spec.n_params)
    phi[0:3] = rng.uniform(-1, 1, 3)
    charts = []
    k0, sg0 = chart0 or (int(rng.integers(4)), float(rng.choice([-1.0, 1.0])))
    q0 = quaternion_in_chart(rng, k0, sg0)
    phi[S0] = np.delete(q0, k0)
    charts.append((k0, sg0))
    for j in range(spec.n_markers):
        phi[spec.marker_slice(j)] = rng.uniform(-0.2, 0.2, 3)
    if spec.has_q1:
        k1, sg1 = chart1 or (int(rng.integers(4)), float(rng.choice([-1.0, 1.0])))
        q1 = quaternion_in_chart(rng, k1, sg1)
        phi[S1] = np.delete(q1, k1)
        charts.append((k1, sg1))
    return Parameters(spec, phi, charts)


def data_for(params, rng, n=7, noise=0.1):
    """Draw inputs over all of SO(3) and outputs near the model's prediction (like real data)."""
    pos_a = rng.uniform(-0.5, 0.5, (n, 3))
    quat_a = random_quat(rng, n)
    pos_b, quat_b = predict(params, pos_a, quat_a)
    pos_b = pos_b + noise * 0.01 * rng.normal(size=pos_b.shape)
    if quat_b is not None:
        quat_b = quat.multiply(quat.exp(noise * rng.normal(size=(n, 3))), quat_b)
        quat_b[::2] *= -1  # either sign of the measurement
    return pos_a, quat_a, pos_b, quat_b


def fd_phi(params, pos_a, quat_a, pos_b, quat_b, h=1e-6):
    P = params.spec.n_params
    cols = []
    for j in range(P):
        d = np.zeros(P)
        d[j] = h
        ep = output_error(params.stepped(d), pos_a, quat_a, pos_b, quat_b)
        em = output_error(params.stepped(-d), pos_a, quat_a, pos_b, quat_b)
        cols.append((ep - em) / (2 * h))
    return np.stack(cols, axis=-1)


def fd_input(params, pos_a, quat_a, pos_b, quat_b, h=1e-6):
    """∂e/∂(δp, δ) with q_A ← Exp(δ) ⊗ q_A, per pair: shape (n, m, 6)."""
    cols = []
    for j in range(6):
        d = np.zeros(6)
        d[j] = h

        def err(sign, d=d):
            pa = pos_a + sign * d[0:3]
            qa = quat.multiply(quat.exp(sign * d[3:6]), quat_a)
            return output_error(params, pa, qa, pos_b, quat_b)
        cols.append((err(1) - err(-1)) / (2 * h))
    return np.stack(cols, axis=-1)


# ---------------------------------------------------------------------------------------------
# Jacobians
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('chart', CHARTS)
def test_j_phi_matches_finite_differences_in_every_chart(model, chart):
    spec = SPECS[model]
    rng = np.random.default_rng(100 * MODELS.index(model) + CHARTS.index(chart))
    for _ in range(3):
        # q1 in a different chart from q0, so that both blocks visit every chart
        chart1 = ((chart[0] + 1) % 4, -chart[1])
        params = params_in_charts(spec, rng, chart, chart1)
        data = data_for(params, rng)
        e, j_phi, j_x = linearize(params, *data, with_input=False)
        assert j_x is None
        assert e.shape == (7, spec.n_res) and j_phi.shape == (7, spec.n_res, spec.n_params)
        np.testing.assert_allclose(e, output_error(params, *data), atol=1e-15)
        np.testing.assert_allclose(j_phi, fd_phi(params, *data), atol=2e-8)


@pytest.mark.parametrize('model', MODELS)
def test_j_x_matches_finite_differences(model):
    spec = SPECS[model]
    rng = np.random.default_rng(7 + len(model))
    for _ in range(8):
        params = params_in_charts(spec, rng)
        data = data_for(params, rng)
        e, j_phi, j_x = linearize(params, *data, with_input=True)
        assert j_x.shape == (7, spec.n_res, 6)
        np.testing.assert_allclose(j_x, fd_input(params, *data), atol=2e-8)
        _, j_phi2, _ = linearize(params, *data, with_input=False)
        np.testing.assert_array_equal(j_phi, j_phi2)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), model=st.sampled_from(MODELS),
       near=st.sampled_from(['identity', 'pi', 'generic']))
def test_jacobians_property_over_so3(seed, model, near):
    """φ and inputs over SO(3), with q0, q1 and q_A also near the identity and near 180°."""
    spec = SPECS[model]
    rng = np.random.default_rng(seed)
    params = params_in_charts(spec, rng)
    if near != 'generic':
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0, 1e-4) if near == 'identity' else np.pi - rng.uniform(0, 1e-4)
        q0 = quat.exp(angle * axis)
        q1 = quat.exp(angle * axis[::-1])
        params = Parameters.from_transforms(spec, params.p0, q0, params.markers, q1)
    pos_a, quat_a = rng.uniform(-0.5, 0.5, (4, 3)), random_quat(rng, 4)
    if near != 'generic':
        quat_a[0] = quat.exp(np.array([0.0, 0.0, np.pi - 1e-5]))
        quat_a[1] = [1.0, 0.0, 0.0, 0.0]
    data = data_for_inputs(params, rng, pos_a, quat_a)
    _, j_phi, j_x = linearize(params, *data, with_input=True)
    np.testing.assert_allclose(j_phi, fd_phi(params, *data), atol=5e-8)
    np.testing.assert_allclose(j_x, fd_input(params, *data), atol=5e-8)


def data_for_inputs(params, rng, pos_a, quat_a, noise=0.1):
    pos_b, quat_b = predict(params, pos_a, quat_a)
    if quat_b is not None:
        quat_b = quat.multiply(quat.exp(noise * rng.normal(size=(len(pos_a), 3))), quat_b)
    return pos_a, quat_a, pos_b, quat_b


def test_error_rotation_jacobian_matches_left_perturbation():
    rng = np.random.default_rng(3)
    q_model = random_quat(rng, 20)
    q_meas = quat.multiply(quat.exp(rng.normal(scale=0.7, size=(20, 3))), q_model)
    e, de_da = error_rotation_jacobian(q_model, q_meas)
    np.testing.assert_allclose(e, quat.rotation_error(q_model, q_meas)[0], atol=1e-15)
    h = 1e-6
    for i in range(3):
        a = np.zeros(3)
        a[i] = h
        fd = (error_rotation_jacobian(quat.multiply(quat.exp(a), q_model), q_meas)[0]
              - error_rotation_jacobian(quat.multiply(quat.exp(-a), q_model), q_meas)[0])
        np.testing.assert_allclose(de_da[:, :, i], fd / (2 * h), atol=1e-9)


@pytest.mark.parametrize('chart', CHARTS)
def test_tangent_of_chart(chart):
    """A chart step δs moves q to Exp(G δs) ⊗ q to first order."""
    k, sign = chart
    rng = np.random.default_rng(k + 10 * (sign > 0))
    h = 1e-6
    for _ in range(10):
        q = quaternion_in_chart(rng, k, sign)
        s = np.delete(q, k)
        q_s, dq = quat.expand(s, k, sign)
        G = tangent_of_chart(q_s, dq)
        for i in range(3):
            d = np.zeros(3)
            d[i] = h
            qp = quat.expand(s + d, k, sign)[0]
            qm = quat.expand(s - d, k, sign)[0]
            # log(q(s+h) ⊗ q(s)*) is the base-frame rotation that the step produced
            col = (quat.log(quat.multiply(qp, quat.conjugate(q_s)))
                   - quat.log(quat.multiply(qm, quat.conjugate(q_s)))) / (2 * h)
            np.testing.assert_allclose(G[:, i], col, atol=1e-8)
        # G is invertible in a well-chosen chart (|q_k| >= 1/2)
        assert np.linalg.cond(G) < 10


# ---------------------------------------------------------------------------------------------
# The model equation, independently
# ---------------------------------------------------------------------------------------------

def homogeneous(p, q):
    T = np.eye(4)
    T[:3, :3] = scipy_rotation(q).as_matrix()
    T[:3, 3] = p
    return T


@pytest.mark.parametrize('model', MODELS)
def test_predict_is_t0_ta_t1(model):
    spec = SPECS[model]
    rng = np.random.default_rng(11)
    for _ in range(5):
        params = params_in_charts(spec, rng)
        n = 6
        pos_a = rng.uniform(-1, 1, (n, 3))
        quat_a = random_quat(rng, n)
        pos_b, quat_b = predict(params, pos_a, quat_a)
        T0 = homogeneous(params.p0, params.q0)
        for i in range(n):
            TA = homogeneous(pos_a[i], quat_a[i])
            if spec.has_q1:
                TB = T0 @ TA @ homogeneous(params.markers[0], params.q1)
                np.testing.assert_allclose(pos_b[i], TB[:3, 3], atol=1e-12)
                np.testing.assert_allclose(quat.to_matrix(quat_b[i]), TB[:3, :3], atol=1e-12)
            else:
                assert quat_b is None
                want = np.stack([(T0 @ TA @ np.append(m, 1.0))[:3] for m in params.markers])
                got = pos_b[i] if pos_b.ndim == 3 else pos_b[i][None]
                np.testing.assert_allclose(got, want, atol=1e-12)
        expected_shape = (n, 3, 3) if model == 'three_marker' else (n, 3)
        assert pos_b.shape == expected_shape


@pytest.mark.parametrize('model', MODELS)
def test_output_error_is_zero_on_the_model_and_measures_offsets(model):
    spec = SPECS[model]
    rng = np.random.default_rng(12)
    params = params_in_charts(spec, rng)
    pos_a, quat_a = rng.uniform(-1, 1, (5, 3)), random_quat(rng, 5)
    pos_b, quat_b = predict(params, pos_a, quat_a)
    if quat_b is not None:
        quat_b = -quat_b  # the sign of a measured quaternion is irrelevant
    np.testing.assert_allclose(output_error(params, pos_a, quat_a, pos_b, quat_b), 0, atol=1e-12)
    # model minus measurement: a measurement displaced by +d gives error -d
    d = np.array([1e-3, -2e-3, 3e-3])
    e = output_error(params, pos_a, quat_a, pos_b + d, quat_b)
    np.testing.assert_allclose(e[:, 0:3], np.broadcast_to(-d, (5, 3)), atol=1e-12)
    if quat_b is not None:
        dth = np.array([2e-3, 0.0, -1e-3])
        e = output_error(params, pos_a, quat_a, pos_b, quat.multiply(quat.exp(dth), quat_b))
        np.testing.assert_allclose(e[:, 3:6], np.broadcast_to(-dth / 2, (5, 3)), atol=1e-9)


@pytest.mark.parametrize('model', MODELS)
def test_from_transforms_round_trip(model):
    spec = SPECS[model]
    rng = np.random.default_rng(13)
    for _ in range(20):
        p0, q0, q1 = rng.normal(size=3), random_quat(rng), random_quat(rng)
        markers = rng.normal(size=(spec.n_markers, 3))
        params = Parameters.from_transforms(spec, p0, q0, markers, q1)
        np.testing.assert_array_equal(params.p0, p0)
        np.testing.assert_array_equal(params.markers, markers)
        np.testing.assert_allclose(params.R0, scipy_rotation(q0)
                                   .as_matrix(), atol=1e-12)
        if spec.has_q1:
            np.testing.assert_allclose(quat.to_matrix(params.q1), quat.to_matrix(q1), atol=1e-12)
        for block, (k, _) in zip(spec.rotation_blocks, params.charts, strict=True):
            q = params.q0 if block == S0 else params.q1
            assert int(np.argmax(np.abs(q))) == k  # the chart of the largest component


# ---------------------------------------------------------------------------------------------
# Re-charting
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('model', MODELS)
def test_recharted_keeps_the_rotation(model):
    spec = SPECS[model]
    rng = np.random.default_rng(14)
    for _ in range(20):
        q0, q1 = random_quat(rng), random_quat(rng)
        # a poor chart: the second-largest component is the computed one
        k0 = int(np.argsort(np.abs(q0))[-2])
        k1 = int(np.argsort(np.abs(q1))[-2])
        phi = np.zeros(spec.n_params)
        phi[0:3] = rng.normal(size=3)
        phi[S0] = np.delete(q0, k0)
        for j in range(spec.n_markers):
            phi[spec.marker_slice(j)] = rng.normal(size=3)
        charts = [(k0, np.sign(q0[k0]))]
        if spec.has_q1:
            phi[S1] = np.delete(q1, k1)
            charts.append((k1, np.sign(q1[k1])))
        params = Parameters(spec, phi, charts)
        new = params.recharted()
        np.testing.assert_allclose(quat.to_matrix(new.q0), quat.to_matrix(params.q0), atol=1e-12)
        np.testing.assert_allclose(quat.to_matrix(new.q1), quat.to_matrix(params.q1), atol=1e-12)
        np.testing.assert_array_equal(new.p0, params.p0)
        np.testing.assert_array_equal(new.markers, params.markers)
        assert new.charts[0][0] == int(np.argmax(np.abs(q0)))
        if spec.has_q1:
            assert new.charts[1][0] == int(np.argmax(np.abs(q1)))
        for block, (k, sg) in zip(spec.rotation_blocks, new.charts, strict=True):
            assert not quat.needs_rechart(new.phi[block], k, sg)
        # the predictions are unchanged
        pos_a, quat_a = rng.normal(size=(3, 3)), random_quat(rng, 3)
        a, b = predict(params, pos_a, quat_a), predict(new, pos_a, quat_a)
        np.testing.assert_allclose(a[0], b[0], atol=1e-12)


def test_stepped_leaving_the_chart_is_invalid():
    spec = SPECS['full_pose']
    params = Parameters.from_transforms(spec, np.zeros(3), [1.0, 0, 0, 0], [[0.1, 0, 0]],
                                        [1.0, 0, 0, 0])
    assert params.valid
    step = np.zeros(12)
    step[S0] = [0.9, 0.9, 0.0]
    assert not params.stepped(step).valid
