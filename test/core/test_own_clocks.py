"""
Clocks that share no stamps (issue 23, item 4).

Each device stamps with its own clock: offsets of minutes to an hour, one device counting from
boot against one on epoch time. The offset search considers every lag at which the devices'
signals overlap; the fine step pins τ where the motion determines it (judging the motion as
recorded, also for trackers whose stated noise dominates a short velocity window); where it
cannot, the coarse estimate is used with a σ that covers its peak, said as such; where no lag
gives a clear peak, the error says how to give the offset.
"""

from dataclasses import replace
import glob
import os

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import CoregError
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import PoseStream
from coreg_ros.sim import simulate_recording
import numpy as np
import pytest
from test_spatiotemporal import _still_poses_recording

#: Where the real three-phone recording lives on the team's machines (never committed).
TANGO = '/work/shared/data/real/eth_hand_eye/tango_triplet_hard'


def _moved(stream: PoseStream, seconds: float) -> PoseStream:
    return replace(stream, stamps=stream.stamps + np.int64(round(seconds * 1e9)))


def _draws(seed: int, n: int):
    """Random recordings: offsets 100 s to 1 h either way, rates and noises of real trackers."""
    rng = np.random.default_rng(seed)
    for k in range(n):
        tau = float(np.exp(rng.uniform(np.log(100.0), np.log(3600.0))) * rng.choice([-1, 1]))
        rate_a, rate_b = (float(r) for r in rng.choice([30.0, 60.0, 100.0], size=2))
        sigma_a = (float(10 ** rng.uniform(-4, -2.3)), float(10 ** rng.uniform(-3.5, -1.8)))
        sigma_b = (float(10 ** rng.uniform(-4, -2.3)), float(10 ** rng.uniform(-3.5, -1.8)))
        model = ('full_pose', 'position_only')[k % 2]
        yield int(rng.integers(1 << 30)), tau, rate_a, rate_b, sigma_a, sigma_b, model


@pytest.mark.parametrize('case', list(_draws(2023, 4)), ids=lambda c: f'tau{c[1]:+.0f}s')
def test_offsets_of_minutes_to_an_hour_found_with_no_offset_given(case):
    seed, tau, rate_a, rate_b, sigma_a, sigma_b, model = case
    rec = simulate_recording(seed, 40.0, model, rate_a=rate_a, rate_b=rate_b, sigma_a=sigma_a,
                             sigma_b=sigma_b)
    a, b = rec.streams[rec.topics_a], _moved(rec.streams[rec.topics_b[0]], tau)
    assert b.stamps[0] > a.stamps[-1] or b.stamps[-1] < a.stamps[0]  # no stamp shared
    result, report = calibrate_streams(a, [b], Settings(model=model, sigma_a=sigma_a,
                                                        sigma_b=sigma_b))
    t = result.time_offset
    assert t.estimated and result.success, (t.message, result.verdict)
    assert abs(t.value_s - tau) < 3.0 * t.sigma_s, (t.value_s - tau, t.sigma_s, t.message)
    assert report.n_paired > 0.9 * len(b)


def test_boot_time_against_epoch_time():
    # A counts from its boot (2 h 13 min ago), B stamps on epoch time: τ ≈ 1.7e9 s
    rec = simulate_recording(77, 40.0, 'full_pose', rate_a=60.0, rate_b=30.0,
                             sigma_a=(3e-3, 1e-2), sigma_b=(1e-3, 5e-3))
    a, b = rec.streams[rec.topics_a], rec.streams[rec.topics_b[0]]
    boot = np.int64(8_000 * 10**9)
    a_boot = replace(a, stamps=a.stamps - a.stamps[0] + boot)
    tau = float(a.stamps[0] - boot) * 1e-9
    result, _ = calibrate_streams(a_boot, [b], Settings(sigma_a=(3e-3, 1e-2),
                                                        sigma_b=(1e-3, 5e-3)))
    t = result.time_offset
    assert t.estimated and result.success
    assert abs(t.value_s - tau) < 3.0 * t.sigma_s, (t.value_s - tau, t.sigma_s)


def test_stop_and_go_with_own_clocks_uses_the_coarse_estimate():
    # the tool rests at each pose while recording and moves between them unrecorded: no
    # velocity is ever recorded, so the fine step cannot pin τ; the poses' sequence can
    a, b = _still_poses_recording(43)
    tau = -1234.5
    result, _ = calibrate_streams(a, _moved(b, tau), Settings())
    t = result.time_offset
    assert t.estimated and result.success
    assert 'coarse estimate' in t.message and 'still' in t.message
    assert abs(t.value_s - tau) < 3.0 * t.sigma_s
    assert t.sigma_s >= 0.01  # the peak's width, not the fine step's precision
    # at overlapping stamps the given offset is kept, as before: the peak cannot exclude it
    kept, _ = calibrate_streams(a, b, Settings(time_offset=0.004))
    assert not kept.time_offset.estimated and kept.time_offset.value_s == 0.004


def test_a_static_recording_with_own_clocks_says_how_to_give_the_offset():
    rec = simulate_recording(5, 20.0, 'full_pose', motion='static')
    a, b = rec.streams[rec.topics_a], _moved(rec.streams[rec.topics_b[0]], 600.0)
    with pytest.raises(CoregError) as err:
        calibrate_streams(a, [b], Settings())
    text = str(err.value)
    assert 'did not move' in text and '--time-offset S' in text and '\n' not in text


@pytest.mark.skipif(not os.path.isdir(TANGO), reason='the real three-phone recording is absent')
def test_real_phones_with_own_clocks_calibrated_with_no_offset_given():
    # three Tango phones on one mount, each stamping with its own clock (minutes to an hour
    # apart, no stamp shared); their VIO poses are noisy at the centimetre level
    from coreg_ros.files.csv_poses import read_pose_csv
    phones = {name: read_pose_csv(glob.glob(f'{TANGO}/{name}_*.csv')[0], sort=True).stream
              for name in ('CALIGULA', 'MARS', 'NERO')}
    sigma = (0.05, 0.05)
    found = {}
    for b in ('MARS', 'NERO'):
        result, report = calibrate_streams(phones['CALIGULA'], phones[b],
                                           Settings(sigma_a=sigma, sigma_b=sigma))
        t = result.time_offset
        assert t.estimated and report.n_paired > 0.8 * len(phones[b]), t.message
        found[b] = t
    # the coarse search's lag (r = 0.998) within a second: the phones' clocks differ by
    # 125.1 s and 4583.4 s
    assert abs(found['MARS'].value_s - 125.1) < 1.0
    assert abs(found['NERO'].value_s - 4583.4) < 1.0
