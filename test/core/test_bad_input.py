"""
Bad input at the core API (calibrate, pair_streams, validate_stream, calibrate_streams).

Each case must raise the right ``CoregError`` subclass with a one-line message that names the
problem; never a bare numpy / LinAlg / attribute error from deep inside the estimator.
"""

from dataclasses import replace

from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.pairing import pair_streams, validate_stream
from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import ConfigError, CoregError, InputError, TooFewPairsError
from coreg_ros.core.settings import Settings
from coreg_ros.sim import simulate_pairs, simulate_recording
import numpy as np
import pytest

MODELS = ('full_pose', 'position_only', 'three_marker')
GAP = 50_000_000


def raises(exc, fn, *words):
    """Call fn, expect exc (and nothing else), one line naming every word (case-insensitive)."""
    try:
        fn()
    except CoregError as e:
        assert isinstance(e, exc), f'{type(e).__name__} instead of {exc.__name__}: {e}'
        msg = str(e)
        assert msg and '\n' not in msg, repr(msg)
        for w in words:
            assert w.lower() in msg.lower(), f'{w!r} not in {msg!r}'
        assert isinstance(e, ValueError)
        return msg
    except Exception as e:  # any other type is the failure under test
        pytest.fail(f'{type(e).__name__} escaped instead of {exc.__name__}: {e}')
    pytest.fail(f'no error; expected {exc.__name__}')


@pytest.fixture(scope='module')
def pairs():
    return {m: simulate_pairs(np.random.default_rng(1), 60, m)[0] for m in MODELS}


@pytest.fixture(scope='module')
def rec():
    return simulate_recording(3, 4.0, 'full_pose')


def _rows(n, i, value, like):
    out = np.array(like, dtype=float)
    out[i] = value
    return out


# ---------------------------------------------------------------------------------------------
# calibrate(pairs)
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('model', MODELS)
def test_calibrate_bad_quaternions(pairs, model):
    p = pairs[model]
    s = Settings(model=model)
    raises(InputError, lambda: calibrate(replace(p, quat_a=_rows(60, 7, np.nan, p.quat_a)), s),
           'device A orientation', 'NaN', 'index 7')
    raises(InputError, lambda: calibrate(replace(p, quat_a=_rows(60, 3, 0.0, p.quat_a)), s),
           'device A orientation', 'not unit length', 'norm 0', 'index 3')
    raises(InputError, lambda: calibrate(replace(p, quat_a=1.5 * p.quat_a), s),
           'device A orientation', 'not unit length', 'norm 1.5')
    raises(InputError, lambda: calibrate(replace(p, quat_a=p.quat_a[:, :3]), s),
           'device A orientation', 'shape')
    if model == 'full_pose':
        raises(InputError, lambda: calibrate(replace(p, quat_b=_rows(60, 2, np.inf, p.quat_b)),
                                             s), 'device B orientation', 'inf')
        raises(InputError, lambda: calibrate(replace(p, quat_b=np.zeros((60, 4))), s),
               'device B orientation', 'not unit length')


@pytest.mark.parametrize('model', MODELS)
def test_calibrate_bad_positions(pairs, model):
    p = pairs[model]
    s = Settings(model=model)
    raises(InputError, lambda: calibrate(replace(p, pos_a=_rows(60, 5, np.nan, p.pos_a)), s),
           'device A position', 'NaN', 'pair 5')
    raises(InputError, lambda: calibrate(replace(p, pos_b=_rows(60, 9, np.inf, p.pos_b)), s),
           'device B position', 'pair 9')
    raises(InputError, lambda: calibrate(replace(p, pos_a=p.pos_a[:, :2]), s), 'shapes', model)
    raises(InputError, lambda: calibrate(replace(p, pos_b=np.swapaxes(p.pos_b, 0, 1)), s),
           'shapes', model)


def test_calibrate_model_and_data_disagree(pairs):
    raises(InputError, lambda: calibrate(pairs['position_only'], Settings(model='three_marker')),
           'shapes', 'three_marker', '(60, 3, 3)')
    raises(InputError, lambda: calibrate(pairs['three_marker'], Settings(model='full_pose')),
           'shapes', 'full_pose')


def test_full_pose_without_b_orientation(pairs):
    p = replace(pairs['full_pose'], quat_b=None)
    raises(InputError, lambda: calibrate(p, Settings(model='full_pose')),
           'full_pose', 'device B orientation', 'position_only')
    # the same data is fine for the position-only model
    assert calibrate(p, Settings(model='position_only')).success


@pytest.mark.parametrize('model', MODELS)
def test_too_few_pairs(pairs, model):
    p = pairs[model]
    few = replace(p, stamps=p.stamps[:10], pos_a=p.pos_a[:10], quat_a=p.quat_a[:10],
                  pos_b=p.pos_b[:10], quat_b=None if p.quat_b is None else p.quat_b[:10])
    raises(TooFewPairsError, lambda: calibrate(few, Settings(model=model)),
           'only 10 pairs', 'at least 30')
    # even with min_pairs lowered, fewer pairs than parameters / residuals per pair is refused
    two = replace(few, stamps=few.stamps[:2], pos_a=few.pos_a[:2], quat_a=few.quat_a[:2],
                  pos_b=few.pos_b[:2], quat_b=None if few.quat_b is None else few.quat_b[:2])
    raises(TooFewPairsError, lambda: calibrate(two, Settings(model=model, min_pairs=3)),
           'only 2 pairs')


def test_bad_a_var_scale(pairs):
    p = pairs['full_pose']
    raises(InputError, lambda: calibrate(replace(p, a_var_scale=np.zeros(60)), Settings()),
           'a_var_scale', 'positive')
    raises(InputError, lambda: calibrate(replace(p, a_var_scale=np.ones(59)), Settings()),
           'a_var_scale', 'one per pair')


@pytest.mark.parametrize('model', MODELS)
def test_calibrate_quat_a_row_count(pairs, model):
    p = pairs[model]
    raises(InputError, lambda: calibrate(replace(p, quat_a=p.quat_a[:-1]), Settings(model=model)),
           'device A orientation', 'shape')


def test_calibrate_quat_b_row_count(pairs):
    p = pairs['full_pose']
    raises(InputError, lambda: calibrate(replace(p, quat_b=p.quat_b[:-1]), Settings()),
           'device B orientation', 'shape')


def test_calibrate_single_quaternion_for_all_pairs(pairs):
    p = pairs['full_pose']
    raises(InputError, lambda: calibrate(replace(p, quat_a=p.quat_a[0]), Settings()),
           'device A orientation', 'shape')


# ---------------------------------------------------------------------------------------------
# validate_stream / pair_streams
# ---------------------------------------------------------------------------------------------

def _both(stream, b, *words, exc=InputError):
    """Expect the same error from validate_stream and from pair_streams."""
    raises(exc, lambda: validate_stream(stream, 'stream_a'), 'stream_a', *words)
    raises(exc, lambda: pair_streams(stream, b, max_gap_ns=GAP), 'stream_a', *words)


def test_stream_duplicate_stamps(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    st = a.stamps.copy()
    st[10] = st[9]
    _both(replace(a, stamps=st), b, 'duplicate stamp', 'index 10', 'coreg fix-bag',
          '--drop-duplicates')


def test_stream_clock_jump_backwards(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    st = a.stamps.copy()
    st[20:] -= 500_000_000
    _both(replace(a, stamps=st), b, 'backwards', 'index 20', 'clock jump', '490.000 ms')


def test_stream_out_of_order(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    order = np.arange(len(a))
    order[[30, 31]] = order[[31, 30]]
    _both(replace(a, stamps=a.stamps[order]), b, 'backwards', 'index 31', 'out-of-order')


@pytest.mark.parametrize('value, words', [
    (np.nan, ('NaN', 'index 5')),
    (0.0, ('not unit length', 'norm 0', 'index 5')),
    (1.5, ('not unit length', 'index 5')),
])
def test_stream_bad_quaternion(rec, value, words):
    a, b = rec.stream_a, rec.streams_b[0]
    q = a.quat_wxyz.copy()
    q[5] = value if value != 1.5 else 1.5 * q[5]
    _both(replace(a, quat_wxyz=q), b, 'quat_wxyz', *words)


def test_stream_bad_b_quaternion_only_matters_for_full_pose(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    bad_b = replace(b, quat_wxyz=np.zeros_like(b.quat_wxyz))
    raises(InputError, lambda: pair_streams(a, bad_b, max_gap_ns=GAP), 'stream_b',
           'not unit length')
    pairs, _ = pair_streams(a, bad_b, max_gap_ns=GAP, with_orientation_b=False)
    assert pairs.quat_b is None and len(pairs) > 0


@pytest.mark.parametrize('field, value, words', [
    ('position', lambda a: a.position[:, :2], ('position', 'shape')),
    ('quat_wxyz', lambda a: a.quat_wxyz[:-1], ('quat_wxyz', 'shape')),
    ('stamps', lambda a: a.stamps[:, None], ('stamps', 'shape (N,)')),
    ('stamps', lambda a: a.stamps.astype(float), ('integer nanoseconds',)),
    ('quat_wxyz', lambda a: None, ('quat_wxyz', 'shape')),
    ('position', lambda a: np.where(np.arange(len(a))[:, None] == 4, np.nan, a.position),
     ('position', 'NaN', 'index 4')),
    ('receive_stamps', lambda a: a.stamps[:-1], ('receive_stamps', 'shape')),
])
def test_stream_wrong_shapes_and_types(rec, field, value, words):
    a, b = rec.stream_a, rec.streams_b[0]
    _both(replace(a, **{field: value(a)}), b, *words)


def test_stream_empty(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    empty = replace(a, stamps=a.stamps[:0], position=a.position[:0], quat_wxyz=a.quat_wxyz[:0])
    _both(empty, b, 'empty')


def test_pair_streams_bad_arguments(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    raises(InputError, lambda: pair_streams(a, b, max_gap_ns=0.05), 'max_gap_ns',
           'integer number of nanoseconds')
    raises(InputError, lambda: pair_streams(a, b, max_gap_ns=-1), 'max_gap_ns', '>= 0')
    raises(InputError, lambda: pair_streams(a, b, max_gap_ns=GAP, offset_ns=0.01), 'offset_ns')
    raises(InputError, lambda: pair_streams(a, [b, b], max_gap_ns=GAP), 'streams_b',
           'three marker streams')


def test_pipeline_too_few_pairs_reports_why(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    # B stamped 10 s late with the offset fixed at 0: nothing pairs
    late = replace(b, stamps=b.stamps + 10 * 10**9)
    fixed = Settings(estimate_time_offset=False)
    msg = raises(TooFewPairsError, lambda: calibrate_streams(a, late, fixed),
                 'only 0 pairs', 'after_last_a')
    assert 'unpaired B' in msg
    # estimated (the default), the coarse search finds the 10 s
    result, _ = calibrate_streams(a, late, Settings())
    assert abs(result.time_offset.value_s - 10.0) < 3 * result.time_offset.sigma_s + 1e-6


def test_pipeline_bad_stream_is_an_input_error(rec):
    a, b = rec.stream_a, rec.streams_b[0]
    st = b.stamps.copy()
    st[3] = st[2]
    raises(InputError, lambda: calibrate_streams(a, replace(b, stamps=st), Settings()),
           'stream_b', 'duplicate stamp')


@pytest.mark.parametrize('topics', [
    {'topic_a': '/device_a/pose', 'topic_b': '/device_a/pose'},
    {'model': 'three_marker', 'topic_b': ('/m1', '/m2', '/m1')},
    {'model': 'three_marker', 'topic_a': '/m3', 'topic_b': ('/m1', '/m2', '/m3')},
])
def test_one_topic_for_two_devices_is_refused(topics):
    """A calibrated against itself fits perfectly: a silent wrong answer, refused instead."""
    with pytest.raises(ConfigError, match='given for more than one device') as info:
        Settings(**topics)
    assert '\n' not in str(info.value)


@pytest.mark.parametrize('sigma', [(2.0, 0.0087), (0.002, 5.0), (2.0, 5.0)])
@pytest.mark.parametrize('name', ['sigma_a', 'sigma_b'])
def test_noise_in_other_units_is_refused(name, sigma):
    """σ in mm or degrees read as m and rad: named as a units problem, not as bad motion."""
    with pytest.raises(ConfigError, match='give metres and radians'):
        Settings(**{name: sigma})
    Settings(**{name: (0.9, 0.45)})  # large, but still a noise
