"""The watchdog: false-alarm design, detection and attribution of T0, T1, clock, noise changes."""

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.live.guidance import PairFeed
from coreg_ros.core.live.watchdog import (
    Calibration,
    cusum_threshold,
    DESIGN_INFLATION,
    ERROR,
    KEY_CHANGE,
    KEY_STALE,
    KEY_STATE,
    llr_constants,
    OK,
    recalibration_prior,
    run_length,
    WARN,
    Watchdog,
)
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import Pairs, PoseStream
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.changes import apply_change, apply_changes, parse_change
import numpy as np
import pytest
from scipy import stats

# the noise of the sample recording bags/sample_full_pose, pairs at 100 Hz
SIGMA_A = (2e-4, 5e-4)
SIGMA_B = (5e-4, 2e-3)
RATE = 100.0


def _record(seed, duration, truth=None, model='full_pose'):
    return simulate_recording(seed, duration, model, rate_a=RATE, rate_b=RATE, sigma_a=SIGMA_A,
                              sigma_b=SIGMA_B, truth=truth)


@pytest.fixture(scope='module')
def calibrated():
    rec = _record(31, 60.0)
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result, _ = calibrate_streams(rec.stream_a, rec.streams_b, settings)
    assert result.success
    return rec.truth, result, settings


def _watch(watchdog, rec, settings, result, chunk=100):
    """Feed a recording through PairFeed and the watchdog in chunks (one second at 100 Hz)."""
    pairs, _ = pair_for(rec.stream_a, rec.streams_b, settings, result.time_offset)
    feed = PairFeed()
    history = []
    for k in range(0, len(pairs), chunk):
        sl = slice(k, k + chunk)
        batch = feed.push(Pairs(pairs.stamps[sl], pairs.pos_a[sl], pairs.quat_a[sl],
                                pairs.pos_b[sl],
                                None if pairs.quat_b is None else pairs.quat_b[sl],
                                pairs.a_var_scale[sl]))
        history.append(watchdog.update(batch))
    history.append(watchdog.update(feed.push(None, final=True)))
    return history


# --------------------------------------------------------------------------- the CUSUM design


def _monte_carlo_run_length(h, m, noncentrality, runs, rng):
    a, b, clip = llr_constants(m, DESIGN_INFLATION)
    s = np.zeros(runs)
    alive = np.ones(runs, dtype=bool)
    length = np.zeros(runs)
    k = 0
    while alive.any():
        k += 1
        n = int(alive.sum())
        d2 = (rng.noncentral_chisquare(m, noncentrality, n) if noncentrality > 0
              else rng.chisquare(m, n))
        s[alive] = np.maximum(0.0, s[alive] + a * np.minimum(d2, clip) - b)
        done = np.flatnonzero(alive)[s[alive] >= h]
        length[done] = k
        alive[done] = False
    return length


@pytest.mark.parametrize('m', [3, 6])
def test_run_length_of_the_markov_chain_matches_monte_carlo(m):
    rng = np.random.default_rng(7)
    h = 5.0  # low, so that false alarms are frequent enough to count
    predicted = run_length(h, m)
    got = _monte_carlo_run_length(h, m, 0.0, 3000, rng)
    # run lengths are nearly exponential: the mean of 3000 has a 1.8 % standard error
    assert abs(got.mean() / predicted - 1.0) < 0.08, (got.mean(), predicted)
    delay = run_length(cusum_threshold(m), m, noncentrality=10.0)
    got = _monte_carlo_run_length(cusum_threshold(m), m, 10.0, 2000, rng)
    assert abs(got.mean() / delay - 1.0) < 0.05, (got.mean(), delay)


def test_threshold_gives_the_target_false_alarm_rate():
    for m in (3, 6, 9):
        h = cusum_threshold(m)
        arl = run_length(h, m)
        assert abs(np.log(arl / 1e9)) < 0.01
        # 1e9 pairs between false alarms: far under one per 24 h at 100 Hz (8.64e6 pairs)
        assert arl > 100 * 24 * 3600 * RATE


# --------------------------------------------------------------------------- no false alarm


def test_no_alarm_on_a_stable_ten_minute_recording(calibrated):
    truth, result, settings = calibrated
    rec = _record(32, 600.0, truth)
    wd = Watchdog(result, SIGMA_A, SIGMA_B)
    history = _watch(wd, rec, settings, result)
    assert all(st.level == OK for st in history)
    assert wd.n_checked > 59_000
    assert wd.transients == 0
    # the normalised residuals are what the stated noise says
    assert 0.9 < np.mean([st.mean_d2 for st in history[1:-1]]) < 1.1
    assert max(st.statistic for st in history) < 0.6 * wd.threshold


def test_isolated_outliers_raise_no_error(calibrated):
    truth, result, settings = calibrated
    rec = _record(33, 60.0, truth)
    b = rec.streams[rec.topics_b[0]]
    pos = b.position.copy()
    rng = np.random.default_rng(3)
    # one gross outlier (5-20 mm) every 2 s, as a tracker misdetecting now and then
    for i in range(100, len(pos), 200):
        pos[i] += rng.uniform(0.005, 0.02) * rng.standard_normal(3) / np.sqrt(3)
    streams = dict(rec.streams)
    streams[rec.topics_b[0]] = PoseStream(b.stamps, pos, b.quat_wxyz, b.frame_id)
    from dataclasses import replace
    rec = replace(rec, streams=streams)
    wd = Watchdog(result, SIGMA_A, SIGMA_B)
    history = _watch(wd, rec, settings, result)
    assert all(st.level != ERROR for st in history)


# --------------------------------------------------------------------------- changes


CHANGES = ['t0_step=2mm@20', 't0_step=0.5deg@20', 't1_step=2mm@20', 't1_step=0.5deg@20',
           'clock_step=0.01@20']


@pytest.mark.parametrize('seed', [41, 42])
@pytest.mark.parametrize('spec', CHANGES)
def test_changes_are_detected_and_attributed(calibrated, spec, seed):
    truth, result, settings = calibrated
    rec = apply_changes(_record(seed, 40.0, truth), [spec], seed=seed)
    change = rec.truth.effects[-1]
    wd = Watchdog(result, SIGMA_A, SIGMA_B)
    history = _watch(wd, rec, settings, result)
    final = history[-1]
    assert final.level == ERROR, final.message
    # detected within 5 s of the change (pairs at 100 Hz), not before it
    delay = (final.alarm_stamp - change['start_ns']) * 1e-9
    assert 0.0 <= delay < 5.0, delay
    # the change point estimate is near the truth
    assert abs(final.change_stamp - change['start_ns']) * 1e-9 < 1.0
    att = final.attribution
    kind = spec.split('_')[0]
    assert att.kind == {'t0': 't0', 't1': 't1', 'clock': 'clock'}[kind], att.text
    assert att.decided
    if kind == 'clock':
        assert abs(att.time_step - 0.01) < max(4 * att.time_sigma, 5e-4), att.text
    else:
        dp = np.asarray(change['translation_m'])
        dth = np.asarray(change['rotation_rad'])
        assert np.linalg.norm(att.translation - dp) < max(4 * att.translation_sigma, 2e-4)
        assert np.linalg.norm(att.rotation - dth) < max(4 * att.rotation_sigma, 2e-4)
    assert final.stale
    values = dict(final.diagnostic_values())
    assert values[KEY_STATE] == 'ERROR' and values[KEY_STALE] == 'true'
    assert values[KEY_CHANGE] == att.kind


def test_noise_change_is_attributed_to_noise(calibrated):
    truth, result, settings = calibrated
    # the noise of B doubles (e.g. metal near an EM field generator)
    rec = apply_changes(_record(43, 40.0, truth), ['noise_step=2@20'])
    wd = Watchdog(result, SIGMA_A, SIGMA_B)
    final = _watch(wd, rec, settings, result)[-1]
    assert final.level == ERROR
    assert final.attribution.kind == 'noise', final.attribution.text
    assert 1.7 < final.attribution.noise_factor < 2.3
    assert len(wd.last_d2) > 0


def test_position_only_t1_step(calibrated):
    rec = _record(44, 60.0, model='position_only')
    settings = Settings(model='position_only', sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result, _ = calibrate_streams(rec.stream_a, rec.streams_b, settings)
    later = apply_changes(_record(45, 40.0, rec.truth, model='position_only'),
                          ['t1_step=2mm@20'])
    wd = Watchdog(result, SIGMA_A, SIGMA_B)
    final = _watch(wd, later, settings, result)[-1]
    assert final.level == ERROR and final.attribution.kind == 't1', final.message
    dp = np.asarray(later.truth.effects[-1]['translation_m'])
    assert np.linalg.norm(final.attribution.translation - dp) < 3e-4


def test_recalibration_on_the_window_with_what_still_holds_as_prior(calibrated):
    truth, result, settings = calibrated
    rec = apply_changes(_record(47, 40.0, truth), ['t0_step=3mm+0.3deg@10'], seed=47)
    wd = Watchdog(result, SIGMA_A, SIGMA_B)
    final = _watch(wd, rec, settings, result)[-1]
    assert final.level == ERROR and final.attribution.kind == 't0'
    prior = recalibration_prior(result, final.attribution.kind)
    assert prior.base_to_base is None and prior.tool_to_marker is not None
    assert recalibration_prior(result, 'noise') is None
    both = recalibration_prior(result, 'clock')
    assert both.base_to_base is not None and both.tool_to_marker is not None

    def since(s):
        keep = s.stamps >= final.change_stamp
        return PoseStream(s.stamps[keep], s.position[keep], s.quat_wxyz[keep], s.frame_id)

    new, _ = calibrate_streams(since(rec.stream_a), [since(s) for s in rec.streams_b],
                               settings, prior)
    assert new.success and new.prior_check['consistent']
    step = rec.truth.effects[-1]
    p0 = truth.p0 + np.asarray(step['translation_m'])
    sd = np.sqrt(np.diag(new.base_to_base.covariance))
    assert np.all(np.abs(new.base_to_base.position - p0) < 4 * sd[:3])
    q0 = quat.multiply(quat.exp(np.asarray(step['rotation_rad'])), truth.q0)
    assert quat.angle_between(new.base_to_base.quat_wxyz, q0) < 4 * np.linalg.norm(sd[3:])


def test_reset_and_the_ok_state(calibrated):
    truth, result, settings = calibrated
    rec = apply_changes(_record(46, 30.0, truth), ['t0_step=5mm@10'])
    wd = Watchdog(result, SIGMA_A, SIGMA_B)
    assert _watch(wd, rec, settings, result)[-1].level == ERROR
    wd.reset()
    st = wd.state()
    assert st.level == OK and st.n_checked == 0 and st.statistic == 0.0
    assert dict(st.diagnostic_values())[KEY_STALE] == 'false'
    assert WARN == 1


def test_calibration_covariance_from_the_result(calibrated):
    _, result, _ = calibrated
    cal = Calibration.from_result(result)
    assert cal.cov.shape == (13, 13)
    assert np.allclose(cal.cov[:12, :12], result.cov_joint, rtol=1e-6,
                       atol=1e-9 * np.abs(result.cov_joint).max())
    assert np.isclose(np.sqrt(cal.cov[12, 12]), result.time_offset.sigma_s)
    assert np.all(np.linalg.eigvalsh(cal.cov) > -1e-18)
    assert cal.time_offset_s == result.time_offset.value_s


# --------------------------------------------------------------------------- simulated changes


def test_parse_change():
    c = parse_change('t0_step=2mm@30')
    assert (c.name, c.translation_m, c.rotation_rad, c.time_s) == ('t0_step', 0.002, 0.0, 30.0)
    c = parse_change('t1_step=0.5deg@30')
    assert np.isclose(c.rotation_rad, np.radians(0.5)) and c.translation_m == 0.0
    c = parse_change('t0_step=1mm+0.2deg:-z@45.5')
    assert np.allclose(c.axis, [0, 0, -1]) and c.time_s == 45.5
    assert parse_change('clock_step=0.01@30').clock_s == 0.01
    assert parse_change('clock_step=10ms@30').clock_s == pytest.approx(0.01)
    assert parse_change('clock_step=-0.005@1').clock_s == -0.005
    assert parse_change('noise_step=2.5@3').noise_factor == 2.5
    for bad in ('t0_step=2@30', 't0_step=2mm', 'wobble=2mm@3', 'clock_step=2mm@3',
                't0_step=2mm@-1', 'clock_step=0.01:x@3', 't0_step=2furlong@3', '',
                'noise_step=0.5@3', 'noise_step=2mm@3'):
        with pytest.raises(ConfigError):
            parse_change(bad)


def test_apply_change_moves_the_noise_free_poses_exactly():
    rec = simulate_recording(51, 4.0, sigma_a=(0.0, 0.0), sigma_b=(0.0, 0.0))
    t = rec.truth
    moved = apply_change(rec, parse_change('t0_step=3mm+1deg:x@2'))
    b0, b1 = rec.streams[rec.topics_b[0]], moved.streams[rec.topics_b[0]]
    before = b0.stamps < rec.start_ns + 2_000_000_000
    assert np.array_equal(b0.position[before], b1.position[before])
    from dataclasses import replace
    q0 = quat.multiply(quat.exp(np.radians(1.0) * np.array([1.0, 0, 0])), t.q0)
    new = replace(t, p0=t.p0 + np.array([0.003, 0, 0]), q0=quat.canonical(q0))
    pos_a, q_a = rec.motion.pose((b0.stamps[~before] - rec.start_ns) * 1e-9)
    pos_b, q_b = new.device_b(pos_a, q_a)
    assert np.allclose(b1.position[~before], pos_b[:, 0], atol=1e-12)
    assert np.allclose(np.abs(np.sum(b1.quat_wxyz[~before] * q_b, axis=1)), 1.0)
    moved = apply_change(rec, parse_change('t1_step=2mm+0.5deg:y@2'))
    b1 = moved.streams[rec.topics_b[0]]
    q1 = quat.multiply(quat.exp(np.radians(0.5) * np.array([0, 1.0, 0])), t.q1)
    p1 = t.p1 + np.array([0, 0.002, 0])
    new = replace(t, p1=p1, markers=p1[None], q1=quat.canonical(q1))
    pos_b, q_b = new.device_b(pos_a, q_a)
    assert np.allclose(b1.position[~before], pos_b[:, 0], atol=1e-12)
    assert np.allclose(np.abs(np.sum(b1.quat_wxyz[~before] * q_b, axis=1)), 1.0)
    assert moved.truth.effects[-1]['name'] == 't1_step'


def test_clock_step_shifts_b_stamps_after_the_time():
    rec = simulate_recording(52, 4.0)
    moved = apply_changes(rec, ['clock_step=0.25@2'])
    b0, b1 = rec.streams[rec.topics_b[0]], moved.streams[rec.topics_b[0]]
    after = b0.stamps >= rec.start_ns + 2_000_000_000
    assert np.array_equal(b1.stamps[after] - b0.stamps[after], np.full(after.sum(), 250_000_000))
    assert np.array_equal(b1.stamps[~after], b0.stamps[~after])
    assert np.array_equal(moved.stream_a.stamps, rec.stream_a.stamps)
    assert moved.truth.effects[-1] == {'name': 'clock_step', 'time_s': 2.0,
                                       'start_ns': rec.start_ns + 2_000_000_000,
                                       'clock_s': 0.25}


def test_random_directions_follow_the_seed():
    rec = simulate_recording(53, 2.0)
    a = apply_changes(rec, ['t0_step=2mm@1'], seed=1).truth.effects[-1]['translation_m']
    b = apply_changes(rec, ['t0_step=2mm@1'], seed=1).truth.effects[-1]['translation_m']
    c = apply_changes(rec, ['t0_step=2mm@1'], seed=2).truth.effects[-1]['translation_m']
    assert a == b and a != c
    assert np.isclose(np.linalg.norm(a), 0.002)


def test_chi_square_clip_leaves_the_step_detectable():
    # a 2 mm step at the sample recording's noise is a noncentrality of about 13 per pair
    _, _, clip = llr_constants(6, DESIGN_INFLATION)
    assert clip == pytest.approx(stats.chi2.isf(1e-3, 6))
    delay = run_length(cusum_threshold(6), 6, noncentrality=13.0)
    assert delay < 0.5 * RATE  # pairs: well under 5 s at 100 Hz


# --------------------------------------------------------------------------- restricted rigs

@pytest.mark.parametrize('rig, model', [('scara', 'full_pose'), ('gantry', 'full_pose'),
                                        ('gantry', 'position_only'),
                                        ('turntable', 'position_only')])
def test_a_restricted_rig_watched_without_false_alarm_and_its_changes_named(rig, model):
    """
    Issue 22: a held direction is no change; a gantry cannot tell T0 from T1 and says so.

    On a SCARA arm or a turntable T0 and T1 are told apart (the tool turns); on a gantry
    (translation only) a translation of T0 and one of T1 change every prediction alike. On a
    turntable the calibration's turn about the axis is held, so a change is said in the
    held turn's axes: its size, not its direction, is the truth's.
    """
    rec = simulate_recording(51, 40.0, model, rate_a=RATE, rate_b=RATE, sigma_a=SIGMA_A,
                             sigma_b=SIGMA_B, motion=rig)
    settings = Settings(model=model, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    result, _ = calibrate_streams(rec.stream_a, rec.streams_b, settings)
    assert result.success and result.held
    quiet = _watch(Watchdog(result, SIGMA_A, SIGMA_B), rec, settings, result)
    assert max(s.level for s in quiet) == OK, quiet[-1].message
    for spec, expected in (('t0_step=2mm@20', 't0'), ('t1_step=2mm@20', 't1')):
        moved = apply_changes(rec, [spec], seed=3)
        final = _watch(Watchdog(result, SIGMA_A, SIGMA_B), moved, settings, result)[-1]
        att = final.attribution
        assert final.level == ERROR and att.decided, final.message
        assert att.kind == ('t0_or_t1' if rig == 'gantry' else expected), final.message
        if rig == 'gantry':
            assert 'cannot tell which' in final.message
            assert recalibration_prior(result, att.kind) == Prior()  # neither kept
        dp = np.asarray(moved.truth.effects[-1]['translation_m'])
        if rig == 'turntable':  # δp is in the held turn's tool axes: its size is the truth's
            size = abs(np.linalg.norm(att.translation) - np.linalg.norm(dp))
            assert size < max(4 * att.translation_sigma, 2e-4), final.message
        elif att.size_in == expected:  # in the moved transform's own terms
            assert np.linalg.norm(att.translation - dp) < max(4 * att.translation_sigma, 2e-4)
