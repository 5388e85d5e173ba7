"""
Spatiotemporal, robust calibration (issue 10).

The clock offset estimated with the transforms, outliers rejected, priors, and the fit verdict.
Statistical claims by Monte Carlo, fixed seeds.
"""

from dataclasses import replace

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import InconsistentDataError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import PoseStream, UncertainPose
from coreg_ros.core.uncertainty import pose_error
from coreg_ros.sim import parse_effect, simulate_recording
import numpy as np
import pytest
from strategies import with_outliers


def _streams(rec):
    return rec.streams[rec.topics_a], [rec.streams[t] for t in rec.topics_b]


def _shift(stream: PoseStream, seconds: float) -> PoseStream:
    return replace(stream, stamps=stream.stamps + np.int64(round(seconds * 1e9)))


def _pose_errors(result, truth) -> np.ndarray:
    """(T0, T1) errors in the ROS layout (12,), truth minus estimate."""
    e0 = pose_error(truth.p0, truth.q0, result.base_to_base.position,
                    result.base_to_base.quat_wxyz)
    e1 = pose_error(truth.markers[0], truth.q1, result.tool_to_marker.position,
                    result.tool_to_marker.quat_wxyz)
    return np.concatenate([e0, e1])


@pytest.mark.parametrize('seed, tau', [(11, -0.5), (12, 0.0), (13, 0.012), (14, 2.5),
                                       (15, 130.0)])
def test_offset_recovered_from_no_guess(seed, tau):
    rec = simulate_recording(seed, 30.0, 'full_pose')
    a, bs = _streams(rec)
    result, _ = calibrate_streams(a, [_shift(bs[0], tau)], Settings())
    t = result.time_offset
    assert result.success and t.estimated
    assert abs(t.value_s - tau) < 3 * t.sigma_s + 1e-6, (t.value_s, t.sigma_s)
    err = _pose_errors(result, rec.truth)
    cov = result.cov_joint
    nees = float(err @ np.linalg.solve(cov, err))
    assert nees < 40.0  # χ²_12 beyond 40 has p < 1e-4


@pytest.mark.parametrize('model', ['position_only', 'three_marker'])
def test_offset_other_models(model):
    rec = simulate_recording(21, 40.0, model, effects=[parse_effect('time_offset=-0.03')])
    a, bs = _streams(rec)
    result, _ = calibrate_streams(a, bs, Settings(model=model))
    t = result.time_offset
    assert t.estimated and abs(t.value_s + 0.03) < 3 * t.sigma_s + 1e-6


def test_clock_drift_recovered():
    ppm = 400.0
    rec = simulate_recording(31, 60.0, 'full_pose', effects=[parse_effect(f'clock_drift={ppm}')])
    a, bs = _streams(rec)
    result, _ = calibrate_streams(a, bs, Settings(estimate_clock_drift=True))
    t = result.time_offset
    assert abs(t.drift_ppm - ppm) < 3 * t.drift_sigma_ppm, (t.drift_ppm, t.drift_sigma_ppm)
    # τ at the reference stamp: the drift accumulated since the first B stamp
    start = int(min(s.stamps[0] for s in rec.streams.values()))
    expected = ppm * 1e-6 * (t.reference_ns - start) * 1e-9
    assert abs(t.value_s - expected) < 3 * t.sigma_s + 2e-5


def _still_poses_recording(seed: int, n_poses: int = 40, hold_s: float = 1.0):
    """Stop-and-go: A and B sampled only while the tool rests at random poses."""
    from coreg_ros.sim import random_truth
    rng = np.random.default_rng(seed)
    truth = random_truth(rng, 'full_pose')
    r0 = quat.to_matrix(truth.q0)
    stamps_a, pa, qa, stamps_b, pb, qb = [], [], [], [], [], []
    t = 10**18
    for _ in range(n_poses):
        q = quat.canonical(quat.exp(rng.normal(size=3) * 0.6))
        p = rng.uniform(-0.2, 0.2, size=3)
        qm = quat.multiply(truth.q0, quat.multiply(q, truth.q1))
        pm = truth.p0 + r0 @ (p + quat.to_matrix(q) @ truth.markers[0])
        for k in range(int(hold_s * 100)):
            stamps_a.append(t + k * 10_000_000)
            pa.append(p + rng.normal(scale=2e-4, size=3))
            qa.append(quat.multiply(quat.exp(rng.normal(scale=5e-4, size=3)), q))
        for k in range(int(hold_s * 50)):
            stamps_b.append(t + 3_000_000 + k * 20_000_000)
            pb.append(pm + rng.normal(scale=5e-4, size=3))
            qb.append(quat.multiply(quat.exp(rng.normal(scale=2e-3, size=3)), qm))
        t += int((hold_s + 2.0) * 1e9)  # the move between poses is not recorded
    a = PoseStream(np.array(stamps_a, dtype=np.int64), np.array(pa), np.array(qa))
    b = PoseStream(np.array(stamps_b, dtype=np.int64), np.array(pb), np.array(qb))
    return a, b


def test_still_recording_keeps_the_given_offset():
    a, b = _still_poses_recording(41)
    result, _ = calibrate_streams(a, b, Settings(time_offset=0.004))
    t = result.time_offset
    assert not t.estimated
    assert t.value_s == 0.004
    assert 'not estimated' in t.message and 'still' in t.message
    assert result.success


def test_constant_velocity_offset_not_invented():
    # A gantry (translation only, no rotation): the transforms are estimated with T1's position
    # held (issue 22), and τ either stays at the given value (when the motion cannot show it)
    # or is estimated honestly: the truth, 0, within 3 σ. Never a made-up offset.
    rec = simulate_recording(42, 30.0, 'full_pose', motion='no_rotation')
    a, bs = _streams(rec)
    result, _ = calibrate_streams(a, bs, Settings(time_offset=0.0))
    assert len(result.held) == 3
    t = result.time_offset
    if t.estimated:
        assert abs(t.value_s) < 3.0 * t.sigma_s and t.sigma_s < 1e-3


@pytest.mark.slow
def test_outliers_keep_the_error_and_clean_data_keep_their_pairs():
    rng = np.random.default_rng(5)
    clean_err, dirty_err = {0.0: [], 0.01: [], 0.2: [], 'burst': []}, []
    rejected = total = 0
    for trial in range(12):
        rec = simulate_recording(100 + trial, 20.0, 'full_pose')
        a, bs = _streams(rec)
        clean, _ = calibrate_streams(a, bs, Settings())
        rejected += clean.n_rejected
        total += clean.n_pairs
        clean_err[0.0].append(_pose_errors(clean, rec.truth)[:3])
        for share in (0.01, 0.2, 'burst'):
            b = with_outliers(bs[0], 0.1 if share == 'burst' else share, rng,
                              burst=share == 'burst')
            dirty, _ = calibrate_streams(a, [b], Settings())
            clean_err[share].append(_pose_errors(dirty, rec.truth)[:3])
    assert rejected / total < 1e-3
    ref = np.sqrt(np.mean(np.square(clean_err[0.0])))
    for share in (0.01, 0.2, 'burst'):
        rms = np.sqrt(np.mean(np.square(clean_err[share])))
        assert rms < 1.2 * ref * (1.0 / np.sqrt(0.8) if share == 0.2 else 1.0) + 1e-12, \
            (share, rms, ref)
    del dirty_err


def test_too_many_outliers_are_refused():
    rec = simulate_recording(7, 20.0, 'full_pose')
    a, bs = _streams(rec)
    b = with_outliers(bs[0], 0.45, np.random.default_rng(1))
    with pytest.raises(InconsistentDataError, match='not the model plus a few outliers') as e:
        calibrate_streams(a, [b], Settings(sigma_a=(3e-4, 6e-4)))
    # the refusal names the noise it judged the pairs by
    assert 'stated: sigma_a 0.0003 m, 0.0006 rad, sigma_b 0.0005 m, 0.002 rad' in str(e.value)


def test_clock_step_is_refused_with_where():
    rec = simulate_recording(8, 40.0, 'full_pose')
    a, bs = _streams(rec)
    b = bs[0]
    half = len(b) // 2
    stamps = b.stamps.copy()
    stamps[half:] += np.int64(2_000_000_000)  # B's clock jumps 2 s forward halfway
    with pytest.raises(InconsistentDataError, match=r'changes from -?0\.0\d+ s to 2\.0\d+ s .* '
                       r'\(a clock step\): split the recording'):
        calibrate_streams(a, [replace(b, stamps=stamps)], Settings())


def test_unit_mismatch_named_and_not_a_success():
    rec = simulate_recording(9, 20.0, 'full_pose')
    a, bs = _streams(rec)
    b = replace(bs[0], position=bs[0].position * 1000.0)
    try:
        result, _ = calibrate_streams(a, [b], Settings())
    except InconsistentDataError as e:
        assert 'units' in str(e)
        return
    assert not result.success and result.fit_consistent is False
    assert 'mm' in result.verdict


def test_ols_on_noisy_input_points_to_tls():
    """OLS fits A's rotation noise as excess: the verdict says so and names the one that fits."""
    rec = simulate_recording(11, 60.0, 'full_pose', sigma_a=(2e-4, np.radians(0.5)))
    a, bs = _streams(rec)
    settings = Settings(sigma_a=(2e-4, float(np.radians(0.5))))
    ols, _ = calibrate_streams(a, bs, settings.updated(method='ols'))
    assert not ols.success and '--method tls includes it' in ols.verdict
    tls, _ = calibrate_streams(a, bs, settings)
    assert tls.success and 'method tls' not in tls.verdict


def test_swapped_devices_named_from_frame_ids():
    rec = simulate_recording(10, 20.0, 'full_pose')
    a, bs = _streams(rec)
    a2 = replace(bs[0], frame_id='device_b_base')  # B's messages on topic A
    b2 = replace(a, frame_id='device_a_base')
    result, _ = calibrate_streams(a2, [b2], Settings(sigma_a=(5e-4, 2e-3),
                                                     sigma_b=(2e-4, 5e-4)),
                                  frames=('device_a_base', 'device_b_base'))
    # the swap fits (the model is symmetric enough), but it is never silent
    assert 'swapped (exchange topic_a and topic_b)' in result.verdict
    right, _ = calibrate_streams(a, bs, Settings(), frames=('device_a_base', 'device_b_base'))
    assert 'swapped' not in right.verdict


def _prior_from(result) -> Prior:
    return Prior(result.base_to_base, result.tool_to_marker, result.cov_joint)


def test_prior_of_a_long_recording_reaches_the_joint_sigma():
    rec = simulate_recording(51, 70.0, 'full_pose')
    a, bs = _streams(rec)
    b = bs[0]
    split = int(b.stamps[0] + 60e9)
    first = replace(b, stamps=b.stamps[b.stamps < split], position=b.position[b.stamps < split],
                    quat_wxyz=b.quat_wxyz[b.stamps < split])
    last = replace(b, stamps=b.stamps[b.stamps >= split],
                   position=b.position[b.stamps >= split],
                   quat_wxyz=b.quat_wxyz[b.stamps >= split])
    settings = Settings(estimate_time_offset=False)
    long_fit, _ = calibrate_streams(a, [first], settings)
    both, _ = calibrate_streams(a, [b], settings)
    refined, _ = calibrate_streams(a, [last], settings, prior=_prior_from(long_fit))
    sd_both = np.sqrt(np.diag(both.cov_joint))
    sd_refined = np.sqrt(np.diag(refined.cov_joint))
    np.testing.assert_allclose(sd_refined, sd_both, rtol=0.1)
    assert refined.prior_check['consistent'] and refined.success


def test_disagreeing_prior_is_flagged():
    rec = simulate_recording(52, 30.0, 'full_pose')
    a, bs = _streams(rec)
    fit, _ = calibrate_streams(a, bs, Settings())
    t0 = fit.base_to_base
    moved = UncertainPose(t0.position + np.array([0.003, 0.0, 0.0]), t0.quat_wxyz,
                          t0.covariance * 4.0)
    result, _ = calibrate_streams(a, bs, Settings(), prior=Prior(moved, None))
    assert result.prior_check is not None and not result.prior_check['consistent']
    assert not result.success and 'prior disagrees' in result.verdict


def test_partial_prior_constrains_only_its_axes():
    rec = simulate_recording(53, 10.0, 'full_pose')
    a, bs = _streams(rec)
    truth = rec.truth
    cov = np.diag([1e-10, 1e-10, 1e-10, np.inf, np.inf, np.inf])  # T1 position from CAD
    prior = Prior(None, UncertainPose(np.asarray(truth.markers[0]), np.array([1.0, 0, 0, 0]),
                                      cov))
    free, _ = calibrate_streams(a, bs, Settings())
    held, _ = calibrate_streams(a, bs, Settings(), prior=prior)
    sd_free = np.sqrt(np.diag(free.tool_to_marker.covariance))
    sd_held = np.sqrt(np.diag(held.tool_to_marker.covariance))
    assert (sd_held[:3] < 0.5 * sd_free[:3]).all()
    assert held.success


@pytest.mark.slow
def test_joint_nees_of_transforms_and_offset():
    """NEES of (T0, T1, τ) over Monte Carlo trials with random offsets: within 5 % of 13."""
    rng = np.random.default_rng(2026)
    nees = []
    for trial in range(240):
        tau = float(rng.uniform(-0.2, 0.2))
        rec = simulate_recording(1000 + trial, 8.0, 'full_pose')
        a, bs = _streams(rec)
        result, _ = calibrate_streams(a, [_shift(bs[0], tau)], Settings())
        t = result.time_offset
        err = np.concatenate([_pose_errors(result, rec.truth), [tau - t.value_s]])
        cov = np.zeros((13, 13))
        cov[:12, :12] = result.cov_joint
        cov[:12, 12] = cov[12, :12] = t.cross_cov[:, 0]
        cov[12, 12] = t.cov[0, 0]
        nees.append(float(err @ np.linalg.solve(cov, err)))
    mean = float(np.mean(nees))
    assert abs(mean - 13.0) < 0.05 * 13.0, mean


def _part(b: PoseStream, mask: np.ndarray) -> PoseStream:
    return replace(b, stamps=b.stamps[mask], position=b.position[mask],
                   quat_wxyz=b.quat_wxyz[mask])


@pytest.mark.slow
def test_prior_refinement_by_monte_carlo():
    """A 10 s recording with the prior of a 60 s one: its error and σ match a 70 s calibration."""
    err_refined, err_both, sd_refined, sd_both = [], [], [], []
    settings = Settings(estimate_time_offset=False)
    for trial in range(16):
        rec = simulate_recording(300 + trial, 70.0, 'full_pose')
        a, bs = _streams(rec)
        b = bs[0]
        early = b.stamps < b.stamps[0] + np.int64(60e9)

        long_fit, _ = calibrate_streams(a, [_part(b, early)], settings)
        refined, _ = calibrate_streams(a, [_part(b, ~early)], settings,
                                       prior=_prior_from(long_fit))
        both, _ = calibrate_streams(a, [b], settings)
        err_refined.append(_pose_errors(refined, rec.truth))
        err_both.append(_pose_errors(both, rec.truth))
        sd_refined.append(np.sqrt(np.diag(refined.cov_joint)))
        sd_both.append(np.sqrt(np.diag(both.cov_joint)))
        assert refined.prior_check['consistent'] or refined.prior_check['p_value'] > 1e-4
    rms_refined = np.sqrt(np.mean(np.square(err_refined), axis=0))
    rms_both = np.sqrt(np.mean(np.square(err_both), axis=0))
    np.testing.assert_allclose(np.mean(sd_refined, axis=0), np.mean(sd_both, axis=0), rtol=0.1)
    # 16 trials: the RMS of each axis is known to ±18 % (1σ); the mean over 12 axes to ±5 %
    ratio = float(np.mean(rms_refined / rms_both))
    assert 0.85 < ratio < 1.15, ratio


def test_swapped_roles_are_flagged():
    from coreg_ros.core.calibration.verdict import judge
    rec = simulate_recording(54, 10.0, 'full_pose')
    a, bs = _streams(rec)
    result, _ = calibrate_streams(a, bs, Settings())
    assert 'swap roles' not in result.verdict
    far = replace(result, tool_to_marker=UncertainPose(np.array([2.5, 0.0, 0.0]),
                                                       result.tool_to_marker.quat_wxyz,
                                                       result.tool_to_marker.covariance))
    judged = judge(far, a, bs, Settings())
    assert 'swap roles' in judged.verdict and '--invert-a --invert-b' in judged.verdict


@pytest.mark.parametrize('model', ['full_pose', 'position_only'])
@pytest.mark.parametrize('drift', [False, True])
@pytest.mark.parametrize('scaled', [False, True])
def test_closed_form_offset_sums_equal_the_generic_ones(model, drift, scaled):
    from coreg_ros.core.calibration.initialize import initialize
    from coreg_ros.core.clock import timing
    from coreg_ros.core.clock.offset_sums import structured_offset_sums
    from coreg_ros.core.estimator import noise_covariance, output_covariance
    from coreg_ros.core.estimator.linearized import PairData
    from coreg_ros.core.models import SPECS
    from coreg_ros.sim import simulate_pairs

    rng = np.random.default_rng(31 + 2 * drift + scaled)
    n = 20_000  # more than two chunks
    sigma_a = (rng.uniform(1e-4, 1e-3), rng.uniform(1e-3, 1e-2))
    sigma_b = (rng.uniform(1e-4, 1e-3), rng.uniform(1e-3, 1e-2))
    pairs, _, _ = simulate_pairs(rng, n, model, sigma_a=sigma_a, sigma_b=sigma_b)
    spec = SPECS[model]
    qa = quat.validate_quaternions(pairs.quat_a)
    qb = None if pairs.quat_b is None else quat.validate_quaternions(pairs.quat_b)
    data = PairData(np.asarray(pairs.pos_a), qa, np.asarray(pairs.pos_b), qb,
                    noise_covariance(sigma_a), output_covariance(noise_covariance(sigma_b), spec),
                    rng.uniform(0.5, 1.0, n) if scaled else None, True)
    # at the closed-form start, a little off the minimum: every sum is non-trivial
    params = initialize(spec, data.pos_a, qa, data.pos_b, qb)
    velocity = rng.normal(size=(n, 6)) * [0.3, 0.3, 0.3, 1.0, 1.0, 1.0]
    velocity[rng.random(n) < 0.05] = 0.0  # unknown velocity (a gap) gives zero
    since = rng.uniform(-100.0, 100.0, n) if drift else None
    k = 1 + drift
    factor = 1e-3 * np.eye(6)
    h_tt, h_pt, g_t, noise = timing._generic_sums(params, data, velocity, since, k,
                                                  spec.n_params, None, factor)
    got = structured_offset_sums(params, data, velocity, since)
    assert got is not None
    for mine, ref in zip(got, (h_tt, h_pt, g_t), strict=True):
        np.testing.assert_allclose(mine, ref, rtol=1e-10, atol=1e-10 * np.abs(ref).max())
    # the noise share, on the pairs it uses only: the very same number
    assert timing._velocity_noise(params, data, velocity, factor) == noise


def test_closed_form_offset_sums_leave_other_cases_to_the_generic_path():
    from coreg_ros.core.calibration.initialize import initialize
    from coreg_ros.core.clock.offset_sums import structured_offset_sums
    from coreg_ros.core.estimator import noise_covariance, output_covariance
    from coreg_ros.core.estimator.linearized import PairData
    from coreg_ros.core.models import SPECS
    from coreg_ros.sim import simulate_pairs

    rng = np.random.default_rng(5)
    sigma = (2e-4, 5e-3)
    for model, cov_a, tls in [('three_marker', noise_covariance(sigma), True),
                              ('full_pose', np.diag([1e-4, 2e-4, 1e-4, 1e-3, 1e-3, 1e-3]) ** 2,
                               True),
                              ('full_pose', noise_covariance(sigma), False)]:
        pairs, _, _ = simulate_pairs(rng, 200, model, sigma_a=sigma, sigma_b=sigma)
        spec = SPECS[model]
        qb = None if pairs.quat_b is None else np.asarray(pairs.quat_b)
        data = PairData(np.asarray(pairs.pos_a), np.asarray(pairs.quat_a),
                        np.asarray(pairs.pos_b), qb, cov_a,
                        output_covariance(noise_covariance(sigma), spec), None, tls)
        params = initialize(spec, data.pos_a, data.quat_a, data.pos_b, qb)
        assert structured_offset_sums(params, data, np.ones((200, 6)), None) is None
