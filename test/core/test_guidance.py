"""Guidance while collecting: σ now (against the calibration's own), the best next motion."""

from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import CoregError, InputError
from coreg_ros.core.live.guidance import (
    batch_from_pairs,
    candidate_motions,
    Estimate,
    GROUPS,
    GuidanceAccumulator,
    information,
    KEY_NEXT,
    KEY_READY,
    KEY_SIGMA_PREFIX,
    KEY_SUMMARY,
    PairFeed,
)
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import Pairs
from coreg_ros.sim import add_pose_noise, simulate_recording
import numpy as np
import pytest

# the noise of the sample recording bags/sample_full_pose
SIGMA_A = (2e-4, 5e-4)
SIGMA_B = (5e-4, 2e-3)


def _chunks(pairs: Pairs, size: int):
    for k in range(0, len(pairs), size):
        sl = slice(k, k + size)
        yield Pairs(pairs.stamps[sl], pairs.pos_a[sl], pairs.quat_a[sl], pairs.pos_b[sl],
                    None if pairs.quat_b is None else pairs.quat_b[sl],
                    None if pairs.a_var_scale is None else pairs.a_var_scale[sl])


def _streamed(model, pairs, with_time, targets=(1e-4, 1e-3), chunk=250):
    """Guidance fed as the node would: batches, a closed-form estimate from the first ones."""
    acc = GuidanceAccumulator(model, SIGMA_A, SIGMA_B, *targets,
                              estimate_time_offset=with_time)
    feed = PairFeed()
    for part in _chunks(pairs, chunk):
        batch = feed.push(part)
        if batch is not None and acc.estimate is None and len(batch) > 50:
            acc.set_estimate(Estimate.from_pairs(model, batch))
        acc.add(batch)
    acc.add(feed.push(None, final=True))
    return acc


@pytest.mark.parametrize('model', ['full_pose', 'position_only', 'three_marker'])
def test_sigma_agrees_with_the_calibration(model):
    rec = simulate_recording(21, 40.0, model, rate_a=100.0, rate_b=50.0, sigma_a=SIGMA_A,
                             sigma_b=SIGMA_B)
    settings = Settings(model=model, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result, _ = calibrate_streams(rec.stream_a, rec.streams_b, settings)
    assert result.success and result.time_offset.estimated
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings, result.time_offset)
    acc = _streamed(model, pairs, with_time=True)
    assert acc.n_pairs == len(pairs)
    # the node then learns the calibration's estimate (re-linearising only if it moved)
    acc.set_estimate(Estimate.from_result(result))
    got = acc.guidance()
    joint = np.sqrt(np.abs(np.diag(result.cov_joint)))  # -1: not estimated
    for i, name in enumerate(GROUPS[model][:4 if model == 'full_pose' else 3]):
        ratio = got.sigma[name] / joint[3 * i:3 * i + 3]
        assert np.all(np.abs(ratio - 1.0) < 0.10), (name, ratio)
    ratio_tau = got.sigma['time_offset'][0] / result.time_offset.sigma_s
    assert abs(ratio_tau - 1.0) < 0.10, ratio_tau


def test_fixed_offset_sigma_agrees_with_calibrate_on_pairs():
    rec = simulate_recording(22, 30.0, rate_a=100.0, rate_b=50.0, sigma_a=SIGMA_A,
                             sigma_b=SIGMA_B)
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B, estimate_time_offset=False)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings)
    result = calibrate(pairs, settings)
    acc = _streamed('full_pose', pairs, with_time=False)
    acc.set_estimate(Estimate.from_result(result), force=True)
    got = acc.guidance()
    joint = np.sqrt(np.diag(result.cov_joint))
    sigma = np.concatenate([got.sigma[n] for n in GROUPS['full_pose']])
    assert np.allclose(sigma, joint, rtol=0.02)
    assert 'time_offset' not in got.sigma


def test_incremental_sum_equals_the_batch_sum():
    rec = simulate_recording(23, 20.0, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B, estimate_time_offset=False)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings)
    truth = rec.truth
    est = Estimate('full_pose', truth.p0, truth.q0, truth.markers, truth.q1)
    whole = batch_from_pairs(pairs)
    acc = GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 1e-4, 1e-3)
    acc.set_estimate(est)
    feed = PairFeed()
    for part in _chunks(pairs, 97):
        acc.add(feed.push(part))
    acc.add(feed.push(None, final=True))
    cov_a, cov_b = acc.cov_a, acc.cov_b
    direct = information(est, whole.pos_a, whole.quat_a, whole.velocity, cov_a, cov_b,
                         whole.a_var_scale)
    assert np.allclose(acc.info, direct, rtol=1e-9, atol=1e-9 * np.abs(direct).max())


def test_pair_feed_releases_every_pair_once_with_interior_velocities_as_in_batch():
    rec = simulate_recording(24, 10.0, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    settings = Settings(estimate_time_offset=False)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings)
    whole = batch_from_pairs(pairs)
    feed = PairFeed()
    parts = []
    # overlapping re-pairing (the node re-pairs a span of its buffers): duplicates ignored
    for k in range(0, len(pairs), 40):
        sl = slice(max(0, k - 20), k + 40)
        parts.append(feed.push(Pairs(pairs.stamps[sl], pairs.pos_a[sl], pairs.quat_a[sl],
                                     pairs.pos_b[sl], pairs.quat_b[sl])))
    parts.append(feed.push(None, final=True))
    got = [p for p in parts if p is not None]
    stamps = np.concatenate([p.stamps for p in got])
    assert np.array_equal(stamps, pairs.stamps)
    vel = np.concatenate([p.velocity for p in got])
    interior = slice(10, -10)
    assert np.allclose(vel[interior], whole.velocity[interior], atol=1e-12)


def test_no_velocity_across_a_tracking_gap():
    rec = simulate_recording(28, 10.0, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, Settings(estimate_time_offset=False))
    t = (pairs.stamps - pairs.stamps[0]) * 1e-9
    keep = (t < 4.0) | (t > 5.0)  # the tracker lost the marker for a second
    cut = Pairs(pairs.stamps[keep], pairs.pos_a[keep], pairs.quat_a[keep], pairs.pos_b[keep],
                pairs.quat_b[keep], pairs.a_var_scale[keep])
    got = batch_from_pairs(cut, max_gap=0.05)
    tc = t[keep]
    near = (np.abs(tc - 4.0) < 0.03) | (np.abs(tc - 5.0) < 0.03)
    assert near.any() and np.all(got.velocity[near] == 0.0)
    far = (np.abs(tc - 4.5) > 0.7) & (tc > 0.2) & (tc < 9.8)
    assert np.all(np.linalg.norm(got.velocity[far], axis=1) > 0.0)
    assert np.allclose(got.velocity[far], batch_from_pairs(cut).velocity[far])


def test_relinearising_from_the_decimated_store_keeps_the_sigma():
    rec = simulate_recording(25, 60.0, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B, estimate_time_offset=False)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings)
    truth = rec.truth
    est = Estimate('full_pose', truth.p0, truth.q0, truth.markers, truth.q1)
    acc = GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 1e-4, 1e-3, max_stored=500)
    acc.add(batch_from_pairs(pairs))  # before any estimate: kept, not yet summed
    assert acc._n_store <= 500 and acc._stride > 1
    acc.set_estimate(est)
    sparse = acc.guidance().sigma
    full = GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 1e-4, 1e-3)
    full.set_estimate(est)
    full.add(batch_from_pairs(pairs))
    dense = full.guidance().sigma
    for name in dense:
        assert np.allclose(sparse[name], dense[name], rtol=0.10), name


def _calibrated_worst(pairs, settings, truth, cand, targets, rng):
    """Worst σ / target the calibration reports with the candidate motion really recorded."""
    pb, qb = truth.device_b(cand.pos_a, cand.quat_a)
    pa_n, qa_n = add_pose_noise(rng, cand.pos_a, cand.quat_a, SIGMA_A)
    pb_n, qb_n = add_pose_noise(rng, pb[:, 0], qb, SIGMA_B)
    n = len(cand.pos_a)
    stamps = pairs.stamps[-1] + 20_000_000 * (1 + np.arange(n))
    both = Pairs(np.concatenate([pairs.stamps, stamps]), np.concatenate([pairs.pos_a, pa_n]),
                 np.concatenate([pairs.quat_a, qa_n]), np.concatenate([pairs.pos_b, pb_n]),
                 np.concatenate([pairs.quat_b, qb_n]),
                 np.concatenate([pairs.a_var_scale, np.ones(n)]))
    try:
        result = calibrate(both, settings)
    except CoregError:  # still unobservable
        return np.inf
    sd = np.sqrt(np.diag(result.cov_joint))
    pos, rot = targets
    return float(np.max(np.concatenate([sd[0:3] / pos, sd[3:6] / rot, sd[6:9] / pos,
                                        sd[9:12] / rot])))


@pytest.mark.parametrize('seed', [1, 2, 3])
def test_suggested_motion_reduces_the_worst_sigma_most(seed):
    # the user rotated about one axis only: the hand-eye problem is not yet determined
    rec = simulate_recording(seed, 20.0, rate_a=100.0, rate_b=50.0, sigma_a=SIGMA_A,
                             sigma_b=SIGMA_B, motion='single_axis')
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B, estimate_time_offset=False)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings)
    targets = (1e-4, np.radians(0.05))
    acc = _streamed('full_pose', pairs, with_time=False, targets=targets)
    got = acc.guidance()
    assert not got.ready and not got.determined
    best = got.suggestion
    assert best is not None and best.name.startswith('rotate_')
    assert best.name in got.summary or best.description in got.summary
    rng = np.random.default_rng(100 + seed)
    achieved = {c.name: _calibrated_worst(pairs, settings, rec.truth, c, targets, rng)
                for c in candidate_motions(*acc.last_pose, acc.rate(), samples=10 ** 6)}
    assert np.isfinite(achieved[best.name])
    others = [v for k, v in achieved.items() if k != best.name]
    assert achieved[best.name] <= min(others), achieved


def test_ready_when_the_targets_are_met_and_the_diagnostics_keys():
    rec = simulate_recording(26, 30.0, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings)
    loose = _streamed('full_pose', pairs, with_time=True, targets=(1e-3, 1e-2)).guidance()
    assert loose.ready and loose.suggestion is None
    assert loose.summary.startswith('ready')
    tight = _streamed('full_pose', pairs, with_time=True, targets=(1e-6, 1e-6)).guidance()
    assert not tight.ready and tight.worst_ratio > 1
    values = dict(tight.diagnostic_values())
    assert values[KEY_READY] == 'false'
    assert values[KEY_NEXT] == tight.suggestion.name
    assert values[KEY_SUMMARY] == tight.summary
    sd = [float(v) for v in values[KEY_SIGMA_PREFIX + 'p0'].split()]
    assert np.allclose(sd, tight.sigma['p0'], rtol=1e-5)
    assert len(values[KEY_SIGMA_PREFIX + 'time_offset'].split()) == 1
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in tight.diagnostic_values())


def test_update_cost_at_two_kilohertz_streams_is_small():
    import time
    rec = simulate_recording(27, 10.0, rate_a=1000.0, rate_b=1000.0, sigma_a=SIGMA_A,
                             sigma_b=SIGMA_B)
    settings = Settings(estimate_time_offset=False)
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings)
    acc = _streamed('full_pose', pairs, with_time=True, chunk=1000)
    one_second = list(_chunks(pairs, 1000))[3]
    feed = PairFeed()
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        acc.add(feed.push(one_second, final=True))
        acc.guidance()
        best = min(best, time.perf_counter() - t)
        feed = PairFeed()
    assert best < 0.2  # one update per second of 1 kHz pairs: well under a fifth of a core


def test_errors():
    with pytest.raises(InputError):
        GuidanceAccumulator('nope', SIGMA_A, SIGMA_B, 1e-4, 1e-3)
    with pytest.raises(InputError):
        GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 0.0, 1e-3)
    with pytest.raises(InputError, match='estimate'):
        GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 1e-4, 1e-3).guidance()


def _scara_guidance(duration, limits):
    rec = simulate_recording(26, duration, sigma_a=SIGMA_A, sigma_b=SIGMA_B, motion='scara')
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B))
    acc = GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 1e-3, 1e-2,
                              estimate_time_offset=True, motion_limits=limits)
    feed = PairFeed()
    for part in _chunks(pairs, 250):
        batch = feed.push(part)
        if batch is not None and acc.estimate is None and len(batch) > 50:
            acc.set_estimate(Estimate.from_pairs('full_pose', batch))
        acc.add(batch)
    acc.add(feed.push(None, final=True))
    return acc.guidance()


def test_a_restricted_rig_is_ready_on_what_it_can_show_and_never_asked_for_more():
    """
    Issue 22: a SCARA arm (yaw only). Free: not ready, asked to turn about another axis.

    Restricted: ready once the determined part meets the targets, the lever along the yaw
    axis held and said, and no candidate that would determine it offered; auto: free for the
    first ``AUTO_RESTRICTED_S`` of recording, restricted after.
    """
    free = _scara_guidance(90.0, 'free')
    assert not free.ready and not free.determined and not free.held
    asked = free.options[0].name
    held = _scara_guidance(90.0, 'restricted')
    assert held.ready and held.determined and len(held.held) == 1
    assert "T1's position along" in held.held[0] and 'held' in held.summary
    names = {o.name for o in held.options}
    assert asked not in names and names < {o.name for o in free.options}
    early, late = _scara_guidance(30.0, 'auto'), _scara_guidance(90.0, 'auto')
    assert not early.ready and not early.held
    assert late.ready and late.held == held.held
    with pytest.raises(InputError, match='motion_limits'):
        GuidanceAccumulator('full_pose', SIGMA_A, SIGMA_B, 1e-3, 1e-2, motion_limits='scara')
