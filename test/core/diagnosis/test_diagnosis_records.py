"""The diagnosis report's records (as_dict: the JSON keys, in order) and the effect registry."""

from dataclasses import dataclass, fields, is_dataclass
import json
from typing import Optional

from coreg_ros.core.diagnosis import EFFECT_NAMES
from coreg_ros.core.diagnosis.effects import CandidateEffect, CANDIDATES
from coreg_ros.core.diagnosis.effects.finding import COARSE_SEARCH, Finding, STAMPS
from coreg_ros.core.diagnosis.effects.local import ClusteredOutliers
from coreg_ros.core.diagnosis.excess import LocalSize
from coreg_ros.core.diagnosis.record import apart, inline, keyed, optional, Record
from coreg_ros.core.diagnosis.selection import CandidateScore
from coreg_ros.core.diagnosis.stamps import StampJitter
import pytest


@dataclass(frozen=True)
class _Inner(Record):
    a: float
    b: Optional[float] = optional()


@dataclass(frozen=True, kw_only=True)
class _Outer(Record):
    first: str = keyed('from')
    inner: _Inner = inline()
    tail: _Inner = inline('_tail')
    items: tuple
    skipped: Optional[int] = apart()
    maybe: Optional[int] = optional()


def test_record_as_dict_keys_in_order():
    r = _Outer(first='x', inner=_Inner(1.0, 2.0), tail=_Inner(3.0), items=(_Inner(4.0), 5),
               skipped=7)
    doc = r.as_dict()
    assert list(doc) == ['from', 'a', 'b', 'a_tail', 'items']
    assert doc == {'from': 'x', 'a': 1.0, 'b': 2.0, 'a_tail': 3.0, 'items': [{'a': 4.0}, 5]}
    assert _Outer(first='x', inner=_Inner(1.0), tail=_Inner(3.0), items=(), maybe=0
                  ).as_dict()['maybe'] == 0      # optional: only None is left out
    json.dumps(doc)


def test_registry_one_class_per_effect():
    assert tuple(EFFECT_NAMES) == tuple(n for n in CANDIDATES if n != 'non_stationary')
    for name, cls in CANDIDATES.items():
        assert cls.name == name and issubclass(cls, CandidateEffect)
        assert cls.kind in ('structured', 'noise')
        assert cls.device in ('A', 'B', 'A and B', 'A or B', 'link')
        assert cls.simpler is None or CANDIDATES[cls.simpler].acts_on == cls.acts_on
        if cls.acts_on in ('time', 'mean'):
            assert cls.term is not None and not cls.var_params
        elif cls.acts_on == 'variance':
            assert cls.term is None and cls.var_params
        if cls.acts_on is not None:
            # an estimate: a frozen record whose fields are its JSON keys, text among them
            assert is_dataclass(cls) and 'text' in {f.name for f in fields(cls)}
            assert cls.size.__func__ is not CandidateEffect.size.__func__


def test_clock_estimates_shift_with_the_coarse_search():
    tau = CANDIDATES['time_offset'](tau_s=0.01, sigma_s=1e-4, text='')
    moved = tau.shifted(0.5)
    assert moved.tau_s == pytest.approx(0.51) and moved.text == '510.00 ± 0.10 ms'
    drift = CANDIDATES['clock_drift'](ppm=100.0, sigma_ppm=1.0, offset_at_start_s=0.0,
                                      sigma_offset_at_start_s=1e-4, offset_at_end_s=0.006,
                                      text='100.0 ± 1.0 ppm')
    assert drift.shifted(0.5).offset_at_end_s == pytest.approx(0.506)
    assert drift.shifted(0.5).text == drift.text
    noise = CANDIDATES['noise_scale'](factor=2.0, sigma=0.1, text='× 2.000 ± 0.100')
    assert noise.shifted(0.5) is noise


def test_finding_places_its_source_and_renaming():
    tau = CANDIDATES['time_offset'](tau_s=0.01, sigma_s=1e-4, text='10.00 ± 0.10 ms')
    found = Finding.of(tau, source=COARSE_SEARCH)
    assert list(found.as_dict()) == ['name', 'kind', 'device', 'estimate', 'source',
                                     'held_out_gain', 'held_out_gain_per_residual',
                                     'blocks_improved', 'blocks']
    assert found.device == 'B'  # B's clock against A's
    stamps = StampJitter(sigma_s=1e-3, sigma_sigma_s=1e-5, device='B', dropped=3, gaps=[],
                         text='1.00 ms')
    read = Finding(name='timestamp_jitter', kind='noise', device='B', estimate=stamps,
                   source=STAMPS)
    assert list(read.as_dict())[:5] == ['name', 'kind', 'device', 'source', 'estimate']
    local = ClusteredOutliers.of(12, 0.006, 'time 28-32 s', False).sized(
        LocalSize(max_mm=3.8, rms_mm=3.4, noise_mm=0.5, from_s=29.0, to_s=30.0))
    renamed = Finding.of(local, renamed_from='outliers', held_out_gain=105.6)
    doc = renamed.as_dict()
    assert doc['name'] == 'non_stationary' and doc['kind'] == 'structured'
    assert list(doc)[-1] == 'from' and doc['from'] == 'outliers'
    assert list(doc['estimate']) == ['flagged_pairs', 'flagged_share', 'where', 'at_cap', 'text',
                                     'max_mm', 'rms_mm', 'window_s']
    assert doc['estimate']['text'].endswith('; up to 3.80 mm (RMS 3.40 mm) in 29-30 s')


def test_every_effect_says_whose_it_is():
    # issue 23, item 5: the effect's device, as the simulator injects it (sim.injected)
    whose = {'time_offset': 'B', 'clock_drift': 'B', 'field_distortion': 'B',
             'distance_noise': 'B', 'scale': 'B', 'backlash': 'A', 'link_flex': 'link',
             'noise_scale': 'A and B', 'clock_step': 'B', 'anisotropic_noise': 'B',
             'noise_step': 'B'}
    for name, device in whose.items():
        assert CANDIDATES[name].device == device, name
    # what the residuals alone cannot place says so (the stamps name their device)
    for name in ('outliers', 'timestamp_jitter', 'non_stationary', 'pose_step'):
        assert CANDIDATES[name].device == 'A or B', name


def test_screened_candidate_keeps_its_keys_order():
    kept = CandidateScore(name='scale', held_out_gain=12.0, held_out_gain_per_residual=0.1,
                          blocks_improved=5, blocks=5, accepted_test=True, reason='passes')
    assert list(kept.as_dict()) == ['name', 'held_out_gain', 'held_out_gain_per_residual',
                                    'blocks_improved', 'blocks', 'accepted_test', 'reason']
    screened = CandidateScore(name='backlash', held_out_gain=None,
                              held_out_gain_per_residual=None, blocks_improved=0, blocks=5,
                              accepted_test=False, reason='screened',
                              predicted_in_sample_gain=1.5)
    doc = screened.as_dict()
    assert screened.screened and not kept.screened
    assert list(doc) == ['name', 'held_out_gain_per_residual', 'blocks_improved', 'blocks',
                         'accepted_test', 'reason', 'screened', 'predicted_in_sample_gain',
                         'held_out_gain']
    assert doc['held_out_gain'] is None and doc['predicted_in_sample_gain'] == 1.5
