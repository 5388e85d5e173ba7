"""Noise shapes, practical significance and restricted rigs (issue 26 items 4-5, issue 22)."""

from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
import numpy as np
import pytest


def _diagnosed(seed, specs, duration=25.0, motion='diverse'):
    rec = simulate_recording(seed, duration, effects=[parse_effect(s) for s in specs],
                             motion=motion)
    report = diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report
    return rec, report.as_dict()


def test_noise_larger_along_one_axis_of_b_is_anisotropic_not_distance_noise():
    rng = np.random.default_rng(2640)
    factor = float(rng.uniform(2.0, 3.5))
    rec, r = _diagnosed(int(rng.integers(1000)), [f'anisotropic_noise={factor:.3f}'])
    names = [e['name'] for e in r['effects']]
    assert names == ['anisotropic_noise']
    first = r['effects'][0]
    assert first['kind'] == 'noise'
    est, truth = first['estimate'], rec.truth.effects[0]
    assert max(est['factors']) == pytest.approx(factor, rel=0.2)
    # its direction in B's base (up to sign), the other two axes at the stated noise
    axis = np.asarray(est['axes'])[int(np.argmax(est['factors']))]
    assert abs(float(axis @ np.asarray(truth['axis']))) > np.cos(np.radians(10))
    assert sorted(est['factors'])[:2] == pytest.approx([1.0, 1.0], abs=0.2)


def test_an_offset_too_small_to_matter_is_never_reported_as_found():
    # 0.1-0.3 ms moves no pair by a tenth of the stated noise at the simulator's speeds (the
    # issue's clean recording got a 0.14 ms time_offset): at most listed as not significant
    rng = np.random.default_rng(2650)
    tau = float(rng.uniform(1e-4, 3e-4))
    rec, r = _diagnosed(int(rng.integers(1000)), [f'time_offset={tau:.5f}'])
    assert r['effects'] == []
    small = {e['name']: e for e in r['not_significant']}
    assert set(small) <= {'time_offset'}


@pytest.mark.parametrize('rig, spec', [('scara', None), ('gantry', 'time_offset'),
                                       ('turntable', 'time_offset')])
def test_a_restricted_rig_is_diagnosed_and_held_directions_are_no_effect(rig, spec):
    rng = np.random.default_rng(2660 + len(rig))
    tau = float(rng.uniform(0.02, 0.05))
    specs = [f'time_offset={tau:.4f}'] if spec else []
    rec, r = _diagnosed(int(rng.integers(1000)), specs, motion=rig)
    names = [e['name'] for e in r['effects']]
    if spec is None:
        # nothing but the noise: what the motion cannot determine is no effect
        assert names == [] and not r['gap_detected']
    else:
        assert names == ['time_offset']
        assert r['effects'][0]['estimate']['tau_s'] == pytest.approx(tau, rel=0.1)


def test_a_recording_well_inside_its_stated_noise_gets_no_outliers_or_structure():
    # noise 0.2-0.4 of the stated (the simulated ETH control reads 0.29): no pair lies off the
    # stated noise, so none is an outlier, and nothing structured is there to find
    rng = np.random.default_rng(2670)
    factor = float(rng.uniform(0.2, 0.4))
    rec, r = _diagnosed(int(rng.integers(1000)), [f'noise_scale={factor:.3f}'])
    names = [e['name'] for e in r['effects']]
    assert names == ['noise_scale']
    assert r['effects'][0]['estimate']['factor'] == pytest.approx(factor, rel=0.2)
