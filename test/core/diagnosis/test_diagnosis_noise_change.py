"""A noise change at an instant is white noise grown; a smooth excess is structure, not noise."""

from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.diagnosis.structure import SMOOTH_LAG1, smoothness
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
import numpy as np
import pytest


def test_smoothness_tells_grown_noise_from_a_smooth_error_beside_a_smooth_rest():
    # Monte Carlo: white noise × 1.5-3 against a smooth error (a random walk low-passed over
    # ~1 s at 50 Hz) of the same excess, both beside a rest that holds a smooth error of its
    # own (what no fitted effect took off, everywhere): only the excess's smoothness counts
    rng = np.random.default_rng(2710)
    for _ in range(50):
        n, m = 1000, 3
        kernel = np.ones(50) / 50.0
        smooth = np.stack([np.convolve(rng.normal(size=n + 49), kernel, 'valid')
                           for _ in range(m)], axis=1)
        smooth *= 0.5 / smooth.std()
        rest = rng.normal(size=(n, m)) + smooth
        factor = rng.uniform(1.5, 3.0)
        grown = rng.normal(size=(n, m)) * factor + smooth
        excess = np.sqrt(factor ** 2 - 1.0)
        lagged = np.stack([np.convolve(rng.normal(size=n + 49), kernel, 'valid')
                           for _ in range(m)], axis=1)
        structured = rng.normal(size=(n, m)) + smooth + lagged * excess / lagged.std()
        assert smoothness(grown, rest, rest_lag=True) < 0.2
        assert smoothness(structured, rest, rest_lag=True) > SMOOTH_LAG1


@pytest.mark.parametrize('k', range(2))
def test_a_noise_change_is_still_found_where_it_is_noise(k):
    # Monte Carlo over random draws: B's noise × 1.5-3 from a random instant on
    rng = np.random.default_rng(2720 + k)
    factor = float(rng.uniform(1.5, 3.0))
    rec = simulate_recording(int(rng.integers(1000)), 30.0,
                             effects=[parse_effect(f'noise_step={factor:.3f}')])
    r = diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report.as_dict()
    names = [e['name'] for e in r['effects']]
    assert names[:1] == ['noise_step'], (names, r['not_significant'])
    assert r['effects'][0]['estimate']['factor'] == pytest.approx(factor, rel=0.2)
