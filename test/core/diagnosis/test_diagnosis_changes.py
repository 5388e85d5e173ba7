"""Changes in time and mixtures (issue 26, items 2 and 3), on randomly drawn sizes and instants."""

from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
import numpy as np
import pytest


def _diagnosed(seed, specs, duration=30.0, motion='diverse'):
    rec = simulate_recording(seed, duration, effects=[parse_effect(s) for s in specs],
                             motion=motion)
    report = diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report
    return rec, report.as_dict()


@pytest.mark.parametrize('draw', [0, 1])
def test_a_clock_step_is_named_with_its_size_and_instant(draw):
    rng = np.random.default_rng(2600 + draw)
    # a jump of B's clock either way, 20-150 ms (the issue's +28 and -133 ms lie inside)
    step = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.02, 0.15))
    rec, r = _diagnosed(int(rng.integers(1000)), [f'clock_step={step:.4f}'])
    first = r['effects'][0]
    assert first['name'] == 'clock_step' and first['kind'] == 'structured'
    est, truth = first['estimate'], rec.truth.effects[0]
    assert est['step_s'] == pytest.approx(truth['step_s'], rel=0.05)
    assert est['offset_before_s'] == pytest.approx(0.0, abs=0.05 * abs(step))
    # located within a few of B's samples (50 Hz)
    assert abs(est['at_s'] - truth['at_s']) < 0.1
    names = [e['name'] for e in r['effects']]
    assert not {'non_stationary', 'timestamp_jitter', 'clock_drift'} & set(names)


def test_bursts_of_outliers_are_outliers_in_bursts_not_a_change():
    rng = np.random.default_rng(2610)
    fraction = float(rng.uniform(0.03, 0.07))
    rec, r = _diagnosed(int(rng.integers(1000)), [f'outlier_bursts={fraction:.3f}'])
    names = [e['name'] for e in r['effects']]
    assert names[0] == 'outliers' and 'non_stationary' not in names
    est = r['effects'][0]['estimate']
    assert est['fraction'] == pytest.approx(fraction, rel=0.2)
    # the time scale: runs of a few samples (the simulator's 2-6), then back
    assert 2 <= est['run_median'] <= est['run_max'] <= 8
    assert 'bursts' in est['text']


def test_an_offset_beside_outliers_is_named_with_them_both_sized():
    rng = np.random.default_rng(2620)
    offset = float(rng.uniform(0.02, 0.05))
    fraction = float(rng.uniform(0.02, 0.03))
    rec, r = _diagnosed(int(rng.integers(1000)),
                        [f'time_offset={offset:.4f}', f'outliers={fraction:.4f}'])
    found = {e['name']: e['estimate'] for e in r['effects']}
    assert {'time_offset', 'outliers'} <= set(found)
    assert found['time_offset']['tau_s'] == pytest.approx(offset, rel=0.2)
    assert found['outliers']['fraction'] == pytest.approx(fraction, rel=0.2)
    # each keeps its held-out gain with the other present; no third effect is named
    assert len(found) == 2
    assert all(e['held_out_gain'] > 0 for e in r['effects'])
