"""
The Python front door's faults of issue 25 (item 4): each test failed before its fix.

What a new user passes by mistake (a scalar sigma, a prior as a dict or a file, a covariance
of the wrong size or not positive definite, a garbage time offset, a misspelt keyword) gets a
``CoregError`` subclass whose one-line message names the fix, never a raw TypeError,
AttributeError or ValueError. A prior given as a dict or a path is loaded (what ``--prior``
reads), and gives the same result as the loaded ``Prior``.
"""

import coreg_ros as cr
from coreg_ros.files.atomic import write_json
from coreg_ros.files.results import result_to_dict
from coreg_ros.sim import simulate_pairs
import numpy as np
import pytest

SIGMA_A, SIGMA_B = (2e-4, 5e-4), (5e-4, 2e-3)


@pytest.fixture(scope='module')
def data():
    pairs, _, _ = simulate_pairs(np.random.default_rng(7), 400, sigma_a=SIGMA_A,
                                 sigma_b=SIGMA_B)
    previous, _, _ = simulate_pairs(np.random.default_rng(8), 400, sigma_a=SIGMA_A,
                                    sigma_b=SIGMA_B)
    args = (pairs.pos_a, pairs.quat_a, pairs.pos_b, pairs.quat_b)
    # a previous calibration from other data (another rig: only the prior's form matters)
    first = cr.calibrate(previous.pos_a, previous.quat_a, previous.pos_b, previous.quat_b,
                         sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    return args, first


def _fails(args, words, error=cr.CoregError, **kwargs):
    kwargs = {'sigma_a': SIGMA_A, 'sigma_b': SIGMA_B, **kwargs}
    with pytest.raises(error) as e:
        cr.calibrate(*args, **kwargs)
    message = str(e.value)
    assert '\n' not in message
    for w in words:
        assert w in message, message
    return message


def test_a_scalar_sigma_names_the_two_numbers(data):
    args, _ = data
    _fails(args, ['sigma_a', 'two', '(position m, rotation rad)'], cr.ConfigError,
           sigma_a=2e-4)
    _fails(args, ['sigma_b', 'two'], cr.ConfigError, sigma_b='0.001')


def test_a_garbage_time_offset_names_auto_or_seconds(data):
    args, _ = data
    _fails(args, ['time_offset', "'auto'", 'seconds'], cr.ConfigError, time_offset='garbage')
    _fails(args, ['time_offset'], cr.ConfigError, time_offset=float('nan'))


def test_a_misspelt_keyword_names_the_nearest(data):
    args, _ = data
    _fails(args, ['metod', "'method'"], cr.ConfigError, metod='ols')
    _fails(args, ['max_gapp', "'max_gap'"], cr.ConfigError, max_gapp=0.1)


def test_a_prior_as_a_dict_or_a_path_is_loaded(data, tmp_path):
    args, first = data
    doc = result_to_dict(first)
    path = write_json(tmp_path / 'prior.json', doc)
    loaded = cr.load_prior(path)
    want = cr.calibrate(*args, sigma_a=SIGMA_A, sigma_b=SIGMA_B, prior=loaded)
    assert want.prior_check is not None
    for prior in (doc, path, str(path)):
        got = cr.calibrate(*args, sigma_a=SIGMA_A, sigma_b=SIGMA_B, prior=prior)
        np.testing.assert_array_equal(got.params, want.params)
        assert got.prior_check == want.prior_check
    _fails(args, ['prior', 'cannot read', 'no_such.json'], cr.InputError,
           prior=str(tmp_path / 'no_such.json'))
    _fails(args, ['prior', 'Prior'], cr.InputError, prior=[1, 2, 3])


def test_a_prior_covariance_of_the_wrong_size_or_not_positive_definite(data):
    args, first = data
    t0, t1 = first.base_to_base, first.tool_to_marker
    small = cr.UncertainPose(t0.position, t0.quat_wxyz, np.eye(3) * 1e-6)
    with pytest.raises(cr.InputError, match=r'base_to_base must be 6×6 .* shape \(3, 3\)'):
        cr.Prior(small)
    with pytest.raises(cr.InputError, match=r'joint covariance .* 12×12 .* shape \(3, 3\)'):
        cr.Prior(t0, t1, np.eye(3))
    # the same 3×3 in a dict is refused when loaded
    doc = result_to_dict(first)
    doc['base_to_base']['covariance'] = np.eye(3).ravel().tolist()
    doc.pop('cov_joint')
    _fails(args, ['covariance', '36 numbers'], cr.InputError, prior=doc)
    # symmetric, positive variances, but x and y correlated beyond 1
    cov = np.eye(6) * 1e-6
    cov[0, 1] = cov[1, 0] = 2e-6
    message = _fails(args, ['not positive definite', 'eigenvalue', 'np.inf'], cr.InputError,
                     prior=cr.Prior(cr.UncertainPose(t0.position, t0.quat_wxyz, cov)))
    assert 'fix it' not in message
    _fails(args, ['not positive definite'], cr.InputError,
           prior=cr.Prior(t0, t1, -np.eye(12)))
    # negative variances everywhere: the "not estimated" mark of a result, so nothing is known
    negative = cr.UncertainPose(t0.position, t0.quat_wxyz, -np.eye(6) * 1e-6)
    _fails(args, ['base_to_base constrains nothing'], cr.InputError, prior=cr.Prior(negative))


def test_the_friends_refuse_the_same_way(data):
    args, _ = data
    a = cr.PoseStream(np.arange(len(args[0]), dtype=np.int64) * 10**7, args[0], args[1])
    b = cr.PoseStream(a.stamps, args[2], args[3])
    with pytest.raises(cr.ConfigError, match='Settings'):
        cr.calibrate_streams(a, [b], {'method': 'ols'})
    with pytest.raises(cr.InputError, match='load_prior'):
        cr.calibrate_streams(a, [b], cr.Settings(), prior={'base_to_base': {}})
    with pytest.raises(cr.ConfigError, match='sigma_a'):
        cr.Settings(sigma_a=1e-3)
    with pytest.raises(cr.ConfigError, match='max_gap'):
        cr.Settings(max_gap='soon')
