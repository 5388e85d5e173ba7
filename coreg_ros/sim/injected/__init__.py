"""
Unmodelled effects to inject into simulated recordings (docs/design.md §5, issue 4).

Each effect is a small frozen dataclass implementing the ``Effect`` protocol of
``coreg_ros.sim.injection`` (``__call__(streams, context, rng) -> streams``, ``as_dict()``) and
a ``stage`` saying where it acts (``coreg_ros.sim.injection.STAGES``): ``'clean'`` effects change
the noise-free poses before the device noise is added (physics: distortion, scale, a bending
link, backlash), ``'noise'`` effects change the device noise itself, ``'measured'`` effects act
on the recorded samples (stamps, dropped samples, outliers). ``parse_effect('name=value')``
builds one from the command line (``coreg simulate --effect NAME=VALUE``).

=================== ========== ========= ====================================================
name                VALUE unit stage     what it does
=================== ========== ========= ====================================================
time_offset         s          measured  B's header stamps = true time + τ (B stamped late)
clock_drift         ppm        measured  B's stamps + κ (t - t_start), κ = VALUE·1e-6
timestamp_jitter    s          measured  B's stamps + N(0, VALUE²), 2 % of B dropped (more,
                                         and gaps of seconds, through the class)
field_distortion    mm         clean     a harmonic quadratic field around B's base or a
                                         dipole disturbance just outside the workspace; its
                                         part a rigid registration cannot absorb reaches
                                         VALUE; a rotation error (1 mrad per mm) beside it
distance_noise      exponent k noise     B's noise σ × (r / r0)^k, r = distance from B's base
scale               fraction   clean     B's positions × (1 + s) per axis about B's base
link_flex           mm         clean     the link pivots under gravity (a random direction in
                                         A's base): the marker sags VALUE when the link is
                                         level, and tilts with it
outliers            fraction   measured  that fraction of B's samples jump 2-10 cm, 10-90°
backlash            mm         clean     A's position lags VALUE/2 per axis behind the
                                         motion, flipping at each reversal (play operator)
noise_scale         factor     noise     the true noise of A and B is VALUE × the stated
non_stationary      mm         clean     a dipole disturbance during one window of the
                                         recording (a metal object brought near), VALUE at
                                         most
shared_clock        s          measured  A and B stamped on receipt by one host clock: B's
                                         latency exceeds A's by VALUE, no drift
outlier_bursts      fraction   measured  that fraction of B's samples jump as outliers do,
                                         in runs of 2-6 samples at random times
clock_step          s          measured  B's stamps + VALUE from a random instant (25-75 %
                                         of the recording) on: the offset steps
anisotropic_noise   factor     noise     B's position noise × VALUE along one direction of
                                         B's base frame (an axis, or a random direction)
t0_step, t1_step    mm         measured  T0 (T1) moves by VALUE (and turns 0.05° per mm)
                                         at a random instant (``sim.changes``)
noise_step          factor     measured  B's noise × VALUE from a random instant on
=================== ========== ========= ====================================================

``as_dict()`` gives ``name``, ``value`` (as parsed), ``unit``, ``stage`` and the effect's
parameters; effects whose size depends on the recording (e.g. the workspace edge of a field
distortion) add what they found on the recording they were last applied to.

Modules by physics: ``timing`` (clock and stamp effects), ``field`` (B's spatial errors),
``link`` (the link between the devices and A's backlash), ``noise`` (the noise and outliers of
the samples); ``registry`` builds them by name, ``common`` holds the names and units.
"""

from coreg_ros.sim.injected.common import (
    ALL_EFFECT_NAMES,
    EFFECT_NAMES,
    EFFECT_UNITS,
    EXTRA_EFFECT_NAMES,
)
from coreg_ros.sim.injected.field import (
    DISTORTION_ROTATION_PER_MM,
    FieldDistortion,
    NonStationary,
    Scale,
)
from coreg_ros.sim.injected.link import Backlash, LinkFlex, play_operator
from coreg_ros.sim.injected.noise import (
    AnisotropicNoise,
    DistanceNoise,
    NoiseScale,
    OUTLIER_ANGLE,
    OUTLIER_JUMP,
    OutlierBursts,
    Outliers,
)
from coreg_ros.sim.injected.registry import make_effect, parse_effect
from coreg_ros.sim.injected.timing import (
    ClockDrift,
    ClockStep,
    JITTER_DROP_FRACTION,
    SharedClock,
    TimeOffset,
    TimestampJitter,
)

__all__ = [
    'ALL_EFFECT_NAMES', 'AnisotropicNoise', 'Backlash', 'ClockDrift', 'ClockStep',
    'DISTORTION_ROTATION_PER_MM', 'DistanceNoise', 'EFFECT_NAMES', 'EFFECT_UNITS',
    'EXTRA_EFFECT_NAMES', 'FieldDistortion', 'JITTER_DROP_FRACTION', 'LinkFlex', 'NoiseScale',
    'NonStationary', 'OUTLIER_ANGLE', 'OUTLIER_JUMP', 'OutlierBursts', 'Outliers', 'Scale',
    'SharedClock', 'TimeOffset', 'TimestampJitter', 'make_effect', 'parse_effect',
    'play_operator'
]
