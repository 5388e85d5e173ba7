"""
The pairs ``calibrate`` is given, checked against the model before any arithmetic.

Every failure is one line that names the problem and the fix (too few pairs, wrong shapes,
NaN or inf, quaternions that are not unit, input weights out of range).
"""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.pairing import UNIT_QUATERNIONS
from coreg_ros.core.errors import InputError, TooFewPairsError
from coreg_ros.core.models import ModelSpec
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import Pairs
import numpy as np


def validated_arrays(pairs: Pairs, spec: ModelSpec, settings: Settings) -> tuple:
    """
    Check the pairs against the model and return their arrays, or say what is wrong.

    Returns
    -------
    pos_a : ndarray, shape (N, 3)
        m.
    quat_a : ndarray, shape (N, 4)
        Unit (w, x, y, z).
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
        m (three_marker: three markers per pair).
    quat_b : ndarray, shape (N, 4) or None
        Unit (w, x, y, z); None unless the model needs B's orientation.
    scale : ndarray, shape (N,) or None
        ``pairs.a_var_scale``, positive and finite.

    Raises
    ------
    TooFewPairsError, InputError

    """
    n = len(pairs)
    min_pairs = max(int(settings.min_pairs), spec.n_params // spec.n_res + 2)
    if n < min_pairs:
        raise TooFewPairsError(
            f'only {n} pairs (need at least {min_pairs}); record longer, move while recording, '
            f'or raise max_gap if the devices were not paired')
    pos_a = np.asarray(pairs.pos_a, dtype=float)
    pos_b = np.asarray(pairs.pos_b, dtype=float)
    want_b = (n, 3, 3) if spec.name == 'three_marker' else (n, 3)
    if pos_a.shape != (n, 3) or pos_b.shape != want_b:
        raise InputError(f'pairs have shapes {pos_a.shape} and {pos_b.shape}; model '
                         f'{spec.name} needs (N, 3) and {want_b}')
    for name, arr in (('device A position', pos_a), ('device B position', pos_b)):
        if np.isfinite(arr).all():  # the usual case, without a per-pair mask
            continue
        bad = ~np.isfinite(arr).reshape(n, -1).all(axis=1)
        if bad.any():
            raise InputError(f'{name}: {int(bad.sum())} pair(s) contain NaN or inf (first at '
                             f'pair {int(np.flatnonzero(bad)[0])}); drop those samples')
    orientations = (('device A orientation', pairs.quat_a), ('device B orientation', pairs.quat_b))
    for name, q in orientations:
        if q is not None and np.shape(q) != (n, 4):
            raise InputError(f'{name}: expected shape ({n}, 4) (one (w, x, y, z) per pair), got '
                             f'{np.shape(q)}')
    # the pairing's are unit and canonical already (UNIT_QUATERNIONS): taken as they are
    unit = quat.unit_quaternions if not getattr(pairs, UNIT_QUATERNIONS, False) else (
        lambda q, _: np.asarray(q, dtype=float))
    quat_a = unit(pairs.quat_a, 'device A orientation')
    quat_b = None
    if spec.has_q1:
        if pairs.quat_b is None:
            raise InputError('model full_pose needs device B orientations; use '
                             '--model position_only for a position-only tracker')
        quat_b = unit(pairs.quat_b, 'device B orientation')
    scale = None
    if pairs.a_var_scale is not None:
        scale = np.asarray(pairs.a_var_scale, dtype=float)
        if scale.shape != (n,) or not (np.isfinite(scale) & (scale > 0)).all():
            raise InputError('a_var_scale must be positive and finite, one per pair')
    return pos_a, quat_a, pos_b, quat_b, scale
