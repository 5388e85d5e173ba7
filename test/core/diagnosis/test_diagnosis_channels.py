"""Practical significance judged per channel: what an effect claims, and no channel made worse."""

from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.diagnosis.channels import channel_reasons, MIN_RMS_GAIN, SIZE_FLOOR
from coreg_ros.core.diagnosis.significance import EffectTest
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect
import numpy as np
import pytest


def _test(position, rotation):
    return EffectTest(name='link_flex', held_out_gain=100.0, blocks_improved=5, blocks=5,
                      share_of_gap=0.5, rms_gain_position=position,
                      rms_gain_rotation=rotation, passes=True, reason='passes')


def test_an_effect_that_lowers_one_channel_and_raises_another_is_refused():
    # the simulated ETH control's flex: position RMS -4.8 %, rotation RMS +8.4 %
    moved = {'position': 5.0, 'rotation': 3.0}
    reasons = channel_reasons(moved, _test(0.048, -0.084))
    assert len(reasons) == 1 and 'raises the held-out rotation RMS' in reasons[0]
    # the same gains without the rise pass
    assert channel_reasons(moved, _test(0.048, 0.0)) == []
    # a rise below the floor is the held-out estimate's own scatter, not a channel made worse
    assert channel_reasons(moved, _test(0.048, -0.5 * MIN_RMS_GAIN)) == []


def test_an_effect_is_judged_on_the_channel_it_moves():
    # it moves only positions: a rotation gain cannot stand in for the position it claims
    moved = {'position': 5.0, 'rotation': 0.5 * SIZE_FLOOR}
    reasons = channel_reasons(moved, _test(0.1 * MIN_RMS_GAIN, 0.2))
    assert len(reasons) == 1 and 'position it moves' in reasons[0]
    assert channel_reasons(moved, _test(2 * MIN_RMS_GAIN, 0.0)) == []
    # it moves nothing by a tenth of the noise: not significant whatever the gains
    small = {'position': 0.5 * SIZE_FLOOR, 'rotation': 0.5 * SIZE_FLOOR}
    assert 'moves no pair' in channel_reasons(small, _test(0.2, 0.2))[0]


@pytest.mark.parametrize('k', range(3))
def test_a_real_flex_or_offset_gains_where_it_claims_and_raises_no_channel(k):
    # Monte Carlo over random draws: medium flexes and offsets (both channels on a full pose)
    # are found, and the re-test in the final model shows no channel made worse
    rng = np.random.default_rng(2690 + k)
    spec = (f'link_flex={rng.uniform(0.8, 1.5):.3f}' if k < 2
            else f'time_offset={rng.uniform(0.008, 0.02):.4f}')
    rec = simulate_recording(int(rng.integers(1000)), 30.0, effects=[parse_effect(spec)])
    r = diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report.as_dict()
    found = {e['name']: e for e in r['effects']}
    name = spec.split('=')[0]
    assert name in found, (spec, list(found), r['not_significant'])
    gains = found[name]['held_out_rms_gain']
    assert max(gains.values()) >= MIN_RMS_GAIN
    assert min(gains.values()) > -MIN_RMS_GAIN
