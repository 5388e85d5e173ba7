"""
Tests of coreg_ros.core.live.fusion.

The fused covariance against the spread of a seeded Monte Carlo (calibration error, A's and B's
noise all drawn), the position-only branch, and incremental pairing against pair_streams on the
whole streams.

Monte Carlo tolerance: with N = 20 000 trials the mean NEES of a 6-dimensional error has a
standard deviation of sqrt(12 / N) = 0.024 (0.4 % of 6); NEES within 5 % of 6 and 95 %
ellipsoid coverage within 93-97 % fail only for a real mismatch.
"""

from dataclasses import replace

from coreg_ros.core import quaternion as quat
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.pairing import pair_streams
from coreg_ros.core.live.fusion import (
    fused_stream,
    FusionCalibration,
    pending_pairs,
)
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import Pairs, PoseStream
from coreg_ros.sim import random_rotation, simulate_pairs, simulate_recording
import numpy as np
import pytest
from scipy import stats

N_MC = 20_000
#: Hoff & Vincent's complementary devices (docs/hoff_experiment.md).
SIGMA_A = (1.0e-4, 2.0e-3)
SIGMA_B = (2.0e-3, 8.0e-4)


def _calibration(model, seed=3, n=300):
    rng = np.random.default_rng(seed)
    pairs, _, _ = simulate_pairs(rng, n, model, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result = calibrate(pairs, Settings(model=model, sigma_a=SIGMA_A, sigma_b=SIGMA_B))
    assert result.success
    return result


def _draw(rng, cov, n):
    """δ ~ N(0, cov) on the known components (unknown ones, negative diagonal, stay 0)."""
    known = np.diag(cov) >= 0
    d = np.zeros((n, cov.shape[0]))
    sub = cov[np.ix_(known, known)]
    d[:, known] = rng.multivariate_normal(np.zeros(sub.shape[0]), sub, size=n)
    return d


def _perturb(p, q, d):
    return p + d[..., 0:3], quat.canonical(quat.multiply(quat.exp(d[..., 3:6]), q))


def _compose(p1, q1, p2, q2):
    return (p1 + np.einsum('...ij,...j->...i', quat.to_matrix(q1), p2),
            quat.canonical(quat.multiply(q1, q2)))


def _monte_carlo(result, seed, n=N_MC):
    """
    Truths around the estimated calibration, noisy A and B: (pairs, true marker pose).

    Given the estimate, the true (T0, T1) ~ N(estimate, cov_joint) to first order; A's tool
    poses are uniform over SO(3) and a 0.3 m cube, A's noise scaled by a random interpolation
    factor α² + (1 - α)².
    """
    rng = np.random.default_rng(seed)
    t0, t1 = result.base_to_base, result.tool_to_marker
    d = _draw(rng, np.asarray(result.cov_joint), n)
    p0, q0 = _perturb(t0.position, t0.quat_wxyz, d[:, 0:6])
    p1, q1 = _perturb(t1.position, t1.quat_wxyz, d[:, 6:12])
    pa_true = rng.uniform(-0.3, 0.3, size=(n, 3))
    qa_true = random_rotation(rng, n)
    alpha = rng.uniform(0.0, 1.0, n)
    scale = alpha ** 2 + (1.0 - alpha) ** 2
    noise_a = _draw(rng, np.diag([SIGMA_A[0] ** 2] * 3 + [SIGMA_A[1] ** 2] * 3), n)
    pa, qa = _perturb(pa_true, qa_true, noise_a * np.sqrt(scale)[:, None])
    pm, qm = _compose(*_compose(p0, q0, pa_true, qa_true), p1, q1)
    noise_b = _draw(rng, np.diag([SIGMA_B[0] ** 2] * 3 + [SIGMA_B[1] ** 2] * 3), n)
    pb, qb = _perturb(pm, qm, noise_b)
    pairs = Pairs(stamps=np.arange(n, dtype=np.int64), pos_a=pa, quat_a=qa, pos_b=pb,
                  quat_b=qb, a_var_scale=scale)
    return pairs, pm, qm


def _consistent(err, cov, dim):
    e = unc.nees(err, cov)
    mean, coverage = float(np.mean(e)), float(np.mean(e <= stats.chi2.ppf(0.95, dim)))
    print(f'fused d={dim}: NEES {mean:.3f}, 95 % coverage {coverage:.4f}')
    assert abs(mean - dim) <= 0.05 * dim, f'NEES {mean:.3f} vs {dim}'
    assert 0.93 <= coverage <= 0.97, f'coverage {coverage:.4f}'


def test_full_pose_fused_covariance_matches_monte_carlo_spread():
    result = _calibration('full_pose')
    pairs, pm, qm = _monte_carlo(result, seed=11)
    fused = fused_stream(result, pairs, SIGMA_A, SIGMA_B)
    assert fused.orientation_fused and len(fused) == N_MC
    err = unc.pose_error(pm, qm, fused.position, fused.quat_wxyz)
    _consistent(err, fused.covariance, 6)
    # the spread per axis matches the predicted σ (RMS over the trials, 3 %)
    rms = np.sqrt(np.mean(err ** 2, axis=0))
    pred = np.sqrt(np.mean(np.diagonal(fused.covariance, axis1=1, axis2=2), axis=0))
    np.testing.assert_allclose(rms, pred, rtol=0.03)
    # better than B alone on every axis, and than A through the calibration
    p_a, q_a, c_a = unc.through_calibration_arrays(result, pairs.pos_a, pairs.quat_a,
                                                   np.diag([SIGMA_A[0] ** 2] * 3
                                                           + [SIGMA_A[1] ** 2] * 3))
    sig_a = np.sqrt(np.mean(np.diagonal(c_a, axis1=1, axis2=2), axis=0))
    sig_b = np.array([SIGMA_B[0]] * 3 + [SIGMA_B[1]] * 3)
    assert (pred < sig_b).all() and (pred < sig_a).all()
    print('σ fused', pred, 'A through calibration', sig_a, 'B', sig_b)


def test_ignoring_the_calibration_or_the_cross_terms_is_detected():
    # The same check with the calibration's covariance dropped fails: the test has teeth.
    result = _calibration('full_pose', n=40)
    pairs, pm, qm = _monte_carlo(result, seed=12)
    exact = replace(result, cov_joint=np.zeros((12, 12)))
    fused = fused_stream(exact, pairs, SIGMA_A, SIGMA_B)
    e = unc.nees(unc.pose_error(pm, qm, fused.position, fused.quat_wxyz), fused.covariance)
    assert np.mean(e) > 6.3
    # from_poses without cov_joint keeps the marginals (cross terms zero): still usable
    calib = FusionCalibration.from_poses(result.base_to_base, result.tool_to_marker,
                                         'full_pose')
    np.testing.assert_array_equal(calib.cov_joint[0:6, 0:6], result.cov_joint[0:6, 0:6])
    assert not calib.cov_joint[0:6, 6:12].any()


@pytest.mark.parametrize('model', ['position_only', 'three_marker'])
def test_position_only_models_fuse_positions(model):
    result = _calibration(model)
    pairs, pm, qm = _monte_carlo(result, seed=13)
    if model == 'three_marker':  # markers 2, 3 are ignored by the fusion: any values do
        pairs = replace(pairs, pos_b=np.stack([pairs.pos_b] * 3, axis=1))
    pairs = replace(pairs, quat_b=None)
    fused = fused_stream(result, pairs, SIGMA_A, SIGMA_B)
    assert not fused.orientation_fused
    assert (np.diagonal(fused.covariance, axis1=1, axis2=2)[:, 3:6] == -1.0).all()
    assert not fused.covariance[:, 0:3, 3:6].any()
    _consistent(fused.position - pm, fused.covariance[:, 0:3, 0:3], 3)


def _arrivals(streams, latency_ns):
    """All samples in arrival order, each topic delayed by its latency: (time, topic, index)."""
    events = [(int(s.stamps[i]) + latency_ns[t], t, i) for t, s in streams.items()
              for i in range(len(s))]
    return sorted(events)


def _window(stream, n, k):
    """Return the newest k of the first n samples (a buffer tail) as a PoseStream."""
    lo = max(0, n - k)
    return PoseStream(stamps=stream.stamps[lo:n], position=stream.position[lo:n],
                      quat_wxyz=stream.quat_wxyz[lo:n], frame_id=stream.frame_id)


@pytest.mark.parametrize('model,offset_ns', [('full_pose', 0), ('full_pose', 7_000_000),
                                             ('three_marker', 0)])
def test_incremental_pairing_equals_pair_streams(model, offset_ns):
    rec = simulate_recording(4, 3.0, model, rate_a=100.0, rate_b=60.0)
    a, bs = rec.topics_a, list(rec.topics_b)
    settings = Settings(model=model)
    full, _ = pair_streams(rec.streams[a], [rec.streams[t] for t in bs],
                           max_gap_ns=settings.max_gap_ns, offset_ns=offset_ns,
                           with_orientation_b=model == 'full_pose')
    count = dict.fromkeys(rec.streams, 0)
    cursor, got = None, []
    rng = np.random.default_rng(0)
    # A arrives 25 ms after its stamp, B 2 ms after (so B often waits for A), markers 9 ms
    latency = dict.fromkeys(bs, 9000000) | {a: 25_000_000, bs[0]: 2_000_000}
    events = _arrivals(rec.streams, latency)
    for j, (_, topic, _) in enumerate(events):
        count[topic] += 1
        if rng.random() > 0.1 and j != len(events) - 1:  # a tick now and then
            continue
        pairs, cursor = pending_pairs(
            _window(rec.streams[a], count[a], 64), [_window(rec.streams[t], count[t], 64)
                                                    for t in bs],
            cursor, max_gap_ns=settings.max_gap_ns, offset_ns=offset_ns,
            with_orientation_b=model == 'full_pose')
        got.append(pairs)
    stamps = np.concatenate([p.stamps for p in got])
    # every B sample at most once, and all the pairs of the whole streams but those whose
    # next A sample never came
    assert (np.diff(stamps) > 0).all()
    np.testing.assert_array_equal(stamps, full.stamps)
    np.testing.assert_allclose(np.concatenate([p.pos_a for p in got]), full.pos_a, atol=1e-15)
    np.testing.assert_allclose(np.concatenate([p.pos_b for p in got]), full.pos_b)
    np.testing.assert_allclose(np.concatenate([p.a_var_scale for p in got]), full.a_var_scale)


def test_pending_pairs_waits_for_a_and_restarts_after_a_reset():
    rec = simulate_recording(5, 1.0)
    a, b = rec.streams[rec.topics_a], rec.streams[rec.topics_b[0]]
    gap = Settings().max_gap_ns
    # A stops half-way: B samples after A's newest wait, they are not dropped
    half = len(a) // 2
    a_half = _window(a, half, 10_000)
    pairs, cursor = pending_pairs(a_half, b, None, max_gap_ns=gap)
    assert cursor <= a.stamps[half - 1] and len(pairs) > 0
    rest, cursor2 = pending_pairs(a, b, cursor, max_gap_ns=gap)
    assert rest.stamps[0] > cursor and cursor2 > cursor
    # nothing new: nothing again
    again, cursor3 = pending_pairs(a, b, cursor2, max_gap_ns=gap)
    assert len(again) == 0 and cursor3 == cursor2
    # a reset (stamps restart earlier): the cursor is forgotten
    early = replace(b, stamps=b.stamps - 10**10)
    early_a = replace(a, stamps=a.stamps - 10**10)
    fresh, _ = pending_pairs(early_a, early, cursor2, max_gap_ns=gap)
    assert len(fresh) > 0
    # empty windows
    empty = _window(a, 0, 10)
    none, c = pending_pairs(empty, b, 5, max_gap_ns=gap)
    assert len(none) == 0 and c == 5
