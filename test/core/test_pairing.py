"""Tests of coreg_ros.core.calibration.pairing: the one pairing rule of the package."""


from concurrent.futures import ThreadPoolExecutor
import dataclasses

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration import pairing
from coreg_ros.core.calibration.pairing import (
    pair_streams,
    UNIT_QUATERNIONS,
    UNPAIRED_REASONS,
    validate_stream,
    VALIDATED,
    validated_streams,
)
from coreg_ros.core.errors import InputError
from coreg_ros.core.types import PoseStream
from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

MS = 1_000_000
T0 = 1_700_000_000 * 10**9 + 123  # realistic epoch stamps: too large for exact float64 seconds

OMEGA = np.array([0.3, -1.1, 0.7])  # rad/s, constant angular velocity of A
Q_START = quat.exp(np.array([0.4, 0.2, -2.5]))
VEL = np.array([0.05, -0.02, 0.11])  # m/s
P_START = np.array([0.3, -0.1, 0.8])


def truth(t_ns):
    """Pose of A at stamps t_ns: linear position, constant angular velocity rotation."""
    s = (np.asarray(t_ns, dtype=np.int64) - T0).astype(float) / 1e9
    pos = P_START + s[:, None] * VEL
    q = quat.canonical(quat.multiply(quat.exp(s[:, None] * OMEGA), Q_START))
    return pos, q


def stream(stamps, pos=None, q=None, frame='base'):
    stamps = np.asarray(stamps, dtype=np.int64)
    if pos is None:
        pos, q = truth(stamps)
    return PoseStream(stamps=stamps, position=np.asarray(pos, float),
                      quat_wxyz=np.asarray(q, float), frame_id=frame)


def assert_same_rotation(q0, q1, atol=1e-9):
    assert np.all(quat.angle_between(q0, q1) < atol) or np.allclose(
        quat.canonical(q0), quat.canonical(q1), atol=atol)


def test_linear_motion_is_recovered_exactly_between_samples():
    ta = T0 + np.arange(0, 2000, 10) * MS  # 100 Hz
    tb = T0 + 3 * MS + np.arange(0, 1900, 7) * MS  # 143 Hz, never on an A stamp
    pairs, report = pair_streams(stream(ta), stream(tb), max_gap_ns=10 * MS)
    pos_true, q_true = truth(tb)
    assert report.n_paired == len(tb)
    np.testing.assert_array_equal(pairs.stamps, tb)
    np.testing.assert_allclose(pairs.pos_a, pos_true, atol=1e-12)
    # Constant angular velocity: slerp between samples is exact.
    assert np.max(quat.angle_between(pairs.quat_a, q_true)) < 1e-7
    np.testing.assert_allclose(quat.canonical(pairs.quat_a), q_true, atol=1e-12)
    # B's own pose is passed through untouched.
    np.testing.assert_array_equal(pairs.pos_b, pos_true)
    assert pairs.quat_b.shape == (len(tb), 4)
    assert np.all(pairs.quat_a[:, 0] >= 0.0)


def test_slerp_matches_reference_and_variance_scale():
    rng = np.random.default_rng(7)
    n = 400
    q0 = quat.exp(rng.normal(size=(n, 3)))
    # Steps up to nearly 180 degrees and tiny ones, with random sign of the stored quaternion.
    angles = np.concatenate([rng.uniform(0, 3.1, n - 4), [0.0, 1e-9, 1e-5, 3.14]])
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    q1 = quat.multiply(q0, quat.exp(angles[:, None] * axes))
    q1 *= rng.choice([-1.0, 1.0], size=(n, 1))
    # One A stream: sample 2k at 100 ms * k, sample 2k+1 10 ms later; B at fraction alpha.
    ta = T0 + np.arange(2 * n) // 2 * 100 * MS + np.arange(2 * n) % 2 * 10 * MS
    qa = np.empty((2 * n, 4))
    qa[0::2], qa[1::2] = q0, q1
    alpha_ns = rng.integers(1, 10 * MS, n)
    tb = ta[0::2] + alpha_ns
    pos = np.zeros((2 * n, 3))
    pairs, report = pair_streams(stream(ta, pos, qa), stream(tb), max_gap_ns=10 * MS)
    assert report.n_paired == n
    alpha = alpha_ns / (10 * MS)
    expected = quat.multiply(q0, quat.exp((alpha * angles)[:, None] * axes))
    assert np.max(quat.angle_between(pairs.quat_a, expected)) < 1e-6
    np.testing.assert_allclose(pairs.quat_a, quat.slerp(q0, q1, alpha), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(pairs.quat_a, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(pairs.a_var_scale, alpha**2 + (1 - alpha) ** 2)


def test_exact_stamp_match_uses_that_sample_alone():
    ta = T0 + np.arange(10) * 10 * MS
    rng = np.random.default_rng(3)
    pos = rng.normal(size=(10, 3))
    qa = quat.exp(rng.normal(size=(10, 3)))
    tb = ta[[0, 4, 9]]  # first, middle and last A sample
    pairs, report = pair_streams(stream(ta, pos, qa), stream(tb), max_gap_ns=1)
    assert report.n_paired == 3
    np.testing.assert_array_equal(pairs.pos_a, pos[[0, 4, 9]])
    # Bit-exact: the validated (normalised) sample itself, not an interpolation of it.
    np.testing.assert_array_equal(pairs.quat_a, quat.validate_quaternions(qa)[[0, 4, 9]])
    np.testing.assert_array_equal(pairs.a_var_scale, 1.0)
    # Midpoint: variance of the average of two samples is half.
    pairs, _ = pair_streams(stream(ta, pos, qa), stream(ta[:1] + 5 * MS), max_gap_ns=5 * MS)
    np.testing.assert_allclose(pairs.a_var_scale, [0.5])
    np.testing.assert_allclose(pairs.pos_a, [(pos[0] + pos[1]) / 2])


def test_gap_rule_is_inclusive_and_per_side():
    ta = T0 + np.array([0, 10, 20, 120, 130]) * MS  # a 100 ms hole between 20 and 120
    tb = T0 + np.array([15, 30, 70, 110, 125]) * MS
    _, report = pair_streams(stream(ta), stream(tb), max_gap_ns=10 * MS)
    # 15 and 125 pair; 30 is 10 ms from A(20) but 90 ms from A(120); 110 likewise.
    assert report.n_paired == 2
    assert report.unpaired['gap_too_large'] == 3
    # Exactly max_gap on both sides pairs; one nanosecond more does not.
    ta = T0 + np.array([0, 20]) * MS
    ok, _ = pair_streams(stream(ta), stream([T0 + 10 * MS]), max_gap_ns=10 * MS)
    bad, rep = pair_streams(stream(ta), stream([T0 + 10 * MS]), max_gap_ns=10 * MS - 1)
    assert len(ok) == 1 and len(bad) == 0 and rep.unpaired['gap_too_large'] == 1
    # One side close is not enough.
    _, rep = pair_streams(stream(ta), stream([T0 + 1 * MS]), max_gap_ns=10 * MS)
    assert rep.unpaired['gap_too_large'] == 1


def test_offset_shifts_b_into_a_clock():
    tau = 37 * MS + 11  # B's clock minus A's clock
    ta = T0 + np.arange(0, 1000, 10) * MS
    t_true = T0 + 100 * MS + np.arange(0, 500, 13) * MS + 5
    pos_true, q_true = truth(t_true)
    b = stream(t_true + tau, pos_true, q_true)
    pairs, report = pair_streams(stream(ta), b, max_gap_ns=10 * MS, offset_ns=tau)
    assert report.n_paired == len(t_true)
    np.testing.assert_array_equal(pairs.stamps, t_true + tau)  # B's own stamps are kept
    np.testing.assert_allclose(pairs.pos_a, pairs.pos_b, atol=1e-12)
    assert np.max(quat.angle_between(pairs.quat_a, pairs.quat_b)) < 1e-7
    # Without the offset A is evaluated 37 ms late: a position error of |v| * tau.
    wrong, _ = pair_streams(stream(ta), b, max_gap_ns=10 * MS)
    err = np.linalg.norm(wrong.pos_a - wrong.pos_b, axis=1)
    np.testing.assert_allclose(err, np.linalg.norm(VEL) * tau / 1e9, rtol=1e-6)


def test_counts_by_reason_add_up():
    ta = T0 + np.arange(100, 200, 10) * MS
    tb = T0 + np.arange(0, 300, 4) * MS
    pairs, report = pair_streams(stream(ta), stream(tb), max_gap_ns=10 * MS)
    assert set(report.unpaired) == set(UNPAIRED_REASONS)
    assert report.unpaired['before_first_a'] == np.sum(tb < ta[0])
    assert report.unpaired['after_last_a'] == np.sum(tb > ta[-1])
    assert report.n_paired + sum(report.unpaired.values()) == report.n_b == len(tb)
    assert report.n_a == len(ta) and report.n_a_unused == 0
    assert 'pairs from' in report.summary()
    # A samples far from any B sample are counted as unused.
    ta = T0 + np.array([0, 10, 20, 500, 510, 1000]) * MS
    _, report = pair_streams(stream(ta), stream([T0 + 5 * MS]), max_gap_ns=10 * MS)
    assert report.n_paired == 1 and report.n_a_unused == 4


def test_position_only_ignores_b_orientation():
    ta = T0 + np.arange(0, 100, 10) * MS
    tb = T0 + np.arange(5, 90, 10) * MS
    pos, _ = truth(tb)
    # A 3-DOF tracker may fill the orientation with zeros or NaN: that must not matter.
    b = stream(tb, pos, np.full((len(tb), 4), np.nan))
    pairs, report = pair_streams(stream(ta), b, max_gap_ns=10 * MS, with_orientation_b=False)
    assert pairs.quat_b is None and report.n_paired == len(tb)
    with pytest.raises(InputError, match='stream_b quat_wxyz'):
        pair_streams(stream(ta), b, max_gap_ns=10 * MS)


def test_three_markers_interpolated_at_marker_one():
    ta = T0 + np.arange(0, 1000, 10) * MS
    t1 = T0 + np.arange(100, 800, 20) * MS + 3
    t2 = T0 + np.arange(90, 900, 10) * MS + 7
    t3 = T0 + np.arange(95, 900, 10) * MS
    offsets = [np.zeros(3), np.array([0.05, 0.0, 0.0]), np.array([0.0, 0.04, 0.01])]

    def marker(t, k):
        pos, _ = truth(t)
        return stream(t, pos + offsets[k], np.zeros((len(t), 4)))  # orientations unused

    # Marker 2 loses tracking between 400 and 500 ms.
    keep2 = (t2 < T0 + 400 * MS) | (t2 > T0 + 500 * MS)
    m1, m2, m3 = marker(t1, 0), marker(t2[keep2], 1), marker(t3, 2)
    pairs, report = pair_streams(stream(ta), [m1, m2, m3], max_gap_ns=10 * MS)
    assert pairs.pos_b.shape == (report.n_paired, 3, 3) and pairs.quat_b is None
    expected_missing = [t for t in t1 if not (
        np.any(np.abs(t2[keep2] - t) <= 10 * MS) and
        np.any((t2[keep2] <= t) & (t - t2[keep2] <= 10 * MS)) and
        np.any((t2[keep2] >= t) & (t2[keep2] - t <= 10 * MS)))]
    assert report.unpaired['marker_missing'] == len(expected_missing) > 0
    assert report.n_paired + sum(report.unpaired.values()) == len(t1)
    pos1, _ = truth(pairs.stamps)
    for k in range(3):
        np.testing.assert_allclose(pairs.pos_b[:, k], pos1 + offsets[k], atol=1e-12)
    np.testing.assert_allclose(pairs.pos_a, pos1, atol=1e-12)


@pytest.mark.parametrize('stamps, pattern', [
    ([0, 10, 10, 20], r'duplicate stamp .* at index 2'),
    ([0, 10, 20, 15, 30], r'backwards at index 3 by 5000000 ns \(5\.000 ms\)'),
])
def test_bad_stamp_order_is_refused(stamps, pattern):
    s = stream(T0 + np.asarray(stamps) * MS)
    with pytest.raises(InputError, match=pattern):
        validate_stream(s, 'stream_a')
    with pytest.raises(InputError, match='stream_b'):
        pair_streams(stream(T0 + np.arange(5) * MS), s, max_gap_ns=MS)


def test_bad_values_are_refused_with_index():
    t = T0 + np.arange(6) * MS
    pos, q = truth(t)
    nan_pos = pos.copy()
    nan_pos[4, 1] = np.nan
    with pytest.raises(InputError, match=r'stream_a: position contains NaN or inf at index 4'):
        pair_streams(stream(t, nan_pos, q), stream(t), max_gap_ns=MS)
    for bad, pattern in [(np.nan, 'NaN or inf'), (0.0, 'not unit length'),
                         (0.5, 'not unit length')]:
        bad_q = q.copy()
        bad_q[3] = bad if bad != 0.5 else q[3] * 0.5
        with pytest.raises(InputError, match=rf'stream_a quat_wxyz.*{pattern}.*index 3'):
            validate_stream(stream(t, pos, bad_q), 'stream_a')
    with pytest.raises(InputError, match='empty'):
        validate_stream(stream(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 4))), 'a')
    with pytest.raises(InputError, match='integer nanoseconds'):
        validate_stream(PoseStream(t / 1e9, pos, q), 'a')
    with pytest.raises(InputError, match=r'shape \(6, 3\)'):
        validate_stream(PoseStream(t, pos[:5], q), 'a')


@pytest.mark.parametrize('in_thread', [True, False])
@pytest.mark.parametrize('bad_a', [True, False])
@pytest.mark.parametrize('bad_b', [True, False])
def test_validated_streams_names_a_first_then_b(monkeypatch, bad_a, bad_b, in_thread):
    """A checked in a second thread or not: its error is the one told when both are bad."""
    monkeypatch.setattr(pairing, 'VALIDATE_IN_THREAD', 1 if in_thread else 10**9)
    started = []
    monkeypatch.setattr(pairing, 'ThreadPoolExecutor', lambda *a, **k: started.append(1) or
                        ThreadPoolExecutor(*a, **k))
    t = T0 + np.arange(6) * MS
    pos, q = truth(t)
    nan_pos = pos.copy()
    nan_pos[4, 1] = np.nan
    a = stream(t, nan_pos if bad_a else pos, q)
    b = stream(t[::-1] if bad_b else t)
    if not (bad_a or bad_b):
        va, (vb,) = validated_streams(a, [b], True)
        assert np.array_equal(va.position, pos) and np.array_equal(vb.stamps, t)
        assert bool(started) == in_thread
        return
    with pytest.raises(InputError, match='stream_a' if bad_a else 'stream_b'):
        validated_streams(a, [b], True)
    assert bool(started) == in_thread


def test_bad_arguments_are_refused():
    s = stream(T0 + np.arange(5) * MS)
    with pytest.raises(InputError, match='max_gap_ns must be >= 0'):
        pair_streams(s, s, max_gap_ns=-1)
    with pytest.raises(InputError, match='max_gap_ns must be an integer'):
        pair_streams(s, s, max_gap_ns=0.01)
    with pytest.raises(InputError, match='offset_ns must be an integer'):
        pair_streams(s, s, max_gap_ns=MS, offset_ns=0.5)
    with pytest.raises(InputError, match='three marker streams, got 2'):
        pair_streams(s, [s, s], max_gap_ns=MS)


def test_validate_normalises_and_keeps_inputs_untouched():
    t = T0 + np.arange(4) * MS
    pos, q = truth(t)
    q_in = -q * 1.004  # wrong sign and slightly off unit: accepted and normalised
    s = stream(t, pos, q_in)
    out = validate_stream(s, 'a')
    np.testing.assert_allclose(out.quat_wxyz, q, atol=1e-12)
    assert out.stamps.dtype == np.int64
    np.testing.assert_array_equal(s.quat_wxyz, -q * 1.004)  # the input is not modified
    pair_streams(s, s, max_gap_ns=MS)
    np.testing.assert_array_equal(s.quat_wxyz, -q * 1.004)


def test_growing_buffer_gives_the_same_pairs():
    # The live node re-pairs its whole buffer: pairs found early must not change later.
    rng = np.random.default_rng(11)
    ta = T0 + np.cumsum(rng.integers(5 * MS, 15 * MS, 300))
    tb = T0 + np.cumsum(rng.integers(3 * MS, 12 * MS, 400))
    full, _ = pair_streams(stream(ta), stream(tb), max_gap_ns=12 * MS)
    for cut in (50, 150, 299):
        a_part = stream(ta[:cut])
        b_part = stream(tb[tb <= ta[cut - 1]])
        part, _ = pair_streams(a_part, b_part, max_gap_ns=12 * MS)
        n = len(part)
        np.testing.assert_array_equal(part.stamps, full.stamps[:n])
        np.testing.assert_array_equal(part.pos_a, full.pos_a[:n])
        np.testing.assert_array_equal(part.quat_a, full.quat_a[:n])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), gap_ms=st.integers(0, 30),
       offset=st.integers(-50 * MS, 50 * MS))
def test_pairing_is_deterministic_and_one_to_one(seed, gap_ms, offset):
    rng = np.random.default_rng(seed)
    ta = T0 + np.cumsum(rng.integers(1, 40 * MS, rng.integers(1, 80)))
    tb = T0 + np.cumsum(rng.integers(1, 40 * MS, rng.integers(1, 80)))
    if rng.random() < 0.3:  # force some exact matches
        tb = np.unique(np.concatenate([tb, ta[rng.integers(0, len(ta), 5)] + offset]))
    a, b = stream(ta), stream(tb)
    gap = gap_ms * MS
    p1, r1 = pair_streams(a, b, max_gap_ns=gap, offset_ns=offset)
    p2, r2 = pair_streams(a, b, max_gap_ns=gap, offset_ns=offset)
    assert r1 == r2
    for f in ('stamps', 'pos_a', 'quat_a', 'pos_b', 'quat_b', 'a_var_scale'):
        np.testing.assert_array_equal(getattr(p1, f), getattr(p2, f))
    # One-to-one: every pair is a distinct B sample.
    assert np.all(np.diff(p1.stamps) > 0) and np.all(np.isin(p1.stamps, tb))
    assert r1.n_paired + sum(r1.unpaired.values()) == len(tb)
    # Every pair obeys the gap rule, checked by brute force.
    for t in p1.stamps - offset:
        if np.any(ta == t):
            continue
        lo, hi = ta[ta < t].max(), ta[ta > t].min()
        assert t - lo <= gap and hi - t <= gap
    # Every unpaired B sample really had no admissible bracket.
    unpaired = np.setdiff1d(tb, p1.stamps) - offset
    for t in unpaired:
        assert not np.any(ta == t)
        below, above = ta[ta < t], ta[ta > t]
        assert below.size == 0 or above.size == 0 or t - below.max() > gap or \
            above.min() - t > gap
    assert np.all((p1.a_var_scale >= 0.5) & (p1.a_var_scale <= 1.0))


def test_a_million_samples_pair():
    # A vectorised path at scale; speed goals belong in bench/, not in unit tests.
    n = 1_000_000
    rng = np.random.default_rng(5)
    ta = T0 + np.cumsum(rng.integers(9 * MS, 11 * MS, n))
    tb = T0 + 4 * MS + np.cumsum(rng.integers(9 * MS, 11 * MS, n))
    q = quat.exp(rng.normal(size=(n, 3)))
    a = PoseStream(ta, rng.normal(size=(n, 3)), q)
    b = PoseStream(tb, rng.normal(size=(n, 3)), q)
    pairs, report = pair_streams(a, b, max_gap_ns=20 * MS)
    assert report.n_paired > 0.99 * n


def test_a_validated_stream_is_checked_once():
    rng = np.random.default_rng(4)
    q = rng.normal(size=(50, 4))
    raw = PoseStream(np.arange(50, dtype=np.int64) * 10**6, rng.normal(size=(50, 3)),
                     q / np.linalg.norm(q, axis=1, keepdims=True) * (1 + 1e-9))
    once = validate_stream(raw, 'stream_a')
    assert once is not raw and validate_stream(once, 'stream_a') is once
    assert np.all(once.quat_wxyz[:, 0] >= 0)
    # checked without its orientation: asked with it, the quaternions are checked then
    positions = validate_stream(raw, 'stream_b', orientation=False)
    assert validate_stream(positions, 'stream_b', orientation=False) is positions
    full = validate_stream(positions, 'stream_b')
    assert full is not positions and np.array_equal(full.quat_wxyz, once.quat_wxyz)
    # the mark is no field (equality, copies and the fingerprint do not see it)
    assert all(f.name != VALIDATED for f in dataclasses.fields(once))


def test_pairs_come_with_unit_quaternions_that_calibrate_takes_as_they_are():
    """
    The pairing's quaternions are unit and canonical (slerps normalised), and marked so.

    ``calibrate`` then uses them without normalising a copy: the same fit as of the same
    pairs given unmarked (normalised by ``calibrate``), to rounding.
    """
    from coreg_ros.core.calibration.calibrate import calibrate
    from coreg_ros.core.settings import Settings
    from coreg_ros.core.types import Pairs
    from coreg_ros.sim import simulate_recording

    rec = simulate_recording(11, 60.0, 'full_pose', rate_a=100.0, rate_b=37.0)
    a, b = rec.streams[rec.topics_a], rec.streams[rec.topics_b[0]]
    pairs, _ = pair_streams(a, b, max_gap_ns=50_000_000, offset_ns=1_234_567)
    assert getattr(pairs, UNIT_QUATERNIONS) is True
    assert all(f.name != UNIT_QUATERNIONS for f in dataclasses.fields(pairs))
    for q in (pairs.quat_a, pairs.quat_b):
        assert np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)) <= 4e-16
        assert np.all(q[:, 0] >= 0.0)
    # raw slerps are unit to a few ulps only: their normalised rows are what the fit sees
    plain = Pairs(*(np.array(getattr(pairs, f.name)) for f in dataclasses.fields(pairs)))
    settings = Settings(estimate_time_offset=False)
    marked, unmarked = calibrate(pairs, settings), calibrate(plain, settings)
    sigma = np.sqrt(np.diag(unmarked.param_cov))
    assert np.max(np.abs(marked.params - unmarked.params) / sigma) < 1e-9
    assert abs(marked.chi2 - unmarked.chi2) <= 1e-9 * unmarked.chi2
