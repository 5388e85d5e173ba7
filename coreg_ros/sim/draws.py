"""
The random cases of the blind validation (``coreg validate-diagnosis``): what is simulated.

A case is a recording with no effect, one effect, or two at once (``TWO_SHARE``: every pair of
the library that can co-occur), of a random size drawn from the realistic ranges of
docs/design.md §5, on random noise, duration and model; a share of the cases
(``RIG_SHARE``) is recorded on a rig that cannot move in every direction (SCARA, planar,
gantry, turntable), where an effect the motion cannot show is not expected to be found and a
clean recording must stay clean.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

#: Realistic sizes per effect (docs/design.md §5) split into small / medium / large ranges, in the
#: unit of the simulator's ``NAME=VALUE`` (coreg_ros.sim.injected).
SIZE_RANGES = {
    'time_offset': ((0.001, 0.003), (0.003, 0.015), (0.015, 0.050)),
    'clock_drift': ((1.0, 10.0), (10.0, 100.0), (100.0, 500.0)),
    'timestamp_jitter': ((0.001, 0.003), (0.003, 0.010), (0.010, 0.025)),
    'field_distortion': ((1.0, 2.0), (2.0, 5.0), (5.0, 10.0)),
    'distance_noise': ((1.0, 2.0), (2.0, 4.0), (4.0, 8.0)),
    'scale': ((0.0005, 0.002), (0.002, 0.007), (0.007, 0.02)),
    'link_flex': ((0.1, 0.5), (0.5, 1.5), (1.5, 3.0)),
    'outliers': ((0.005, 0.01), (0.01, 0.025), (0.025, 0.05)),
    'backlash': ((0.05, 0.2), (0.2, 0.5), (0.5, 1.0)),
    'noise_scale': ((1.1, 1.3), (1.3, 2.0), (2.0, 3.0)),
    'non_stationary': ((1.0, 2.0), (2.0, 5.0), (5.0, 10.0)),
    'shared_clock': ((0.001, 0.003), (0.003, 0.015), (0.015, 0.050)),
    'outlier_bursts': ((0.005, 0.01), (0.01, 0.025), (0.025, 0.05)),
    # an NTP correction or a driver restart: milliseconds to a good part of a second
    'clock_step': ((0.002, 0.005), (0.005, 0.020), (0.020, 0.150)),
    # an optical tracker's depth axis, an EM field axis: noise × 1.2 to × 4 along it
    'anisotropic_noise': ((1.2, 1.5), (1.5, 2.5), (2.5, 4.0)),
    # a bumped base, a slipped marker: mm; metal brought near: a factor on the noise
    't0_step': ((0.2, 0.5), (0.5, 2.0), (2.0, 8.0)),
    't1_step': ((0.2, 0.5), (0.5, 2.0), (2.0, 8.0)),
    'noise_step': ((1.2, 1.5), (1.5, 2.5), (2.5, 4.0)),
}
#: Effects whose value may be negative (a clock set back, B stamped early).
SIGNED = ('time_offset', 'clock_drift', 'shared_clock', 'clock_step')
#: Effects that cannot be told apart when both act, or that one model covers: at most one of
#: each group in a case (one clock, one noise level, one kind of outliers).
EXCLUSIVE = (('time_offset', 'clock_drift', 'shared_clock', 'clock_step'),
             ('noise_scale', 'distance_noise', 'anisotropic_noise'),
             ('outliers', 'outlier_bursts'), ('t0_step', 't1_step'))
SIZES = ('small', 'medium', 'large')
#: Share of cases with a second effect at once, and of large offsets (0.1-2 s).
TWO_SHARE = 0.3
LARGE_OFFSET_SHARE = 0.25
#: Share of clean recordings among the validation cases.
CLEAN_SHARE = 0.25
#: Share of cases on a rig that cannot move in every direction, and those rigs.
RIG_SHARE = 0.1
RIGS = ('scara', 'planar', 'gantry', 'turntable')
#: Range of the recordings' durations, s (B at 50 Hz: 2000-6000 pairs).
DURATION = (40.0, 120.0)


def co_occurring(name: str) -> tuple:
    """Return the effects that can act together with ``name`` (not of its exclusive group)."""
    from coreg_ros.sim.injected import ALL_EFFECT_NAMES

    group = next((g for g in EXCLUSIVE if name in g), (name,))
    return tuple(n for n in ALL_EFFECT_NAMES if n not in group and n != name)


def _draw_effect(rng: np.random.Generator, names: tuple) -> dict:
    """One effect: name, size class, value, constructor arguments, spec text."""
    name = names[int(rng.integers(len(names)))]
    size = SIZES[int(rng.integers(3))]
    lo, hi = SIZE_RANGES[name][SIZES.index(size)]
    value = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    kwargs = {}
    if name == 'noise_scale' and rng.random() < 0.4:
        value = 1.0 / value if value < 2.0 else 0.5 + 0.1 * rng.random()
    if name == 'time_offset' and size == 'large' and rng.random() < LARGE_OFFSET_SHARE:
        value = float(np.exp(rng.uniform(np.log(0.1), np.log(2.0))))
    if name in SIGNED and rng.random() < 0.3:
        value = -value
    if name == 'timestamp_jitter':
        # drops of 1-25 % and, in a third of the cases, gaps of seconds
        kwargs = {'drop_fraction': float(rng.uniform(0.01, 0.25)),
                  'gaps': int(rng.integers(1, 3)) if rng.random() < 0.33 else 0,
                  'gap_s': float(rng.uniform(1.0, 4.0))}
    if name == 'scale':
        signs = rng.choice([-1.0, 1.0], size=3)
        mags = value * rng.uniform(0.5, 1.0, size=3)
        mags[int(rng.integers(3))] = value
        value = (signs * mags).tolist()
        spec = f'scale={",".join(f"{v:.6g}" for v in value)}'
    else:
        spec = f'{name}={value:.6g}'
    return {'effect': name, 'size': size, 'value': value, 'spec': spec, 'kwargs': kwargs}


def draw_case(rng: np.random.Generator, clean_share: float = CLEAN_SHARE,
              duration: Optional[tuple] = None) -> dict:
    """
    Draw one validation case: effect(s) (or none), size class, value, recording settings.

    Returns
    -------
    dict
        ``effect`` (name or None), ``size`` ('small', 'medium', 'large' or None), ``value``
        (float or list), ``spec`` (the ``NAME=VALUE`` text), ``kwargs`` (further arguments of
        the simulator's effect), ``second`` (a second effect at once, or None), ``model``,
        ``motion`` (``'diverse'`` or a restricted rig), ``duration``, ``sigma_a``,
        ``sigma_b``, ``seed``.

    """
    from coreg_ros.sim.injected import ALL_EFFECT_NAMES

    case = {'seed': int(rng.integers(0, 2 ** 31 - 1)),
            'model': 'full_pose' if rng.random() < 0.75 else 'position_only',
            'duration': float(rng.uniform(*(duration or DURATION))),
            'sigma_a': [float(rng.uniform(0.05, 0.3) * 1e-3), float(rng.uniform(0.2, 1.0) * 1e-3)],
            'sigma_b': [float(rng.uniform(0.2, 1.0) * 1e-3), float(rng.uniform(1.0, 4.0) * 1e-3)],
            'second': None,
            'motion': (RIGS[int(rng.integers(len(RIGS)))] if rng.random() < RIG_SHARE
                       else 'diverse')}
    if rng.random() < clean_share:
        case.update(effect=None, size=None, value=None, spec=None, kwargs={})
        return case
    case.update(_draw_effect(rng, ALL_EFFECT_NAMES))
    if rng.random() < TWO_SHARE:
        # two effects at once: any other of the library that can act together with it
        second = _draw_effect(rng, co_occurring(case['effect']))
        second['size'] = 'large' if second['size'] == 'small' else second['size']
        lo, hi = SIZE_RANGES[second['effect']][SIZES.index(second['size'])]
        if second['effect'] != 'scale':
            v = float(np.sign(second['value']) * np.exp(rng.uniform(np.log(lo), np.log(hi))))
            if second['effect'] in ('noise_scale', 'anisotropic_noise', 'noise_step'):
                v = abs(v)
            second.update(value=v, spec=f'{second["effect"]}={v:.6g}')
        case['second'] = second
    return case


def draw_effect_cases(rng: np.random.Generator, name: str, n: int,
                      sizes: tuple = ('medium', 'large'),
                      duration: Optional[tuple] = None) -> list:
    """
    Draw ``n`` cases of the one effect ``name`` (alone) at the given size classes.

    The recordings' settings are drawn as in ``draw_case`` (free motion); for studying one
    effect's size accuracy on fresh random draws (never on the fixed cases of a validation
    seed).
    """
    out = []
    for _ in range(n):
        case = draw_case(rng, clean_share=0.0, duration=duration)
        eff = _draw_effect(rng, (name,))
        size = sizes[int(rng.integers(len(sizes)))]
        lo, hi = SIZE_RANGES[name][SIZES.index(size)]
        value = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        if name in SIGNED and eff['value'] < 0:
            value = -value
        eff.update(size=size, value=value, spec=f'{name}={value:.6g}')
        case.update(eff)
        case['second'] = None
        case['motion'] = 'diverse'
        out.append(case)
    return out
