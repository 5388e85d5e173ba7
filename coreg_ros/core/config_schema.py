"""
The schema of the parameter files: every key of ``config/coreg.yaml``, its type and default.

One pure function, ``check_parameters``, decides which parameter mappings are accepted, for the
node (its ROS parameter overrides, ``coreg_ros.ros.parameters``) and for the command line
(``coreg --config``, ``coreg_ros.files.parameters.load_parameters``) alike, so both accept and
refuse the same files. The types come from the defaults: those of ``Settings`` for the
calibration keys and ``NODE_DEFAULTS`` for the keys of the node only.

A value of the wrong type is refused with one line naming the key, the expected type and an
example; an integer is accepted where a number with a decimal point is expected (ROS would
refuse ``max_gap: 1``), a single topic name where a list of topics is expected. Unknown keys
are not errors (other nodes' files share sections) but are reported with the nearest valid name.
"""

from __future__ import annotations

from collections.abc import Mapping
import difflib
import math
from typing import Any

from coreg_ros.core.errors import ConfigError
from coreg_ros.core.settings import NOISE_MODES, Settings

#: Keys of the node only (the calibration keys and their defaults are those of Settings).
NODE_DEFAULTS = {
    'prior_file': '',
    'noise_file': '',
    'use_last_result_as_prior': False,
    'gravity_aligned_sigma': 0.0,
    'publish_inconsistent': False,
    'roles_confirmed': False,
    'buffer_capacity': 200_000,
    'qos_reliable': False,
    'frame_base_a': 'device_a_base',
    'frame_base_b': 'device_b_base',
    'frame_tool': 'device_a_tool',
    'frame_marker': 'device_b_marker',
    'publish_tf': True,
    'storage_dir': '~/.ros/coreg',
    'resume_samples': False,
    'publish_fused_pose': True,
    'publish_markers': True,
    'fused_rate_limit': 50.0,
    'marker_magnification': 1.0,
    'fuse_when_stale': False,
    'guidance': True,
    'motion_limits': 'auto',
    'target_sigma_position': 1e-4,
    'target_sigma_rotation': 1e-3,
    'target_sigma_time': 0.0,
    'auto_calibrate': False,
    'watchdog': True,
    'auto_recalibrate': False,
}

#: Every key with its default: the calibration keys first, in the order of Settings.
DEFAULTS = {**Settings().as_dict(), **NODE_DEFAULTS}

#: Allowed ranges (inclusive) of the numeric keys: the node's descriptors and the file check.
RANGES = {
    'max_gap': (1e-6, 10.0),
    'time_offset': (-1e6, 1e6),
    'min_pairs': (3, 1_000_000_000),
    'max_iterations': (1, 100_000),
    'buffer_capacity': (10, 100_000_000),
    'fused_rate_limit': (0.0, 1000.0),
    'marker_magnification': (1e-3, 1e6),
    'target_sigma_position': (1e-9, 10.0),
    'target_sigma_rotation': (1e-9, 3.2),
    'target_sigma_time': (0.0, 10.0),
    'gravity_aligned_sigma': (0.0, 3.2),
}

#: Allowed values of the string keys of the node that name a choice.
CHOICES = {
    'motion_limits': ('free', 'auto', 'restricted'),
    'noise': NOISE_MODES,
}

#: Keys ROS itself gives every node (not ours, never warned about), all booleans.
ROS_KEYS = ('use_sim_time', 'start_type_description_service')
ROS_PREFIXES = ('qos_overrides.',)

_WHAT = {
    'bool': 'true or false',
    'int': 'an integer',
    'float': 'a number',
    'str': 'a string',
    'float_list': 'a list of numbers',
    'str_list': 'a list of names',
}


def kind_of(key: str) -> str:
    """Return the value kind of a known key: bool, int, float, str, float_list or str_list."""
    default = DEFAULTS[key]
    if isinstance(default, bool):
        return 'bool'
    if isinstance(default, int):
        return 'int'
    if isinstance(default, float):
        return 'float'
    if isinstance(default, str):
        return 'str'
    return 'str_list' if all(isinstance(v, str) for v in default) else 'float_list'


def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return value if value else "''"
    return repr(value)


def example(key: str) -> str:
    """One line of a parameter file with the default of ``key``, e.g. ``max_gap: 0.05``."""
    default = DEFAULTS[key]
    if isinstance(default, list):
        return f'{key}: [{", ".join(_yaml_scalar(v) for v in default)}]'
    return f'{key}: {_yaml_scalar(default)}'


def nearest_key(key: str) -> str | None:
    """Return the valid key closest to ``key`` (difflib, case-insensitive), or None."""
    lowered = {k.lower(): k for k in DEFAULTS}
    match = difflib.get_close_matches(str(key).lower(), list(lowered), n=1, cutoff=0.6)
    return lowered[match[0]] if match else None


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _plain(value: Any) -> Any:
    """Arrays (array.array, numpy, tuples) as lists; anything else as it is."""
    if isinstance(value, (list, tuple)):
        return list(value)
    if hasattr(value, 'tolist') and not isinstance(value, (str, bytes)):
        return value.tolist()
    return value


def _describe(value: Any) -> str:
    if value is None:
        return 'nothing'
    text = repr(value)
    if len(text) > 40:
        text = text[:37] + '...'
    return f'{text} ({type(value).__name__})'


def check_value(key: str, value: Any, where: str = '') -> Any:
    """
    Check one known key's value against its type; return it converted (int -> float etc.).

    Raises
    ------
    ConfigError
        One line: the key, what was found, the expected type and an example.

    """
    kind = kind_of(key)
    value = _plain(value)

    def refuse(extra: str = '') -> ConfigError:
        return ConfigError(f'{where}{key} must be {_WHAT[kind]}{extra}, got {_describe(value)}; '
                           f'e.g. {example(key)}')

    if kind == 'bool':
        if not isinstance(value, bool):
            raise refuse()
        return value
    if kind == 'int':
        if isinstance(value, bool) or not isinstance(value, int):
            raise refuse(' (no decimal point)')
        return value
    if kind == 'float':
        if not _is_number(value):
            raise refuse(' (write it without quotes or units, in seconds or metres)')
        if not math.isfinite(value):
            raise refuse(' (finite)')
        return float(value)
    if kind == 'str':
        if not isinstance(value, str):
            raise refuse()
        if key in CHOICES and value not in CHOICES[key]:
            raise ConfigError(f'{where}{key} must be one of {" | ".join(CHOICES[key])}, got '
                              f'{value!r}; e.g. {example(key)}')
        return value
    if kind == 'str_list':
        if isinstance(value, str):
            return [value]
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise refuse(' (topic names)')
        return value
    # float_list
    if not isinstance(value, list) or not value or not all(_is_number(v) for v in value):
        raise refuse(f' in brackets ({len(DEFAULTS[key])} of them)')
    if len({type(v) for v in value}) > 1:
        # ROS parameter files cannot hold a list mixing integers and decimals
        raise refuse(' all written with a decimal point (a ROS list cannot mix 1 and 0.5)')
    if not all(math.isfinite(v) for v in value):
        raise refuse(' (finite)')
    return [float(v) for v in value]


def _check_range(key: str, value: Any, where: str) -> None:
    if key in RANGES:
        lo, hi = RANGES[key]
        if not lo <= value <= hi:
            raise ConfigError(f'{where}{key} must lie in [{lo:g}, {hi:g}], got {value!r}; '
                              f'e.g. {example(key)}')


def is_ros_key(key: str) -> bool:
    """Tell whether ROS declares ``key`` on every node (use_sim_time, qos_overrides...)."""
    return key in ROS_KEYS or str(key).startswith(ROS_PREFIXES)


def unknown_key_warning(key: str, where: str = '') -> str:
    """One line about an unknown key, naming the nearest valid one."""
    near = nearest_key(key)
    hint = f'did you mean {near!r}?' if near else 'config/coreg.yaml lists the valid keys'
    return f'{where}unknown key {key!r} is ignored; {hint}'


def check_parameters(values: Mapping[str, Any], where: str = '') -> tuple[dict, list[str]]:
    """
    Check a mapping of parameter names to values (a file's ``ros__parameters``, node overrides).

    Parameters
    ----------
    values : mapping
        Names to values as YAML or ROS gives them.
    where : str
        Prefix of the messages, e.g. ``'config/coreg.yaml: '``.

    Returns
    -------
    checked : dict
        The known keys with their values converted to the expected type (an integer where a
        number is expected becomes a float, a single topic name a list of one). Unknown keys
        and the keys ROS gives every node are left out.
    warnings : list of str
        One line per unknown key, naming the nearest valid key.

    Raises
    ------
    ConfigError
        On the first value of the wrong type: one line naming the key, what was found, the
        expected type and an example.

    """
    checked, warnings = {}, []
    for key, value in values.items():
        if not isinstance(key, str):
            raise ConfigError(f'{where}key {key!r} is not a name; write keys like '
                              f'{example("max_gap")}')
        if key in DEFAULTS:
            checked[key] = check_value(key, value, where)
            _check_range(key, checked[key], where)
        elif key in ROS_KEYS and not isinstance(value, bool):
            # ROS declares these booleans on every node and refuses anything else
            raise ConfigError(f'{where}{key} must be true or false, got {_describe(value)}; '
                              f'e.g. {key}: false')
        elif not is_ros_key(key):
            warnings.append(unknown_key_warning(key, where))
    return checked, warnings
