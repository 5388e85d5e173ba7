"""
The front door for Python users: ``coreg_ros.calibrate`` on numpy arrays.

``import coreg_ros as cr; res = cr.calibrate(pos_a, quat_a_wxyz, pos_b, quat_b_wxyz,
sigma_a=(2e-4, 5e-4), sigma_b=(5e-4, 2e-3))`` runs the same pipeline as ``coreg calibrate``
(pairing, clock offset when stamps are given, robust Ikits OLS/TLS, posterior covariance, fit
verdict) and returns its ``CalibrationResult``; ``res.summary()`` is the text the command
prints.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields
import difflib
import math
import os
from typing import Optional, Union

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, PoseStream
import numpy as np

#: Stamp spacing given to synchronised arrays without stamps (1 kHz), ns.
_SYNC_STEP_NS = 1_000_000


def model_of(pos_b: np.ndarray, quat_b_wxyz: Optional[np.ndarray]) -> str:
    """
    Return the measurement model that the shapes of device B's arrays imply.

    ``pos_b`` (N, 3) with ``quat_b_wxyz`` (N, 4): ``full_pose``; (N, 3) alone:
    ``position_only``; (N, 3, 3), three marker positions per sample: ``three_marker``.
    """
    pos_b = np.asarray(pos_b)
    if pos_b.ndim == 3 and pos_b.shape[1:] == (3, 3):
        if quat_b_wxyz is not None:
            raise InputError('quat_b_wxyz was given with three marker positions per sample '
                             '(pos_b of shape (N, 3, 3)); the three-marker model has no B '
                             'orientation: leave quat_b_wxyz out')
        return 'three_marker'
    if pos_b.ndim == 2 and pos_b.shape[1] == 3:
        return 'full_pose' if quat_b_wxyz is not None else 'position_only'
    raise InputError(f'pos_b must have shape (N, 3), or (N, 3, 3) for three markers; got '
                     f'{pos_b.shape}')


def _stamps(stamps, n: int, name: str) -> np.ndarray:
    if stamps is None:
        return np.arange(n, dtype=np.int64) * _SYNC_STEP_NS
    s = np.asarray(stamps)
    if s.shape != (n,):
        raise InputError(f'{name} must have one stamp per sample, shape ({n},); got {s.shape}')
    if not np.issubdtype(s.dtype, np.integer):
        raise InputError(f'{name} must be integer nanoseconds (int64); got {s.dtype} (multiply '
                         f'seconds by 1e9 and round)')
    return s.astype(np.int64)


#: Keywords of ``calibrate`` besides the ``Settings`` fields (for the nearest-name hint).
_KEYWORDS = ('sigma_a', 'sigma_b', 'method', 'stamps_a', 'stamps_b', 'time_offset', 'robust',
             'prior', 'noise', 'quat_b_wxyz')
#: Settings fields ``calibrate`` sets itself, and what to give instead.
_DERIVED = {'model': 'the model follows from the shapes of pos_b and quat_b_wxyz (model_of)',
            'estimate_time_offset': "give time_offset='auto' (estimate) or seconds (fixed)"}


def _check_keywords(settings: dict) -> None:
    """Refuse keywords ``calibrate`` does not know, naming the nearest one."""
    known = [f.name for f in fields(Settings)]
    for key in settings:
        if key in _DERIVED:
            raise ConfigError(f'calibrate() sets {key} itself: {_DERIVED[key]}')
        if key not in known:
            near = difflib.get_close_matches(key, [*_KEYWORDS, *known], n=1)
            hint = f"; did you mean '{near[0]}'?" if near else ''
            raise ConfigError(f'calibrate() has no keyword {key!r}{hint} (the keywords: '
                              f'{", ".join(_KEYWORDS)} and the Settings fields)')


def _offset(time_offset) -> tuple:
    """(estimate, seconds) of ``time_offset``: 'auto' or a finite number of seconds."""
    if isinstance(time_offset, str) and time_offset.strip().lower() == 'auto':
        return True, 0.0
    try:
        value = float(time_offset)
    except (TypeError, ValueError):
        value = math.nan
    if isinstance(time_offset, bool) or not math.isfinite(value):
        raise ConfigError(f"time_offset must be 'auto' (estimated) or B's clock minus A's in "
                          f'seconds (a finite number, fixed); got {time_offset!r}')
    return False, value


def as_prior(prior) -> Optional[Prior]:
    """
    Return ``prior`` as a ``Prior``: a ``Prior``, a dict or a file path (loaded), or None.

    A dict is read as ``--prior`` reads a file (a previous result or a partial prior,
    ``files.results.prior_from_dict``); a path (str or path-like) is loaded with
    ``load_prior``.

    Raises
    ------
    InputError
        Anything else, or a dict or file that is not a prior (one line naming the fix).

    """
    if prior is None or isinstance(prior, Prior):
        return prior
    from coreg_ros.files.results import load_prior, prior_from_dict

    if isinstance(prior, Mapping):
        return prior_from_dict(prior)
    if isinstance(prior, (str, os.PathLike)):
        return load_prior(prior)
    raise InputError(f'prior must be a coreg_ros.Prior, a dict (a previous result, or '
                     f'base_to_base/tool_to_marker with sigma per axis) or the path of such a '
                     f'file; got {type(prior).__name__}')


def _with_noise(settings: Settings, noise) -> Settings:
    """Return the settings with ``calibrate``'s ``noise`` argument applied (one-line errors)."""
    from dataclasses import replace
    from pathlib import Path

    from coreg_ros.core.noise_model import DeviceNoise
    from coreg_ros.core.settings import NOISE_MODES

    if isinstance(noise, str) and noise in NOISE_MODES:
        return settings.updated(noise=noise)
    if isinstance(noise, (str, Path)):
        from coreg_ros.files.noise_file import load_noise_file, with_noise_file
        return with_noise_file(settings, load_noise_file(noise))
    if isinstance(noise, Mapping) and set(noise) <= {'a', 'b'} and all(
            isinstance(v, DeviceNoise) for v in noise.values()):
        return replace(settings, **{f'noise_{d}': v for d, v in noise.items()})
    raise InputError(f"noise must be 'stated', 'auto', a noise file or {{'a': DeviceNoise, "
                     f"'b': DeviceNoise}}, got {type(noise).__name__}")


def calibrate(pos_a, quat_a_wxyz, pos_b, quat_b_wxyz=None, *,
              sigma_a: tuple = Settings.sigma_a, sigma_b: tuple = Settings.sigma_b,
              method: str = 'tls', stamps_a=None, stamps_b=None,
              time_offset: Union[str, float] = 'auto', robust: bool = True,
              prior: Union[Prior, Mapping, str, os.PathLike, None] = None,
              noise='stated', **settings) -> CalibrationResult:
    """
    Calibrate from numpy arrays: T0 (A's base in B's base), T1 (B's marker in A's tool).

    Parameters
    ----------
    pos_a : array_like, shape (N, 3)
        Device A's tool position in A's base frame, m.
    quat_a_wxyz : array_like, shape (N, 4)
        Device A's tool orientation, (w, x, y, z).
    pos_b : array_like, shape (M, 3) or (M, 3, 3)
        Device B's marker position in B's base frame, m (three markers: (M, 3, 3)).
    quat_b_wxyz : array_like, shape (M, 4), optional
        Device B's marker orientation (w, x, y, z); leave out for a position-only device.
    sigma_a, sigma_b : (float, float)
        Stated noise of A and B: position (m) and rotation (rad) standard deviations.
    method : {'tls', 'ols'}
        Ikits B.2 (errors in both devices) or B.1 (A exact).
    stamps_a, stamps_b : array_like of int64, shape (N,) and (M,), optional
        Sample times, ns. Without them the rows are taken as simultaneous pairs (N = M).
    time_offset : 'auto' or float
        B's clock minus A's, s: estimated ('auto', the default when stamps are given) or fixed.
    robust : bool
        Reject pairs far outside the stated noise and refit.
    prior : Prior, dict, str or path-like, optional
        A priori estimate of T0 and T1 (Ikits B.3); a dict or a file (a previous result, or
        a partial prior) is loaded as ``coreg calibrate --prior`` loads it (``as_prior``).
    noise : 'stated', 'auto', str or Path, or dict
        ``'stated'``: ``sigma_a``/``sigma_b`` as given; ``'auto'``: each device's noise
        estimated with the calibration (``res.noise``; what the motion cannot separate held
        at ``sigma_a``/``sigma_b``), the verdict naming what was misstated; a noise file
        (``coreg noise``) or ``{'a': DeviceNoise, 'b': DeviceNoise}`` (either may be left
        out): full covariances in each device's base frame instead of the σ.
    **settings
        Further ``Settings`` fields (``max_gap``, ``estimate_clock_drift``, ``min_pairs``,
        ``max_iterations``); a keyword that is none of them is refused, naming the nearest.

    Returns
    -------
    CalibrationResult
        ``success`` only when the estimator converged and the fit matches the stated noise;
        ``summary()`` gives the text ``coreg calibrate`` prints.

    Raises
    ------
    InputError, ConfigError, TooFewPairsError, UnobservableError, ConvergenceError,
    InconsistentDataError
        All subclasses of ``CoregError``, with a message that names the fix.

    """
    _check_keywords(settings)
    estimate, offset = _offset(time_offset)
    prior = as_prior(prior)
    model = model_of(pos_b, quat_b_wxyz)
    pos_a = np.asarray(pos_a, dtype=float)
    pos_b = np.asarray(pos_b, dtype=float)
    n, m = len(pos_a), len(pos_b)
    synchronised = stamps_a is None and stamps_b is None
    if synchronised and n != m:
        raise InputError(f'without stamps the rows are pairs, so A and B need as many samples; '
                         f'got {n} and {m} (give stamps_a and stamps_b to pair them by time)')
    if (stamps_a is None) != (stamps_b is None):
        raise InputError('give both stamps_a and stamps_b, or neither (simultaneous rows)')
    estimate = estimate and not synchronised
    cfg = _with_noise(Settings(model=model, method=method, sigma_a=sigma_a,
                               sigma_b=sigma_b, robust=robust,
                               estimate_time_offset=estimate, time_offset=offset,
                               **settings), noise)
    ta, tb = _stamps(stamps_a, n, 'stamps_a'), _stamps(stamps_b, m, 'stamps_b')
    stream_a = PoseStream(ta, pos_a, np.asarray(quat_a_wxyz, dtype=float))
    if model == 'three_marker':
        ident = np.tile([1.0, 0.0, 0.0, 0.0], (m, 1))
        streams_b = [PoseStream(tb, pos_b[:, j], ident) for j in range(3)]
    else:
        q_b = (np.tile([1.0, 0.0, 0.0, 0.0], (m, 1)) if quat_b_wxyz is None
               else np.asarray(quat_b_wxyz, dtype=float))
        streams_b = [PoseStream(tb, pos_b, q_b)]
    result, _ = calibrate_streams(stream_a, streams_b, cfg, prior)
    return result
