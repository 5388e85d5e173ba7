"""Building effects by name: ``make_effect(name, value)`` and ``parse_effect('NAME=VALUE')``."""

from __future__ import annotations

from functools import partial
from typing import Union

from coreg_ros.core.errors import ConfigError
from coreg_ros.sim.changes import StepEffect
from coreg_ros.sim.injected.common import ALL_EFFECT_NAMES, EFFECT_UNITS
from coreg_ros.sim.injected.field import FieldDistortion, NonStationary, Scale
from coreg_ros.sim.injected.link import Backlash, LinkFlex
from coreg_ros.sim.injected.noise import (
    AnisotropicNoise,
    DistanceNoise,
    NoiseScale,
    OutlierBursts,
    Outliers,
)
from coreg_ros.sim.injected.timing import (
    ClockDrift,
    ClockStep,
    SharedClock,
    TimeOffset,
    TimestampJitter,
)
import numpy as np

_CLASSES = {
    'time_offset': TimeOffset, 'clock_drift': ClockDrift, 'timestamp_jitter': TimestampJitter,
    'field_distortion': FieldDistortion, 'distance_noise': DistanceNoise, 'scale': Scale,
    'link_flex': LinkFlex, 'outliers': Outliers, 'backlash': Backlash,
    'noise_scale': NoiseScale, 'non_stationary': NonStationary, 'shared_clock': SharedClock,
    'outlier_bursts': OutlierBursts, 'clock_step': ClockStep,
    'anisotropic_noise': AnisotropicNoise,
    't0_step': partial(StepEffect, 't0_step'), 't1_step': partial(StepEffect, 't1_step'),
    'noise_step': partial(StepEffect, 'noise_step'),
}

# accepted range of VALUE per effect: (low, high, low inclusive), for the error message
_RANGES = {
    'time_offset': (-10.0, 10.0, True), 'clock_drift': (-1e5, 1e5, True),
    'timestamp_jitter': (0.0, 1.0, True), 'field_distortion': (0.0, 1000.0, True),
    'distance_noise': (-10.0, 10.0, True), 'scale': (-0.5, 0.5, True),
    'link_flex': (0.0, 100.0, True), 'outliers': (0.0, 1.0, True),
    'backlash': (0.0, 100.0, True), 'noise_scale': (0.0, 100.0, False),
    'non_stationary': (0.0, 1000.0, True), 'shared_clock': (-10.0, 10.0, True),
    'outlier_bursts': (0.0, 0.5, True), 'clock_step': (-10.0, 10.0, True),
    'anisotropic_noise': (0.0, 100.0, False), 't0_step': (0.0, 1000.0, True),
    't1_step': (0.0, 1000.0, True), 'noise_step': (1.0, 100.0, True),
}


def _accepted() -> str:
    return ', '.join(f'{n}=<{EFFECT_UNITS[n].split(",")[0]}>' for n in ALL_EFFECT_NAMES)


def make_effect(name: str, value: Union[float, tuple]):
    """
    Build the effect ``name`` of size ``value`` (unit ``EFFECT_UNITS[name]``).

    Raises
    ------
    ConfigError
        For an unknown name or a value out of its range.

    """
    if name not in _CLASSES:
        raise ConfigError(f'effect {name!r} is unknown; use NAME=VALUE with one of '
                          f'{_accepted()}')
    low, high, inclusive = _RANGES[name]
    values = np.atleast_1d(np.asarray(value, dtype=float))
    ok = np.isfinite(values).all() and (values <= high).all() and (
        (values >= low).all() if inclusive else (values > low).all())
    sizes_ok = values.size in (1, 3) if name == 'scale' else values.size == 1
    if not ok or not sizes_ok:
        bracket = '[' if inclusive else '('
        raise ConfigError(f'effect {name}: value {value!r} is out of range; give one number'
                          f'{" or three comma-separated" if name == "scale" else ""} in '
                          f'{bracket}{low:g}, {high:g}] ({EFFECT_UNITS[name]})')
    if name == 'scale':
        return Scale(tuple(values.tolist()) if values.size == 3 else float(values[0]))
    return _CLASSES[name](float(values[0]))


def parse_effect(text: str):
    """
    Parse ``'NAME=VALUE'`` (e.g. ``'time_offset=0.012'``, ``'scale=0.01,0,-0.005'``) to an effect.

    Parameters
    ----------
    text : str
        NAME one of ``EFFECT_NAMES``; VALUE a number in the unit of ``EFFECT_UNITS[NAME]``
        (for ``scale`` one number for all axes or three comma-separated).

    Returns
    -------
    Effect

    Raises
    ------
    ConfigError
        One line naming the accepted names and units.

    """
    name, sep, raw = str(text).partition('=')
    name = name.strip()
    if not sep or not raw.strip():
        raise ConfigError(f'effect {text!r}: expected NAME=VALUE, one of {_accepted()}')
    if name not in _CLASSES:
        raise ConfigError(f'effect {name!r} is unknown; use NAME=VALUE with one of '
                          f'{_accepted()}')
    try:
        values = tuple(float(v) for v in raw.replace(' ', '').split(','))
    except ValueError:
        raise ConfigError(f'effect {name}: {raw.strip()!r} is not a number; give VALUE in '
                          f'{EFFECT_UNITS[name]}, e.g. {name}={_EXAMPLES[name]}') from None
    return make_effect(name, values if len(values) > 1 else values[0])


_EXAMPLES = {
    'time_offset': '0.012', 'clock_drift': '100', 'timestamp_jitter': '0.005',
    'field_distortion': '5', 'distance_noise': '2', 'scale': '0.005', 'link_flex': '1',
    'outliers': '0.02', 'backlash': '0.3', 'noise_scale': '2', 'non_stationary': '3',
    'shared_clock': '0.02', 'outlier_bursts': '0.05', 'clock_step': '0.03',
    'anisotropic_noise': '3', 't0_step': '2', 't1_step': '1', 'noise_step': '2',
}
