"""
The shared parameter schema (``coreg_ros.core.config_schema``) and ``coreg --config`` files.

The node applies the same function to its overrides (``test_node_faults.py`` runs both on the
same files); here the pure rules, quickly.
"""

from coreg_ros.core.config_schema import (
    check_parameters,
    DEFAULTS,
    example,
    kind_of,
    nearest_key,
)
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.settings import Settings, settings_from_mapping
from coreg_ros.files.parameters import load_parameters
import pytest


def test_every_key_has_a_type_and_an_example():
    assert set(Settings().as_dict()) <= set(DEFAULTS)
    for key in DEFAULTS:
        assert kind_of(key) in ('bool', 'int', 'float', 'str', 'float_list', 'str_list')
        assert example(key).startswith(f'{key}: ')
    assert example('sigma_a') == 'sigma_a: [0.0002, 0.0005]'
    assert example('prior_file') == "prior_file: ''"


@pytest.mark.parametrize('values, expected', [
    ({'max_gap': 1}, {'max_gap': 1.0}),
    ({'time_offset': 0}, {'time_offset': 0.0}),
    ({'sigma_a': [0.001, 0.002]}, {'sigma_a': [0.001, 0.002]}),
    ({'topic_b': '/b'}, {'topic_b': ['/b']}),
    ({'min_pairs': 40, 'robust': False}, {'min_pairs': 40, 'robust': False}),
    ({'use_sim_time': True, 'qos_overrides./x.publisher.depth': 3}, {}),
])
def test_accepted_values_are_converted(values, expected):
    checked, warnings = check_parameters(values)
    assert checked == expected and warnings == []
    assert all(type(checked[k]) is type(v) for k, v in expected.items())
    settings_from_mapping(checked)  # and Settings takes them


@pytest.mark.parametrize('key, value, words', [
    ('max_gap', '0.05', 'max_gap must be a number'),
    ('max_gap', True, 'max_gap must be a number'),
    ('max_gap', float('nan'), 'finite'),
    ('min_pairs', 2.5, 'min_pairs must be an integer'),
    ('min_pairs', True, 'min_pairs must be an integer'),
    ('sigma_a', 0.001, 'sigma_a must be a list of numbers'),
    ('sigma_a', [1, 0.5], 'decimal point'),
    ('sigma_a', [], 'sigma_a must be a list of numbers'),
    ('robust', 'yes', 'robust must be true or false'),
    ('topic_b', [1], 'topic_b must be a list of names'),
    ('storage_dir', None, 'got nothing'),
    ('motion_limits', 'scara', 'motion_limits must be one of free | auto | restricted'),
    ('motion_limits', 3, 'motion_limits must be a string'),
])
def test_wrong_types_are_one_line_with_an_example(key, value, words):
    with pytest.raises(ConfigError) as err:
        check_parameters({key: value}, where='f.yaml: ')
    text = str(err.value)
    assert '\n' not in text and text.startswith(f'f.yaml: {key} must be ')
    assert words in text and f'e.g. {example(key)}' in text


def test_unknown_keys_name_the_nearest_valid_one():
    checked, warnings = check_parameters({'sigma_A': [1.0, 2.0], 'methd': 'ols', 'zzz': 1})
    assert checked == {}
    assert "unknown key 'sigma_A' is ignored; did you mean 'sigma_a'?" in warnings[0]
    assert "did you mean 'method'?" in warnings[1]
    assert 'config/coreg.yaml lists the valid keys' in warnings[2]
    assert nearest_key('storage') == 'storage_dir'


def _file(tmp_path, text):
    path = tmp_path / 'p.yaml'
    path.write_text(text)
    return path


def test_load_parameters_merges_sections_and_reads_ros_numbers(tmp_path):
    path = _file(tmp_path, '/**:\n  ros__parameters:\n    max_gap: 1e-2\n    min_pairs: 9\n'
                           'coreg_node:\n  ros__parameters:\n    min_pairs: 12\n')
    assert load_parameters(path) == {'max_gap': 0.01, 'min_pairs': 12}


def test_load_parameters_refuses_in_one_line(tmp_path, capsys):
    with pytest.raises(ConfigError, match=r'not valid YAML at line 4, column 1: expected'):
        load_parameters(_file(tmp_path, 'coreg_node:\n  ros__parameters:\n    a: [1\n'))
    # a file for other nodes sets nothing here (as ROS treats it for the node): said, not fatal
    assert load_parameters(_file(tmp_path, 'other:\n  ros__parameters:\n    a: 1\n')) == {}
    assert 'has no "coreg_node: ros__parameters:" section' in capsys.readouterr().err
    with pytest.raises(ConfigError, match='anchor or alias .* line 3'):
        load_parameters(_file(tmp_path, 'coreg_node:\n  ros__parameters:\n'
                                        '    sigma_a: &s [0.001, 0.002]\n    sigma_b: *s\n'))
    with pytest.raises(ConfigError, match=r'marker_magnification must lie in \[0.001, 1e\+06\]'):
        load_parameters(_file(tmp_path, 'coreg_node:\n  ros__parameters:\n'
                                        '    marker_magnification: 0.0\n'))
    with pytest.raises(ConfigError, match='use_sim_time must be true or false'):
        load_parameters(_file(tmp_path, 'coreg_node:\n  ros__parameters:\n'
                                        '    use_sim_time: abc\n'))
    with pytest.raises(ConfigError, match='max_gap must be a number'):
        load_parameters(_file(tmp_path, 'coreg_node:\n  ros__parameters:\n    max_gap: 5ms\n'))
    load_parameters(_file(tmp_path, 'coreg_node:\n  ros__parameters:\n    methd: ols\n'))
    assert "did you mean 'method'?" in capsys.readouterr().err
