"""Tests of ``coreg diagnose`` and ``coreg validate-diagnosis`` (issue 4)."""

import json

from coreg_ros.cli.main import main
from coreg_ros.files.bag.posebag import write_pose_bag
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
from coreg_ros.sim.validation import draw_case, summarize_validation, validate
import numpy as np
import pytest

KEYS = {'gap_detected', 'effects', 'not_separable', 'gap_before', 'gap_after', 'location',
        'verdict'}


def test_diagnose_bag_json_and_report(tmp_path, capsys):
    rec = simulate_recording(9, 25.0, effects=[parse_effect('outliers=0.03')])
    bag = tmp_path / 'rec'
    write_pose_bag(bag, rec.streams)
    out = tmp_path / 'diag.json'
    rep = tmp_path / 'report'
    assert main(['diagnose', str(bag), '--json', str(out), '--report', str(rep),
                 '--quiet']) == 0
    text = capsys.readouterr().out
    assert 'verdict:' in text and 'outliers' in text
    data = json.loads(out.read_text())
    assert KEYS <= set(data)
    assert data['gap_detected'] is True
    assert data['effects'][0]['name'] == 'outliers'
    assert {'name', 'estimate', 'held_out_gain'} <= set(data['effects'][0])
    # whose effect it is (issue 23, item 5): outliers in the residuals could be either's
    assert data['effects'][0]['device'] == 'A or B'
    assert f"outliers [{data['effects'][0]['kind']}; devices A or B]" in text, text
    assert 'chi2_per_dof' in data['gap_before'] and 'chi2_per_dof' in data['gap_after']
    html = (rep / 'index.html').read_text()
    assert 'img src' in html
    for png in ('residuals_time.png', 'qq.png', 'xcorr.png', 'speed_distance.png',
                'workspace.png', 'candidates.png', 'before_after.png'):
        assert (rep / png).stat().st_size > 1000


def test_diagnose_missing_bag_is_one_line_error(tmp_path, capsys):
    assert main(['diagnose', str(tmp_path / 'nope'), '--quiet']) == 1
    err = capsys.readouterr().err
    assert err.startswith('coreg diagnose: error:') and err.count('\n') == 1


def test_draw_case_ranges():
    rng = np.random.default_rng(0)
    cases = [draw_case(rng) for _ in range(200)]
    clean = [c for c in cases if c['effect'] is None]
    assert 20 < len(clean) < 80
    for c in cases:
        if c['effect']:
            parse_effect(c['spec'])  # every drawn effect is valid for the simulator
            if c['second']:
                parse_effect(c['second']['spec'])
            assert c['size'] in ('small', 'medium', 'large')


def test_validate_tiny(tmp_path):
    out = validate(2, seed=3, duration=(15.0, 20.0))
    s = out['summary']
    assert s['cases'] == 2
    cm = s['confusion_matrix']
    # truths: none and every simulated effect; answers: none, every candidate,
    # non_stationary, not_separable, unexplained structure and a cheap cause
    from coreg_ros.core.diagnosis import EFFECT_NAMES as ANSWERS
    from coreg_ros.sim.injected import ALL_EFFECT_NAMES
    assert len(cm['counts']) == 1 + len(ALL_EFFECT_NAMES)
    assert len(cm['counts'][0]) == len(ANSWERS) + 5
    assert sum(map(sum, cm['counts'])) == 2
    for r in out['results']:
        assert r['effect'] is None or r['spec']
        # the diagnosis never saw the truth; the outcome is one of the answers
        assert r['outcome'] in cm['columns_answer']


def test_summary_counts_not_separable_apart():
    base = {'gap_after': {'position_rms_to_floor': 1.0}, 'gap_detected': True, 'seconds': 1.0,
            'named': ['time_offset'], 'value': 0.01, 'size_ratio': 1.05,
            'kinds': ['structured']}
    results = [
        dict(base, effect='time_offset', size='large', outcome='time_offset', correct=True),
        dict(base, effect='backlash', size='large', outcome='not_separable', correct=False),
        dict(base, effect='scale', size='medium', outcome='none', named=[], value=0.01,
             correct=False, size_ratio=None),
        dict(base, effect=None, size=None, outcome='none', named=[], gap_detected=False,
             value=None, correct=False),
        dict(base, effect='noise_scale', size='large', outcome='outliers', named=['outliers'],
             value=2.0, correct=False, size_ratio=None),
    ]
    s = summarize_validation(results)
    assert s['medium_large_named_correctly_share'] == pytest.approx(1 / 3)
    assert s['medium_large_not_separable'] == 1
    assert s['false_alarm_rate_clean'] == 0.0
    # a noise truth answered with a structured effect is counted
    assert s['noise_reported_as_structured'] == 1 and s['noise_cases'] == 1
    assert s['size_accuracy_medium_large']['time_offset']['within_20pct'] == 1.0


def test_two_effect_cases_and_size_ratios():
    from coreg_ros.sim.validation import _size_ratio
    rng = np.random.default_rng(4)
    cases = [draw_case(rng) for _ in range(300)]
    two = [c for c in cases if c['second']]
    assert 20 < len(two) < 80
    assert all(c['second']['effect'] != c['effect'] for c in two)
    assert any(c['effect'] == 'timestamp_jitter' and c['kwargs']['gaps'] for c in cases)
    assert any(c['effect'] == 'time_offset' and abs(c['value']) >= 0.1 for c in cases)
    assert _size_ratio('noise_scale', {'factor': 2.0}, 2.0) == pytest.approx(1.0)
    assert _size_ratio('scale', {'scale': [0.02, 0, 0]}, [0.01, 0, 0]) == pytest.approx(2.0)
    assert _size_ratio('non_stationary', {'where': ''}, 3.0) is None


def test_validate_command(tmp_path, capsys, monkeypatch):
    import coreg_ros.sim.validation as d
    monkeypatch.setattr(d, 'DURATION', (15.0, 16.0))
    out = tmp_path / 'val.json'
    assert main(['validate-diagnosis', '--cases', '1', '--seed', '5', '--json', str(out),
                 '--quiet']) == 0
    text = capsys.readouterr().out
    assert 'truth \\ answer' in text and 'false alarms' in text
    assert json.loads(out.read_text())['summary']['cases'] == 1
