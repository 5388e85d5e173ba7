"""The rules that let a second effect be named beside a larger one (issue 26, mixtures)."""

from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.engine import _base_fit
from coreg_ros.core.diagnosis.judged import (
    blocks_judged,
    EXPECTED_BLOCK_GAIN,
    expected_block_gains,
    own_gain_reasons,
    SCREEN_SHARE,
)
from coreg_ros.core.diagnosis.options import Options
from coreg_ros.core.diagnosis.selection import score_candidate, screen, Selector
from coreg_ros.core.diagnosis.significance import _largest_log_factor, rms_gain
from coreg_ros.core.diagnosis.steps import locate_clock_step
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
import numpy as np
import pytest


def _report(seed, specs, duration=40.0):
    rec = simulate_recording(seed, duration, effects=[parse_effect(s) for s in specs])
    return diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report.as_dict()


def test_a_noise_change_is_sized_along_the_direction_it_changes():
    # σ × 1.5 along one direction of six (a jitter along the motion, one noisier axis): the
    # total variance grows by only (1.5² - 1)/6, σ by 10 %, but along that direction by 50 %
    rng = np.random.default_rng(1)
    n, m = 400, 6
    u = rng.normal(size=(n, m))
    beta = 1.25 / np.sum(u ** 2, axis=1).mean()
    u *= np.sqrt(1.25 / beta) / np.linalg.norm(u, axis=1)[:, None]
    st = vm.PairStats(rng.normal(size=(n, m)), np.zeros((n, m)), u, np.zeros(n))
    var = vm.VarState().with_values(('log_beta',), (np.log(beta),))
    off = vm.VarState()
    along = np.expm1(np.quantile(_largest_log_factor(var, off, st), 0.9))
    assert along == pytest.approx(0.5, rel=1e-6)
    trace = np.sqrt(vm.total_variance(var, st) / vm.total_variance(off, st)) - 1.0
    assert np.all(trace < 0.11)
    # a noise level changes every direction alike: the same either way
    level = vm.VarState().with_values(('log_s2',), (np.log(1.3 ** 2),))
    assert np.allclose(np.expm1(_largest_log_factor(level, off, st)), 0.3)


def test_rms_gain_is_judged_at_the_stated_noise():
    # within the stated noise: the relative fall of the RMS
    assert rms_gain(0.81, 1.0, 1.0) == pytest.approx(0.1)
    assert rms_gain(0.81, 1.0, 4.0) == pytest.approx(0.1)
    assert rms_gain(0.81, 1.0, None) == pytest.approx(0.1)
    # errors 10× the stated variance (another effect's jitter): the same fall of the mean
    # square is a tenth of the RMS, but a whole stated noise's worth at the stated noise
    diluted = rms_gain(9.19, 10.0, None)
    assert diluted < 0.05
    assert rms_gain(9.19, 10.0, 1.0) > 0.5
    # a rise is judged alike, and negative
    assert rms_gain(1.21, 1.0, 1.0) < 0.0


def test_a_drift_from_zero_is_judged_on_the_blocks_it_gains_in():
    # a clock that drifts from zero moves the first time block by almost nothing: the block's
    # held-out sign is a coin flip, and it is not judged. Monte Carlo over fixed draws.
    excluded = 0
    for draw in range(2):
        rng = np.random.default_rng(3300 + draw)
        ppm = float(rng.uniform(15.0, 25.0))
        rec = simulate_recording(int(rng.integers(1000)), 60.0,
                                 effects=[parse_effect(f'clock_drift={ppm:.2f}')])
        settings = Settings()
        pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), settings)
        data, _, fit0 = _base_fit(pairs, settings, rec.stream_a, settings.cov_a,
                                  settings.cov_b, Options().n_folds)
        sel = Selector(data, np.arange(data.n), Options(), lambda f, s: None)
        base = sel.score((), fit0.state)
        cand = score_candidate(sel, (), 'clock_drift', base, 0)
        gains = expected_block_gains(sel, cand.fit, 'clock_drift', sel.tf)
        # the prediction grows with the drift and follows the held-out gains it stands for
        assert np.all(np.diff(gains) > 0)
        assert np.corrcoef(gains, cand.fold_gains)[0, 1] > 0.8
        judged = blocks_judged(sel, 'clock_drift', sel.tf, cand.fit)
        assert np.array_equal(judged, gains >= EXPECTED_BLOCK_GAIN)
        excluded += int(not judged[0])
        # a constant offset moves every block alike: every block is judged
        const = score_candidate(sel, (), 'time_offset', base, 0)
        assert blocks_judged(sel, 'time_offset', sel.tf, const.fit).all()
        # a noise effect moves no error: None (every block with pairs is judged)
        assert expected_block_gains(sel, cand.fit, 'noise_scale', sel.tf) is None
    assert excluded >= 1


@pytest.mark.parametrize('draw', [0, 1])
def test_a_drift_beside_outliers_is_a_drift_not_a_step(draw):
    # the per-block offsets are fitted beside the outliers already accepted: outliers no
    # longer hide the drift's trend (it was named a clock step)
    rng = np.random.default_rng(3310 + draw)
    ppm = float(rng.uniform(30.0, 80.0)) * rng.choice([-1.0, 1.0])
    frac = float(rng.uniform(0.01, 0.03))
    r = _report(int(rng.integers(1000)), [f'clock_drift={ppm:.2f}', f'outliers={frac:.4f}'],
                duration=80.0)
    names = [e['name'] for e in r['effects']]
    assert 'clock_drift' in names and 'outliers' in names, names
    assert 'clock_step' not in names


@pytest.mark.parametrize('draw', [0, 1])
def test_a_pose_step_beside_a_large_jitter_is_named(draw):
    # the jitter leaves errors far above the stated noise: the step's fall of the RMS is
    # judged against the stated noise, not diluted by the jitter's errors
    rng = np.random.default_rng(3320 + draw)
    step = float(rng.uniform(0.4, 0.7))
    jitter = float(rng.uniform(0.018, 0.025))
    r = _report(int(rng.integers(1000)), [f't0_step={step:.3f}',
                                          f'timestamp_jitter={jitter:.4f}'])
    names = [e['name'] for e in r['effects']]
    assert 'pose_step' in names and 'timestamp_jitter' in names, (names, r['not_significant'])


def test_a_clock_step_is_screened_with_its_own_shift():
    # the screening's one-step prediction of a clock step uses the step's own column (the
    # offset after the located instant): a ramp stands for a step only in part, and a step
    # screened on the drift's ramp predicted too little to be refitted beside outliers
    rng = np.random.default_rng(3330)
    step = float(rng.uniform(0.03, 0.06))
    rec = simulate_recording(int(rng.integers(1000)), 40.0,
                             effects=[parse_effect(f'clock_step={step:.4f}')])
    settings = Settings()
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), settings)
    data, _, fit0 = _base_fit(pairs, settings, rec.stream_a, settings.cov_a, settings.cov_b,
                              Options().n_folds)
    sel = Selector(data, np.arange(data.n), Options(), lambda f, s: None)
    data.cache['clock_step'] = locate_clock_step(data, fit0.state, sel.idx)
    base = sel.score((), fit0.state)
    predicted = screen(sel, (), base, ['clock_step', 'clock_drift', 'time_offset'])
    refit = sel.score(('clock_step',), fit0.state)[0]
    in_sample = refit.loglik - base[0].loglik
    # its own prediction is its refit's gain; the ramp's (what it was screened with) is not
    assert predicted['clock_step'] == pytest.approx(in_sample, rel=0.05)
    assert abs(predicted['clock_drift'] - in_sample) > 3 * abs(predicted['clock_step'] - in_sample)


@pytest.mark.parametrize('offset', [0.0, 0.01])
def test_a_gain_must_come_from_the_effects_own_moves(offset):
    # a real offset's own moves predict about its held-out gain; with no offset its θ stays
    # near zero and whatever the refit gains is not its own
    rng = np.random.default_rng(3340)
    effects = [parse_effect(f'time_offset={offset}')] if offset else []
    rec = simulate_recording(int(rng.integers(1000)), 40.0, effects=effects)
    settings = Settings()
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), settings)
    data, _, fit0 = _base_fit(pairs, settings, rec.stream_a, settings.cov_a, settings.cov_b,
                              Options().n_folds)
    sel = Selector(data, np.arange(data.n), Options(), lambda f, s: None)
    base = sel.score((), fit0.state)
    cand = score_candidate(sel, (), 'time_offset', base, 0)
    own = float(np.sum(expected_block_gains(sel, cand.fit, 'time_offset', sel.tf)))
    thr = sel.threshold(0)
    if offset:
        assert cand.passes and own == pytest.approx(cand.gain, rel=0.2)
        assert own_gain_reasons(np.array([own]), thr) == []
    else:
        assert own < SCREEN_SHARE * thr
        assert 'its own moves' in own_gain_reasons(np.array([own]), thr)[0]
        assert not cand.passes and 'its own moves' in cand.reason
