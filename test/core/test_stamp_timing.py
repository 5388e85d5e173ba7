"""Timing read from the stamps (issue 11, item 3): rate, scatter, drops, gaps, latency."""

from coreg_ros.core.diagnosis import diagnose_streams
from coreg_ros.core.diagnosis.stamps import stamp_timing, stamps_report
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import PoseStream
from coreg_ros.sim import simulate_recording
from coreg_ros.sim.injected import parse_effect, TimestampJitter
import numpy as np
import pytest


def _stream(stamps, receive=None):
    n = len(stamps)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return PoseStream(np.asarray(stamps, dtype=np.int64), np.zeros((n, 3)), q, 'f',
                      receive_stamps=None if receive is None else np.asarray(receive, np.int64))


def test_clean_clock_regular_stamps():
    t = stamp_timing(_stream(1_000_000_000 + np.arange(3000) * 10_000_000), 'A')
    assert t.nominal_rate_hz == pytest.approx(100.0)
    assert t.interval_scatter_s < 1e-9 and not t.jittered
    assert t.dropped == 0 and t.gaps == [] and t.backward == t.duplicate == 0
    assert t.latency is None


def test_drops_gaps_backward_duplicates_and_latency():
    rng = np.random.default_rng(0)
    k = np.arange(5000)
    keep = rng.random(5000) > 0.05                      # 5 % dropped
    keep[2000:2300] = False                             # a 3 s gap at 100 Hz
    stamps = (k[keep] * 10_000_000).astype(np.int64)
    stamps = np.insert(stamps, 100, stamps[100])        # one duplicate
    stamps[500], stamps[501] = stamps[501], stamps[500]  # one pair swapped
    receive = stamps + 4_000_000 + rng.integers(0, 200_000, stamps.size)
    t = stamp_timing(_stream(stamps, receive), 'B')
    assert t.duplicate == 1 and t.backward == 1
    assert len(t.gaps) == 1 and t.gaps[0][1] == pytest.approx(3.0, abs=0.1)
    expected = int(np.sum(~keep)) - 300
    assert abs(t.dropped - expected) <= 0.05 * expected + 3
    assert t.latency.median_s == pytest.approx(0.0041, abs=2e-4)
    assert 'gaps' in t.text and 'receive latency' in t.text


@pytest.mark.parametrize('sigma', [0.0007, 0.002, 0.005])
def test_jitter_read_from_stamps(sigma):
    rec = simulate_recording(3, 60.0, effects=[TimestampJitter(sigma, 0.1)])
    rep = stamps_report(rec.stream_a, list(rec.streams_b))
    b = rep.devices[1]
    assert rep.jittered == ['B'] and not rep.devices[0].jittered
    assert b.stamp_jitter_s == pytest.approx(sigma, rel=0.1)
    assert b.dropped == pytest.approx(rec.truth.effects[0]['n_dropped'], rel=0.05)


def test_stamp_only_jitter_is_named_when_residuals_cannot_show_it():
    # 0.7 ms of stamp jitter under slow motion: invisible in the residuals, plain in the stamps
    rec = simulate_recording(4, 40.0, effects=[TimestampJitter(0.0007, 0.05)])
    r = diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report.as_dict()
    assert r['gap_detected'] is True
    assert r['effects'][0]['name'] == 'timestamp_jitter'
    assert r['effects'][0]['kind'] == 'noise'
    assert r['effects'][0]['estimate']['sigma_s'] == pytest.approx(0.0007, rel=0.15)
    assert r['stamps']['devices'][1]['dropped'] > 0


def test_clean_recording_has_no_stamp_issue():
    rec = simulate_recording(2, 30.0)
    r = diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report.as_dict()
    assert r['stamps']['issues'] is False and r['effects'] == []


@pytest.mark.parametrize('tau', [0.45, -0.8, 2.5])
def test_large_offset_found_by_the_coarse_search_beside_another_error(tau):
    rec = simulate_recording(6, 40.0, effects=[parse_effect(f'time_offset={tau}'),
                                               parse_effect('scale=0.01')])
    r = diagnose_streams(rec.stream_a, list(rec.streams_b), Settings()).report.as_dict()
    names = [e['name'] for e in r['effects']]
    assert names[0] == 'time_offset' and 'scale' in names
    est = r['effects'][0]['estimate']
    assert est['tau_s'] == pytest.approx(tau, abs=5 * est['sigma_s'] + 1e-4)
    # the gap before is measured at the offset the user gave (none)
    assert r['gap_before']['chi2_per_dof_at_stated_noise'] > 50
    assert r['gap_after']['share_of_excess_explained'] > 0.9


def test_stamps_rounded_to_milliseconds_are_not_jitter():
    # a CSV export in ms: a 30 Hz device's intervals alternate 33 and 34 ms
    t = np.round(np.arange(2000) * (1e9 / 30.0) / 1e6).astype(np.int64) * 1_000_000
    rep = stamp_timing(_stream(t), 'B')
    assert rep.quantum_s == pytest.approx(1e-3)
    assert not rep.jittered and 'rounded to 1 ms' in rep.text
    rng = np.random.default_rng(1)
    noisy = t + np.round(rng.normal(0, 2e-3, t.size) * 1e3).astype(np.int64) * 1_000_000
    assert stamp_timing(_stream(np.sort(noisy)), 'B').jittered
