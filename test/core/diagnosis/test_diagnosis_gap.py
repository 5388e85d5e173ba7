"""Gap measures a noise model cannot game (issue 11, item 1), outliers versus structure (2)."""

from dataclasses import replace

from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.diagnosis import excess as ex
from coreg_ros.core.diagnosis import gap as gp
from coreg_ros.core.diagnosis.data import prepare
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
import numpy as np
import pytest

NEW_KEYS = {'chi2_per_dof_at_stated_noise', 'rms_position_mm', 'rms_rotation_deg',
            'stated_floor_position_mm', 'excluded_pairs'}
OLD_KEYS = {'chi2_per_dof', 'chi2_per_dof_stated_noise', 'position_rms_m',
            'noise_floor_position_m', 'position_rms_to_floor', 'share_of_excess_explained'}


def _diag(specs, seed=5, duration=40.0, model='full_pose'):
    rec = simulate_recording(seed, duration, model, effects=[parse_effect(s) for s in specs])
    return diagnose_streams(rec.stream_a, list(rec.streams_b), Settings(model=model))


@pytest.mark.parametrize('spec,factor', [('noise_scale=1.8', 1.8), ('distance_noise=4', None)])
def test_a_noise_effect_never_shrinks_the_gap(spec, factor, tmp_path):
    diag = _diag([spec])
    r = diag.report.as_dict()
    assert r['effects'] and r['effects'][0]['kind'] == 'noise'
    b, a = r['gap_before'], r['gap_after']
    assert (NEW_KEYS | OLD_KEYS) <= set(a)
    # at the stated noise nothing moved, so nothing is explained
    assert a['chi2_per_dof_at_stated_noise'] == pytest.approx(
        b['chi2_per_dof_at_stated_noise'], rel=0.01)
    assert a['rms_position_mm'] == pytest.approx(b['rms_position_mm'], rel=0.01)
    assert a['share_of_excess_explained'] == 0.0 and a['rms_moved'] is False
    assert 'explained by' not in r['verdict'] and 'nothing is explained' in r['verdict']
    ne = r['noise_excess']
    assert ne is not None and ne['factor'] > 1.02
    if factor:
        assert ne['factor'] == pytest.approx(factor, rel=0.05)
    from coreg_ros.report.html import write_report
    page = write_report(diag, tmp_path / 'rep').read_text()
    assert 'gap explained by' not in page


def test_distance_noise_exponent_is_never_negative():
    # noise shrinking away from the source is physically backwards: never reported
    r = _diag(['distance_noise=-3']).report.as_dict()
    for e in r['effects']:
        if e['name'] == 'distance_noise':
            assert e['estimate']['exponent'] >= 0.0


def test_structured_effect_moves_the_rms_and_keeps_old_keys():
    r = _diag(['scale=0.01,-0.008,0.006']).report.as_dict()
    assert r['effects'][0]['name'] == 'scale' and r['effects'][0]['kind'] == 'structured'
    b, a = r['gap_before'], r['gap_after']
    assert a['rms_position_mm'] < 0.8 * b['rms_position_mm']
    assert a['rms_position_mm'] < 1.1 * a['stated_floor_position_mm']
    assert a['share_of_excess_explained'] > 0.8
    assert r['verdict'].startswith('gap explained by scale')


def test_set_aside_pairs_are_counted_as_unexplained():
    r = _diag(['outliers=0.03']).report.as_dict()
    a = r['gap_after']
    excl = a['excluded_pairs']
    assert excl['count'] > 0 and excl['counted_as'] == 'unexplained'
    assert a['share_of_excess_explained'] <= 1.0 - excl['share'] + 1e-12
    # all pairs: the glitches stay in the RMS
    assert a['rms_position_mm_all_pairs'] > 3 * a['rms_position_mm']
    assert r['effects'][0]['name'] == 'outliers'           # random glitches stay outliers
    assert r['excess_left']['flagged_pairs']['clustered'] is False


def test_share_explained_rules():
    before = gp.StatedBlock(chi2_per_dof_at_stated_noise=3.0, rms_position_mm=1.0,
                            stated_floor_position_mm=0.5)
    after = gp.StatedBlock(chi2_per_dof_at_stated_noise=1.0, rms_position_mm=0.6,
                           stated_floor_position_mm=0.5)
    assert gp.share_explained(before, after, excluded_share=0.25) == pytest.approx(0.75)
    after = replace(after, rms_position_mm=0.995)  # χ² fell but the RMS did not move
    assert gp.share_explained(before, after, excluded_share=0.25) == 0.0


def test_flagged_pairs_in_one_time_block_are_structure_not_outliers():
    rec = simulate_recording(3, 40.0)
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), Settings())
    data = prepare(pairs, Settings(), rec.stream_a)
    rng = np.random.default_rng(0)
    scattered = rng.random(data.n) < 0.04
    assert ex.flagged_clustering(data, scattered).clustered is False
    burst = np.zeros(data.n, dtype=bool)
    burst[(data.t > 10) & (data.t < 13)] = True
    cl = ex.flagged_clustering(data, burst)
    # one run lasting seconds: a change, not a burst of glitches (timeline.flagged_runs)
    assert cl.clustered and cl.in_time and '10-13 s' in cl.where and 'lasting' in cl.where
    assert cl.runs.changes and not cl.runs.bursts


def test_a_local_error_is_sized_where_it_acts_with_the_noise_taken_off():
    rec = simulate_recording(3, 40.0)
    pairs, _ = pair_for(rec.stream_a, list(rec.streams_b), Settings())
    data = prepare(pairs, Settings(), rec.stream_a)
    rng = np.random.default_rng(1)
    e = rng.normal(scale=5e-4, size=(data.n, data.m))        # 0.5 mm noise
    hot = (data.t > 10) & (data.t < 16)
    bump = np.exp(-0.5 * ((data.t - 13.0) / 1.0) ** 2) * 4e-3
    e[:, 0] += np.where(hot, bump, 0.0)
    size = ex.local_error_size(data, e, hot)
    assert size.max_mm == pytest.approx(4.0, rel=0.2)
    assert 9.5 < size.from_s < size.to_s < 16.5
    # noise alone is small
    assert ex.local_error_size(data, rng.normal(scale=5e-4, size=e.shape),
                               hot).max_mm < 0.8
