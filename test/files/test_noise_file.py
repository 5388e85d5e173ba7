"""The noise file (``files.noise_file``): written, read back, bad files refused with the reason."""

from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.core.settings import Settings
from coreg_ros.files.noise_file import (
    device_block,
    load_noise_file,
    noise_document,
    noise_from_dict,
    with_noise_file,
    write_noise_file,
)
import numpy as np
import pytest
from strategies import random_quat
import yaml


def _noise(rng) -> DeviceNoise:
    from coreg_ros.core.quaternion import to_matrix
    R = to_matrix(random_quat(rng))
    pos = R @ np.diag([2e-4, 3e-4, 9e-4]) ** 2 @ R.T
    return DeviceNoise.from_covariances(pos, np.diag([1e-3, 2e-3, 1.5e-3]) ** 2)


@pytest.mark.parametrize('suffix', ['yaml', 'json'])
def test_round_trip_keeps_the_covariances_bit_for_bit(tmp_path, suffix):
    rng = np.random.default_rng(1)
    a, b = _noise(rng), _noise(rng)
    doc = noise_document({'device_a': device_block(a, '/a/pose', 'a_base'),
                          'device_b': device_block(b, ('/b/pose',), 'b_base')}, 'measured')
    path = write_noise_file(tmp_path / f'noise.{suffix}', doc)
    got = load_noise_file(path)
    assert got.device_a == a and got.device_b == b
    assert got.topics == {'a': '/a/pose', 'b': ('/b/pose',)}
    s = with_noise_file(Settings(topic_a='/a/pose', topic_b=('/b/pose',)), got)
    np.testing.assert_array_equal(s.cov_a, a.covariance())
    assert s.sigma_a == a.largest_sigmas()


def test_hand_written_forms():
    doc = {'coreg_noise': {
        'device_a': {'position_sigma_m': 2e-4, 'rotation_sigma_rad': 5e-4},
        'device_b': {'position_sigma_m': [9e-4, 3e-4, 3e-4],
                     'position_axes': [[0, 0, 1], [1, 0, 0], [0, 1, 0]],
                     'rotation_covariance': np.diag([4e-6, 4e-6, 1e-6]).tolist()}}}
    got = noise_from_dict(doc)
    np.testing.assert_allclose(got.device_a.position_cov, np.eye(3) * 4e-8)
    np.testing.assert_allclose(got.device_b.position_cov, np.diag([9e-8, 9e-8, 8.1e-7]))
    # one device only: the other keeps sigma_a / sigma_b
    only_b = noise_from_dict({'device_b': doc['coreg_noise']['device_b']})
    s = with_noise_file(Settings(), only_b)
    assert s.noise_a is None and s.sigma_a == Settings().sigma_a


@pytest.mark.parametrize('block, reason', [
    ({'units': {'position': 'mm', 'rotation': 'rad'}, 'device_a': {
        'position_sigma_m': 0.2, 'rotation_sigma_rad': 1e-3}}, r'in mm; coreg reads m \(convert'),
    ({'units': {'rotation': 'deg'}, 'device_a': {
        'position_sigma_m': 2e-4, 'rotation_sigma_rad': 0.1}}, 'in deg; coreg reads rad'),
    ({'device_a': {'position_sigma_m': -2e-4, 'rotation_sigma_rad': 1e-3}},
     'standard deviations must be positive'),
    ({'device_a': {'position_sigma_m': 0.0, 'rotation_sigma_rad': 1e-3}},
     'standard deviations must be positive'),
    ({'device_a': {'position_covariance': [[1e-8, 2e-8, 0], [2e-8, 1e-8, 0], [0, 0, 1e-8]],
                   'rotation_sigma_rad': 1e-3}}, 'not positive definite'),
    ({'device_a': {'position_covariance': [[1e-8, 2e-9, 0], [0, 1e-8, 0], [0, 0, 1e-8]],
                   'rotation_sigma_rad': 1e-3}}, 'not symmetric'),
    ({'device_a': {'position_sigma_m': 2e-4}}, 'gives no rotation noise'),
    ({'device_a': {'position_sigma_m': 'small', 'rotation_sigma_rad': 1e-3}}, 'must be numbers'),
    ({'device_a': {'position_sigma_m': 2.0, 'rotation_sigma_rad': 1e-3}}, 'no tracker noise'),
    ({'something': 1}, 'no device_a or device_b noise'),
    ({'version': 9, 'device_a': {'position_sigma_m': 2e-4, 'rotation_sigma_rad': 1e-3}},
     'newer than this coreg reads'),
])
def test_bad_files_are_refused_with_the_reason(block, reason):
    with pytest.raises(ConfigError, match=reason) as e:
        noise_from_dict({'coreg_noise': block}, 'n.yaml')
    assert str(e.value).startswith('noise file n.yaml: ') and '\n' not in str(e.value)


def test_a_file_for_other_topics_is_refused():
    got = noise_from_dict({'device_b': {'topic': '/optical/pose', 'position_sigma_m': 3e-4,
                                        'rotation_sigma_rad': 1e-3}}, 'n.yaml')
    with pytest.raises(ConfigError, match=r'device B noise is for topic /optical/pose, but '
                                          r'device B is /device_b/pose: measure these topics'):
        with_noise_file(Settings(), got)
    assert with_noise_file(Settings(topic_b='/optical/pose'), got).noise_b is not None


def test_unreadable_files(tmp_path):
    with pytest.raises(InputError, match='cannot read the noise file'):
        load_noise_file(tmp_path / 'none.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('device_a: [unclosed\n')
    with pytest.raises(InputError, match='neither YAML nor JSON'):
        load_noise_file(bad)
    ok = tmp_path / 'ok.yaml'
    ok.write_text(yaml.safe_dump({'device_a': {'position_sigma_m': '2e-4'}}))
    with pytest.raises(ConfigError):
        load_noise_file(ok)
