"""Tests of the seeded simulator (coreg_ros.sim)."""

from dataclasses import replace
import json

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.types import PoseStream
from coreg_ros.sim import (
    make_motion,
    MOTION_PRESETS,
    random_rotation,
    random_truth,
    simulate_pairs,
    simulate_recording,
    Truth,
)
import numpy as np
import pytest
from scipy import stats

MODELS = ('full_pose', 'position_only', 'three_marker')
ZERO = (0.0, 0.0)


def _seconds(stamps, start_ns):
    return (stamps - np.int64(start_ns)).astype(float) * 1e-9


def _assert_same_quat(q, r, atol=1e-12):
    """Equal up to sign."""
    d = np.minimum(np.abs(q - r).max(axis=-1), np.abs(q + r).max(axis=-1))
    assert d.max() < atol


def _recording_bytes(rec):
    out = []
    for topic in sorted(rec.streams):
        s = rec.streams[topic]
        out += [topic, s.stamps.tobytes(), s.position.tobytes(), s.quat_wxyz.tobytes(), s.frame_id]
    return out


# ---------------------------------------------------------------- determinism


@pytest.mark.parametrize('model', MODELS)
def test_same_seed_is_bit_identical(model):
    a = simulate_recording(7, 5.0, model)
    b = simulate_recording(7, 5.0, model)
    assert _recording_bytes(a) == _recording_bytes(b)
    assert json.dumps(a.truth.as_dict()) == json.dumps(b.truth.as_dict())
    assert json.dumps(a.motion.as_dict()) == json.dumps(b.motion.as_dict())


def test_different_seeds_differ():
    a = simulate_recording(1, 5.0)
    b = simulate_recording(2, 5.0)
    assert not np.allclose(a.truth.p0, b.truth.p0)
    assert a.stream_a.stamps[0] != b.stream_a.stamps[0]
    assert not np.allclose(a.stream_a.position[:10], b.stream_a.position[:10])


def test_pairs_deterministic_for_generator_state():
    x = simulate_pairs(np.random.default_rng(3), 500, sigma_a=(1e-3, 1e-3), sigma_b=(1e-3, 1e-3))
    y = simulate_pairs(np.random.default_rng(3), 500, sigma_a=(1e-3, 1e-3), sigma_b=(1e-3, 1e-3))
    for p, q in zip(x[:2], y[:2], strict=True):
        assert p.pos_a.tobytes() == q.pos_a.tobytes()
        assert p.quat_b.tobytes() == q.quat_b.tobytes()
    assert x[0].pos_b.tobytes() != simulate_pairs(np.random.default_rng(4), 500)[0].pos_b.tobytes()


def test_fixed_truth_does_not_change_noise_or_stamps():
    truth = random_truth(np.random.default_rng(99), 'full_pose')
    a = simulate_recording(5, 3.0, truth=truth)
    b = simulate_recording(5, 3.0)
    assert np.array_equal(a.stream_a.stamps, b.stream_a.stamps)
    assert np.array_equal(a.stream_a.position, b.stream_a.position)
    assert np.array_equal(a.truth.p0, truth.p0)
    assert a.truth.sigma_b == (0.0005, 0.002)


# ---------------------------------------------------------------- stamps and streams


@pytest.mark.parametrize('model', MODELS)
def test_stamps_rates_topics_frames(model):
    duration = 20.0
    rec = simulate_recording(11, duration, model, rate_a=100.0, rate_b=50.0)
    start = rec.start_ns
    a = rec.stream_a
    assert rec.topics_a == '/device_a/pose'
    if model == 'three_marker':
        assert rec.topics_b == ('/device_b/marker1/pose', '/device_b/marker2/pose',
                                '/device_b/marker3/pose')
    else:
        assert rec.topics_b == ('/device_b/pose',)
    assert set(rec.streams) == {rec.topics_a, *rec.topics_b}
    assert a.frame_id == 'device_a_base'
    for s, rate in [(a, 100.0)] + [(b, 50.0) for b in rec.streams_b]:
        assert isinstance(s, PoseStream)
        assert s.stamps.dtype == np.int64
        d = np.diff(s.stamps)
        assert (d > 0).all()
        assert np.abs(d - 1e9 / rate).max() <= 1
        assert abs(len(s) - duration * rate) <= 1
        assert s.stamps[0] >= start and s.stamps[-1] < start + int(duration * 1e9)
        assert s.position.shape == (len(s), 3) and s.quat_wxyz.shape == (len(s), 4)
        assert (s.quat_wxyz[:, 0] >= 0).all()
        np.testing.assert_allclose(np.linalg.norm(s.quat_wxyz, axis=1), 1.0, atol=1e-12)
    for b in rec.streams_b:
        assert b.frame_id == 'device_b_base'
        assert np.array_equal(b.stamps, rec.streams_b[0].stamps)
    # unsynchronised: A's and B's phases differ
    assert (a.stamps[0] - start) % 10_000_000 != (rec.streams_b[0].stamps[0] - start) % 10_000_000


def test_phases_vary_with_seed():
    phases = {int(simulate_recording(s, 1.0).streams_b[0].stamps[0] % 20_000_000)
              for s in range(10)}
    assert len(phases) == 10


# ---------------------------------------------------------------- model equation


@pytest.mark.parametrize('model', MODELS)
def test_noiseless_recording_satisfies_model_at_b_stamps(model):
    rec = simulate_recording(3, 10.0, model, sigma_a=ZERO, sigma_b=ZERO)
    tr = rec.truth
    a = rec.stream_a
    p_a, q_a = rec.motion.pose(_seconds(a.stamps, rec.start_ns))
    assert np.array_equal(a.position, p_a) and np.array_equal(a.quat_wxyz, q_a)

    t_b = _seconds(rec.streams_b[0].stamps, rec.start_ns)
    p_a, q_a = rec.motion.pose(t_b)       # A's true pose at B's own stamps
    r0, ra = quat.to_matrix(tr.q0), quat.to_matrix(q_a)
    for j, b in enumerate(rec.streams_b):
        expected = tr.p0 + (r0 @ (p_a + np.einsum('nij,j->ni', ra, tr.markers[j])).T).T
        np.testing.assert_allclose(b.position, expected, rtol=0, atol=1e-12)
    b = rec.streams_b[0]
    if model == 'full_pose':
        _assert_same_quat(b.quat_wxyz, quat.multiply(quat.multiply(tr.q0, q_a), tr.q1))
    else:
        assert np.array_equal(b.quat_wxyz, np.tile([1.0, 0, 0, 0], (len(b), 1)))


@pytest.mark.parametrize('model', MODELS)
def test_pairs_shapes_and_model(model):
    rng = np.random.default_rng(8)
    noisy, clean, tr = simulate_pairs(rng, 300, model, sigma_a=(1e-3, 1e-3),
                                      sigma_b=(1e-3, 1e-3))
    assert tr.model == model and len(noisy) == len(clean) == 300
    assert noisy.stamps.dtype == np.int64 and (np.diff(noisy.stamps) > 0).all()
    # default span: max(60 s, n / 100 s)
    assert noisy.stamps[-1] - noisy.stamps[0] == pytest.approx(60e9 * 299 / 300, abs=1)
    k = 3 if model == 'three_marker' else 1
    r0, ra = quat.to_matrix(tr.q0), quat.to_matrix(clean.quat_a)
    expected = tr.p0 + np.einsum(
        'ij,nkj->nki', r0, clean.pos_a[:, None] + np.einsum('nij,kj->nki', ra, tr.markers))
    if model == 'three_marker':
        assert noisy.pos_b.shape == (300, 3, 3) and noisy.quat_b is None
        np.testing.assert_allclose(clean.pos_b, expected, atol=1e-12)
    else:
        assert noisy.pos_b.shape == (300, 3)
        np.testing.assert_allclose(clean.pos_b, expected[:, 0], atol=1e-12)
    assert tr.markers.shape == (k, 3)
    if model == 'full_pose':
        _assert_same_quat(clean.quat_b,
                          quat.multiply(quat.multiply(tr.q0, clean.quat_a), tr.q1))
        assert (noisy.quat_b[:, 0] >= 0).all()
    else:
        assert noisy.quat_b is None and clean.quat_b is None
    assert not np.array_equal(noisy.pos_b, clean.pos_b)


def test_zero_sigma_means_no_noise():
    noisy, clean, _ = simulate_pairs(np.random.default_rng(1), 200, sigma_a=ZERO,
                                     sigma_b=(1e-3, 0.0))
    assert np.array_equal(noisy.pos_a, clean.pos_a)
    assert np.array_equal(noisy.quat_a, clean.quat_a)
    assert np.array_equal(noisy.quat_b, clean.quat_b)
    assert not np.array_equal(noisy.pos_b, clean.pos_b)


def test_pairs_accept_truth_duration_and_motion():
    truth = random_truth(np.random.default_rng(2), 'position_only')
    motion = make_motion(np.random.default_rng(2), 'no_rotation')
    noisy, clean, tr = simulate_pairs(np.random.default_rng(0), 100, 'position_only',
                                      truth=truth, motion=motion, duration=10.0)
    assert np.array_equal(tr.p0, truth.p0)
    assert noisy.stamps[-1] - noisy.stamps[0] == 10_000_000_000 * 99 // 100
    _assert_same_quat(clean.quat_a, np.broadcast_to(motion.q_mean, clean.quat_a.shape))


# ---------------------------------------------------------------- noise


def _rotation_noise(q_meas, q_true):
    """δθ of q_meas = Exp(δθ) ⊗ q_true, in the base frame."""
    return quat.log(quat.multiply(q_meas, quat.conjugate(q_true)))


def test_empirical_noise_matches_sigma():
    sigma_a, sigma_b = (0.0002, 0.0005), (0.0005, 0.002)
    noisy, clean, _ = simulate_pairs(np.random.default_rng(2024), 20_000, sigma_a=sigma_a,
                                     sigma_b=sigma_b)
    checks = [
        (noisy.pos_a - clean.pos_a, sigma_a[0]),
        (_rotation_noise(noisy.quat_a, clean.quat_a), sigma_a[1]),
        (noisy.pos_b - clean.pos_b, sigma_b[0]),
        (_rotation_noise(noisy.quat_b, clean.quat_b), sigma_b[1]),
    ]
    # std of a sample std from 20k draws is 0.5 %: 3 % is six standard errors
    for err, sigma in checks:
        np.testing.assert_allclose(err.std(axis=0), sigma, rtol=0.03)
        np.testing.assert_allclose(err.mean(axis=0), 0.0, atol=4 * sigma / np.sqrt(20_000))
        assert abs(np.corrcoef(err.T)[np.triu_indices(3, 1)]).max() < 0.03
    # A's and B's noise are independent
    c = np.corrcoef(checks[0][0][:, 0], checks[2][0][:, 0])[0, 1]
    assert abs(c) < 0.03


def test_recording_noise_matches_sigma():
    rec = simulate_recording(12, 200.0, 'three_marker', sigma_b=(0.001, 0.0))
    clean = simulate_recording(12, 200.0, 'three_marker', sigma_a=ZERO, sigma_b=ZERO)
    a, a0 = rec.stream_a, clean.stream_a
    assert len(a) == 20_000
    np.testing.assert_allclose((a.position - a0.position).std(axis=0), 2e-4, rtol=0.03)
    np.testing.assert_allclose(_rotation_noise(a.quat_wxyz, a0.quat_wxyz).std(axis=0), 5e-4,
                               rtol=0.03)
    pairs = zip(rec.streams_b, clean.streams_b, strict=True)
    errs = [b.position - b0.position for b, b0 in pairs]
    for e in errs:
        np.testing.assert_allclose(e.std(axis=0), 1e-3, rtol=0.04)
    assert abs(np.corrcoef(errs[0][:, 0], errs[1][:, 0])[0, 1]) < 0.05


# ---------------------------------------------------------------- motion


def _relative_rotvecs(q):
    return quat.log(quat.multiply(quat.conjugate(q[0]), q))


def _principal_stds(v):
    return np.sqrt(np.clip(np.sort(np.linalg.eigvalsh(np.cov(v.T)))[::-1], 0.0, None))


@pytest.mark.parametrize('seed', range(5))
def test_diverse_rotation_spans_three_axes(seed):
    m = make_motion(np.random.default_rng(seed), 'diverse')
    _, q = m.pose(np.arange(0.0, 120.0, 0.05))
    s = _principal_stds(_relative_rotvecs(q))
    assert s[2] > 0.15          # rad: every axis moves substantially
    assert s[2] / s[0] > 0.2
    assert quat.angle_between(q[:, None], q[None, ::40]).max() > 1.0


@pytest.mark.parametrize('seed', range(5))
def test_single_axis_rotation_has_one_axis(seed):
    m = make_motion(np.random.default_rng(seed), 'single_axis')
    p, q = m.pose(np.arange(0.0, 120.0, 0.05))
    s = _principal_stds(_relative_rotvecs(q))
    assert s[0] > 0.2 and s[1] < 1e-6 and s[2] < 1e-6
    assert _principal_stds(p)[2] > 0.02       # translation still free


def test_no_rotation_and_static():
    t = np.arange(0.0, 60.0, 0.1)
    p, q = make_motion(np.random.default_rng(0), 'no_rotation').pose(t)
    assert np.ptp(q, axis=0).max() == 0.0 and _principal_stds(p)[2] > 0.02
    p, q = make_motion(np.random.default_rng(0), 'static').pose(t)
    assert np.ptp(q, axis=0).max() == 0.0 and np.ptp(p, axis=0).max() == 0.0


def test_presets_and_unknown_preset():
    assert MOTION_PRESETS == ('diverse', 'scara', 'planar', 'gantry', 'turntable',
                              'single_axis', 'no_rotation', 'static')
    with pytest.raises(ConfigError, match='preset'):
        make_motion(np.random.default_rng(0), 'wobble')


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_restricted_rigs_move_as_their_machines_do(seed):
    """SCARA, mobile robot, gantry, turntable: what each rig's tool can and cannot do."""
    t = np.linspace(0.0, 120.0, 2000)

    def moved(preset):
        m = make_motion(np.random.default_rng(seed), preset)
        pos, q = m.pose(t)
        # rotation vectors of the tool relative to its mean orientation, in A's base frame
        rot = quat.log(quat.multiply(q, quat.conjugate(m.q_mean)))
        return m, pos, rot

    for preset in ('scara', 'planar', 'turntable'):
        m, pos, rot = moved(preset)
        assert np.abs(rot[:, :2]).max() < 1e-12 and rot[:, 2].std() > 0.3  # yaw only
        if preset == 'scara':
            assert (pos.std(axis=0) > 0.02).all()
        if preset == 'planar':
            assert np.ptp(pos[:, 2]) < 1e-12 and (pos[:, :2].std(axis=0) > 0.02).all()
        if preset == 'turntable':  # on a circle about a vertical axis through the pivot
            lever = pos - m.pivot
            assert np.ptp(np.linalg.norm(lever[:, :2], axis=1)) < 1e-12
            assert np.ptp(lever[:, 2]) < 1e-12 and 0.2 <= np.linalg.norm(lever[0, :2]) <= 0.4
    m, pos, rot = moved('gantry')
    assert np.abs(rot).max() < 1e-12 and (pos.std(axis=0) > 0.02).all()
    # the shared draws: every preset keeps the centre and mean orientation of the seed
    diverse = make_motion(np.random.default_rng(seed))
    assert np.array_equal(m.centre, diverse.centre) and np.array_equal(m.q_mean, diverse.q_mean)


def test_diverse_motion_ranges():
    m = make_motion(np.random.default_rng(4))
    assert np.all((m.pos_freq >= 0.05) & (m.pos_freq <= 0.3))
    assert np.all((m.rot_freq >= 0.03) & (m.rot_freq <= 0.2))
    assert np.all((m.pos_amp.sum(axis=1) >= 0.1 - 1e-12) & (m.pos_amp.sum(axis=1) <= 0.15 + 1e-12))
    assert np.all((m.rot_amp.sum(axis=1) >= 0.6 - 1e-12) & (m.rot_amp.sum(axis=1) <= 0.9 + 1e-12))
    assert m.pos_amp.shape[1] in (2, 3) and m.rot_amp.shape[1] in (2, 3)


def test_linear_interpolation_at_100_hz_is_far_below_noise():
    for seed in range(5):
        m = make_motion(np.random.default_rng(seed))
        t = np.arange(0.0, 120.0, 0.01)
        p, q = m.pose(t)
        pm, qm = m.pose(t[:-1] + 0.005)
        lin_p = 0.5 * (p[:-1] + p[1:])
        lin_q = quat.slerp(q[:-1], q[1:], np.full(len(t) - 1, 0.5))
        assert np.abs(lin_p - pm).max() < 0.1 * 0.0002
        assert quat.angle_between(lin_q, qm).max() < 0.1 * 0.0005


def test_motion_is_continuous_in_time():
    m = make_motion(np.random.default_rng(1))
    p0, q0 = m.pose([10.0])
    p1, q1 = m.pose([10.0 + 1e-6])
    assert np.abs(p1 - p0).max() < 1e-6 and quat.angle_between(q0, q1)[0] < 1e-5


# ---------------------------------------------------------------- truth


def test_random_rotation_is_uniform_over_so3():
    q = random_rotation(np.random.default_rng(0), 20_000)
    assert q.shape == (20_000, 4) and (q[:, 0] >= 0).all()
    # |w| of a Haar-uniform rotation has CDF (2/π)(w √(1-w²) + arcsin w) on [0, 1]
    cdf = lambda w: (2 / np.pi) * (w * np.sqrt(1 - w * w) + np.arcsin(w))  # noqa: E731
    assert stats.kstest(q[:, 0], cdf).pvalue > 0.01
    angle = 2 * np.arccos(np.clip(q[:, 0], 0, 1))
    # P(angle > 170°) ≈ 0.111 for uniform rotations: near-180° rotations are drawn
    assert 0.10 < np.mean(angle > np.deg2rad(170)) < 0.12
    # the axis is isotropic
    np.testing.assert_allclose(np.mean(q[:, 1:] ** 2, axis=0), 0.25, atol=0.01)


def test_random_truth_covers_so3_and_ranges():
    rng = np.random.default_rng(5)
    truths = [random_truth(rng, 'full_pose') for _ in range(3000)]
    w0 = np.array([t.q0[0] for t in truths])
    w1 = np.array([t.q1[0] for t in truths])
    cdf = lambda w: (2 / np.pi) * (w * np.sqrt(1 - w * w) + np.arcsin(w))  # noqa: E731
    assert stats.kstest(w0, cdf).pvalue > 0.01 and stats.kstest(w1, cdf).pvalue > 0.01
    assert w0.min() < 0.02                 # rotations within a few degrees of 180°
    p0 = np.array([t.p0 for t in truths])
    assert np.abs(p0).max() <= 1.0 and np.abs(p0).max() > 0.99
    n1 = np.array([np.linalg.norm(t.p1) for t in truths])
    assert n1.min() >= 0.05 and n1.max() <= 0.2
    assert all(np.array_equal(t.markers, t.p1[None]) for t in truths[:10])


def test_three_markers_non_collinear_and_spaced():
    rng = np.random.default_rng(6)
    for _ in range(300):
        tr = random_truth(rng, 'three_marker')
        m = tr.markers
        assert m.shape == (3, 3) and np.array_equal(m[0], tr.p1)
        d = [np.linalg.norm(m[i] - m[j]) for i, j in ((0, 1), (0, 2), (1, 2))]
        assert min(d) >= 0.05 - 1e-12 and max(d) <= 0.15 + 1e-12
        area = 0.5 * np.linalg.norm(np.cross(m[1] - m[0], m[2] - m[0]))
        assert area / max(d) ** 2 > 0.14         # far from collinear: every angle >= 30°
        assert np.linalg.matrix_rank(np.stack([m[1] - m[0], m[2] - m[0]]), tol=1e-3) == 2


def test_truth_as_dict_round_trip():
    tr = random_truth(np.random.default_rng(1), 'three_marker', sigma_a=(1e-4, 2e-4),
                      sigma_b=(3e-4, 0.0))
    d = json.loads(json.dumps(tr.as_dict()))
    assert set(d) >= {'base_to_base', 'tool_to_marker', 'markers', 'model', 'sigma_a', 'sigma_b'}
    assert set(d['base_to_base']['orientation']) == {'w', 'x', 'y', 'z'}
    assert d['model'] == 'three_marker' and len(d['markers']) == 3
    back = Truth.from_dict(d)
    assert np.array_equal(back.q0, tr.q0) and np.array_equal(back.markers, tr.markers)
    assert back.sigma_a == (1e-4, 2e-4)


def test_truth_is_frozen_and_validated():
    tr = random_truth(np.random.default_rng(1))
    with pytest.raises(ValueError):
        tr.p0[0] = 1.0
    with pytest.raises(ConfigError, match='markers'):
        replace(tr, model='three_marker')
    with pytest.raises(ConfigError, match='model'):
        simulate_recording(0, 1.0, 'three_marker', truth=tr)


@pytest.mark.parametrize('kwargs', [
    {'duration': 0.0}, {'model': 'six_dof'}, {'rate_a': -1.0}, {'sigma_b': (-1.0, 0.0)},
    {'sigma_a': (1.0,)}, {'motion': 3},
])
def test_bad_arguments_raise_config_error(kwargs):
    args = {'duration': 1.0, **kwargs}
    with pytest.raises(ConfigError):
        simulate_recording(0, **args)


# ---------------------------------------------------------------- effects hook


class _Shift:
    """A stand-in effect: B stamped tau late (not a real implementation)."""

    def __init__(self, tau_ns):
        self.tau_ns = tau_ns
        self.calls = 0

    def __call__(self, streams, context, rng):
        self.calls += 1
        assert context.topics_b == ('/device_b/pose',)
        assert set(context.true_streams) == set(streams)
        rng.standard_normal(10)
        out = dict(streams)
        for t in context.topics_b:
            out[t] = replace(streams[t], stamps=streams[t].stamps + self.tau_ns)
        return out

    def as_dict(self):
        return {'name': 'shift', 'tau_ns': self.tau_ns}


def test_effects_hook_applies_in_order_and_records():
    base = simulate_recording(9, 2.0)
    e1, e2 = _Shift(5), _Shift(7)
    rec = simulate_recording(9, 2.0, effects=[e1, e2])
    assert e1.calls == e2.calls == 1
    assert np.array_equal(rec.streams_b[0].stamps, base.streams_b[0].stamps + 12)
    assert np.array_equal(rec.streams_b[0].position, base.streams_b[0].position)
    assert np.array_equal(rec.stream_a.position, base.stream_a.position)
    assert rec.truth.effects == ({'name': 'shift', 'tau_ns': 5}, {'name': 'shift', 'tau_ns': 7})
    assert rec.truth.as_dict()['effects'][1]['tau_ns'] == 7
    assert base.truth.effects == ()
