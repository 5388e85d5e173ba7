"""Tests of the sim-to-real gap diagnosis (coreg_ros.core.diagnosis), issue 4."""

import json

from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.diagnosis import diagnose_streams, EFFECT_NAMES
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.data import prepare, spatial_folds, time_folds, Trajectory
from coreg_ros.core.diagnosis.detect import detect, ljung_box
from coreg_ros.core.diagnosis.effects import CANDIDATES, FitReading
from coreg_ros.core.diagnosis.engine import _params_of
from coreg_ros.core.diagnosis.fit import Model, start_state
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import EFFECT_NAMES as SIM_EFFECT_NAMES
from coreg_ros.sim.injected import parse_effect
from coreg_ros.threads import one_blas_thread
import numpy as np
import pytest

REPORT_KEYS = {'gap_detected', 'effects', 'not_separable', 'gap_before', 'gap_after',
               'location', 'verdict'}


def _recording(effect, seed=4, duration=40.0, model='full_pose'):
    rec = simulate_recording(seed, duration, model,
                             effects=[parse_effect(effect)] if effect else [])
    return rec, Settings(model=model)


def test_effect_names_match_the_simulator():
    from coreg_ros.sim.injected import ALL_EFFECT_NAMES
    from coreg_ros.sim.validation import EXPECTED

    # the ten of docs/design.md first, in their order; every simulated effect has its answer
    assert tuple(EFFECT_NAMES[:3]) == tuple(SIM_EFFECT_NAMES[:2]) + ('clock_step',)
    assert set(SIM_EFFECT_NAMES) <= set(EFFECT_NAMES)
    assert {EXPECTED.get(n, n) for n in ALL_EFFECT_NAMES} <= set(CANDIDATES)


def test_clean_recording_has_no_gap_and_exact_keys():
    rec, settings = _recording(None, seed=21, duration=30.0)
    diag = diagnose_streams(rec.stream_a, list(rec.streams_b), settings)
    r = diag.report.as_dict()
    assert REPORT_KEYS <= set(r)
    assert r['gap_detected'] is False
    assert r['effects'] == []
    assert r['not_separable'] == []
    assert 0.9 < r['gap_before']['chi2_per_dof'] < 1.1
    assert r['verdict'].startswith('no gap')
    json.dumps(r)  # plain JSON types only


def test_time_offset_named_with_estimate_and_gap_closed():
    rec, settings = _recording('time_offset=0.012', seed=5, duration=30.0)
    r = diagnose_streams(rec.stream_a, list(rec.streams_b), settings).report.as_dict()
    assert r['gap_detected'] is True
    assert r['effects'][0]['name'] == 'time_offset'
    est = r['effects'][0]['estimate']
    assert abs(est['tau_s'] - 0.012) < 4 * est['sigma_s'] + 2e-4
    assert r['effects'][0]['held_out_gain'] > 0
    assert r['gap_before']['chi2_per_dof'] > 1.5
    assert r['gap_after']['chi2_per_dof'] < 1.1
    assert r['gap_after']['position_rms_to_floor'] < 1.2
    assert r['gap_after']['share_of_excess_explained'] > 0.8
    assert 'velocity_xcorr' in r['location']


# each effect's model recovers its injected parameter within its reported uncertainty
RECOVERY = [
    ('time_offset=0.02', 'time_offset', lambda e: (e['tau_s'], e['sigma_s']), 0.02),
    ('clock_drift=300', 'clock_drift', lambda e: (e['ppm'], e['sigma_ppm']), 300.0),
    ('timestamp_jitter=0.008', 'timestamp_jitter',
     lambda e: (e['sigma_s'], e['sigma_sigma_s']), None),
    ('field_distortion=6', 'field_distortion', lambda e: (e['max_mm'], e['sigma_max_mm']), 6.0),
    ('distance_noise=3', 'distance_noise', lambda e: (e['exponent'], e['sigma']), 3.0),
    ('scale=0.01,-0.005,0.008', 'scale', lambda e: (np.array(e['scale']), np.array(e['sigma'])),
     np.array([0.01, -0.005, 0.008])),
    ('link_flex=2', 'link_flex', lambda e: (e['sag_mm'], e['sigma_mm']), 2.0),
    ('outliers=0.03', 'outliers', lambda e: (e['fraction'], e['sigma']), 0.03),
    ('backlash=0.6', 'backlash', lambda e: (e['width_mm'], e['sigma_mm']), 0.6),
    ('noise_scale=1.8', 'noise_scale', lambda e: (e['factor'], e['sigma']), 1.8),
]


@pytest.mark.parametrize('spec,name,get,truth', RECOVERY, ids=[r[1] for r in RECOVERY])
def test_effect_model_recovers_injected_parameter(spec, name, get, truth):
    rec, settings = _recording(spec, seed=8, duration=40.0)
    if truth is None:  # jitter: the stamp errors actually drawn
        truth = rec.truth.effects[0]['empirical_sigma_s']
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), settings)
    with one_blas_thread():
        res = calibrate(pairs, settings)
        data = prepare(pairs, settings, rec.stream_a)
        base = Model(data, ()).fit(start_state(_params_of(res, data.spec)))
        fit = Model(data, (name,)).fit(base.state)
        est = CANDIDATES[name].size(FitReading.of(fit)).as_dict()
    value, sigma = get(est)
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    # within the reported uncertainty (3σ), plus the model's approximation where the
    # simulator's effect is not exactly the fitted form (smooth sign, quadratic field)
    slack = {'backlash': 0.05, 'field_distortion': 0.3}.get(name, 0.0)
    assert np.all(np.abs(value - truth) <= 3.0 * sigma + slack * np.abs(truth)), (value, sigma)


def test_fit_base_model_matches_tls_calibration():
    rec, settings = _recording(None, seed=2, duration=20.0)
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), settings)
    res = calibrate(pairs, settings)
    data = prepare(pairs, settings, rec.stream_a)
    fit = Model(data, ()).fit(start_state(_params_of(res, data.spec)))
    assert np.allclose(fit.state.params.p0, res.base_to_base.position, atol=2e-4)
    # the per-pair chi-square under the stated noise is about m per pair
    quad, _, _, _ = vm.components(fit.state.var, fit.stats)
    assert 0.9 < quad.mean() / data.m < 1.1


def test_heldout_blocks_leave_each_block_out():
    rec, settings = _recording('scale=0.01', seed=3, duration=20.0)
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), settings)
    res = calibrate(pairs, settings)
    data = prepare(pairs, settings, rec.stream_a)
    folds = time_folds(data.t, 5)
    assert set(np.unique(folds)) == set(range(5))
    base = Model(data, ()).fit(start_state(_params_of(res, data.spec)), None, folds, 5)
    h_base = base.heldout(folds, 5)
    fit = Model(data, ('scale',)).fit(base.state, None, folds, 5)
    h = fit.heldout(folds, 5)
    gains = h.fold_sums(h.ll) - h_base.fold_sums(h_base.ll)
    assert np.all(gains > 0)
    # held-out is worse than in-sample for the effect's own fit
    assert h.ll.sum() < fit.loglik
    sf = spatial_folds(data.b_points[:, 0, :], 5)
    assert sf.shape == (data.n,) and sf.max() < 5


def test_ljung_box_and_detect():
    rng = np.random.default_rng(0)
    white = rng.standard_normal(4000)
    _, p_white, _ = ljung_box(white)
    assert p_white > 1e-3
    ar = np.zeros(4000)
    for i in range(1, 4000):
        ar[i] = 0.5 * ar[i - 1] + white[i]
    _, p_ar, rho = ljung_box(ar)
    assert p_ar < 1e-6 and abs(rho[0] - 0.5) < 0.05
    z = rng.standard_normal((3000, 6))
    d = detect(np.sum(z ** 2, axis=1), z, 6, 12)
    assert d.gap is False
    z[::50] *= 30.0
    d = detect(np.sum(z ** 2, axis=1), z, 6, 12)
    assert d.flags.heavy_tails and d.flags.chi2_high


def test_variance_fits():
    rng = np.random.default_rng(1)
    n, m = 5000, 6
    lam = rng.uniform(0, 0.5, (n, m))
    z = rng.standard_normal((n, m)) * np.sqrt(1.5 ** 2 * (1 + lam))
    st = vm.PairStats(z, lam, np.zeros((n, m)), np.zeros(n))
    var = vm.fit_variance(st, vm.VarState(), ('log_s2',))
    assert abs(np.exp(0.5 * var.log_s2) - 1.5) < 0.03
    z2 = rng.standard_normal((n, m)) * np.sqrt(1 + lam)
    bad = rng.random(n) < 0.03
    z2[bad] *= 40.0
    st2 = vm.PairStats(z2, lam, np.zeros((n, m)), np.zeros(n))
    var2 = vm.fit_variance(st2, vm.VarState(), ('logit_eps', 'log_lam'))
    assert abs(var2.eps - bad.mean()) < 0.01


def test_trajectory_interpolation_and_velocity():
    t = np.arange(0, 10, 0.01)
    pos = np.stack([np.sin(t), np.cos(t), 0.1 * t], axis=1)
    half = 0.5 * t[:, None] * np.array([0.0, 0.0, 1.0])
    q = np.concatenate([np.cos(half[:, 2:3]), np.zeros((len(t), 2)), np.sin(half[:, 2:3])], 1)
    traj = Trajectory(t, pos, q)
    p, _ = traj.pose(np.array([1.005]))
    assert np.allclose(p[0], [np.sin(1.005), np.cos(1.005), 0.1005], atol=1e-4)
    v, w = traj.velocity(np.array([2.0]))
    assert np.allclose(v[0], [np.cos(2.0), -np.sin(2.0), 0.1], atol=1e-3)
    assert np.allclose(w[0], [0, 0, 1.0], atol=1e-3)


def test_one_blas_thread_holds_blas_at_one_thread_and_restores_it():
    from threadpoolctl import threadpool_info

    def blas_threads():
        return [i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas']

    before = blas_threads()
    assert before  # numpy's BLAS is loaded
    with one_blas_thread():
        assert set(blas_threads()) == {1}
        a = np.ones((50, 50))
        assert (a @ a)[0, 0] == 50.0
    assert blas_threads() == before


def test_position_only_model_diagnosis():
    rec, settings = _recording('outliers=0.03', seed=6, duration=30.0, model='position_only')
    r = diagnose_streams(rec.stream_a, list(rec.streams_b), settings).report.as_dict()
    assert r['effects'] and r['effects'][0]['name'] == 'outliers'
    assert 'rotation_rms_rad' not in r['gap_after']
