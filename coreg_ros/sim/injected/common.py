"""Names, units and the stream helpers every injected effect uses."""

from __future__ import annotations

from dataclasses import replace

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.types import PoseStream
from coreg_ros.sim.changes import STEP_UNITS
from coreg_ros.sim.injection import EffectContext
import numpy as np

#: The ten effects of docs/design.md §5 that the diagnosis models one by one, in its order.
EFFECT_NAMES = ('time_offset', 'clock_drift', 'timestamp_jitter', 'field_distortion',
                'distance_noise', 'scale', 'link_flex', 'outliers', 'backlash', 'noise_scale')
#: Further cases real rigs show (issue 11): a distortion that comes and goes, and both
#: devices stamped by one host clock (a constant offset, no drift).
EXTRA_EFFECT_NAMES = ('non_stationary', 'shared_clock', 'outlier_bursts', 'clock_step',
                      'anisotropic_noise', 't0_step', 't1_step', 'noise_step')
#: Every name ``parse_effect`` accepts.
ALL_EFFECT_NAMES = EFFECT_NAMES + EXTRA_EFFECT_NAMES

#: Unit of each effect's VALUE, as shown in error messages and ``as_dict()['unit']``.
EFFECT_UNITS = {
    'time_offset': 's', 'clock_drift': 'ppm', 'timestamp_jitter': 's std',
    'field_distortion': 'mm at the workspace edge', 'distance_noise': 'exponent k',
    'scale': 'fraction, one or three comma-separated', 'link_flex': 'mm of sag',
    'outliers': 'fraction of B samples', 'backlash': 'mm', 'noise_scale': 'factor',
    'non_stationary': 'mm at most, during a window', 'shared_clock': 's of B latency over A',
    'outlier_bursts': 'fraction of B samples, in runs of 2-6',
    'clock_step': 's added to B stamps from a random instant on',
    'anisotropic_noise': "factor on B's position noise along one axis of B's base",
    **STEP_UNITS,
}


def full_pose(context: EffectContext) -> bool:
    """Whether B measures orientation too (the ``full_pose`` model)."""
    return context.truth.model == 'full_pose'


def scale_noise(noisy: PoseStream, clean: PoseStream, factor) -> PoseStream:
    """Scale the noise of ``noisy`` about ``clean`` (same stamps) by ``factor``, scalar or (N,)."""
    if not np.array_equal(noisy.stamps, clean.stamps):
        raise ConfigError('noise effects need the noisy and the clean stream at the same '
                          'stamps; apply them before effects that change stamps')
    f = np.broadcast_to(np.asarray(factor, dtype=float), (len(noisy),))
    position = clean.position + f[:, None] * (noisy.position - clean.position)
    dtheta = quat.log(quat.multiply(noisy.quat_wxyz, quat.conjugate(clean.quat_wxyz)))
    q = quat.canonical(quat.multiply(quat.exp(f[:, None] * dtheta), clean.quat_wxyz))
    return replace(noisy, position=position, quat_wxyz=q)
