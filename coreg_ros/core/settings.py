"""
Calibration settings shared by the command-line tools and the node.

The keys are those of ``config/coreg.yaml`` (ROS parameter file form, under
``coreg_node: ros__parameters:``); the node declares each one as a ROS parameter with a
descriptor, the CLI reads the same file with ``--config`` and overrides keys with flags.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any, Optional

from coreg_ros.core.errors import ConfigError
from coreg_ros.core.noise_model import DeviceNoise, MAX_SIGMA, noise_covariance
from coreg_ros.core.types import METHODS, MODELS
import numpy as np

#: Largest noise σ taken as meant (position m, rotation rad; ``noise_model.MAX_SIGMA``).
MAX_SIGMA_M = MAX_SIGMA['position']
MAX_SIGMA_RAD = MAX_SIGMA['rotation']
#: How the noise is known: ``stated`` (sigma_a/sigma_b or a noise file, taken as true) or
#: ``auto`` (estimated jointly with the calibration, ``calibration.noise_components``).
NOISE_MODES = ('stated', 'auto')
#: Fields of Settings that are not parameters of a file (objects: the noise file's contents).
OBJECT_FIELDS = ('noise_a', 'noise_b')
DEFAULT_TOPIC_A = '/device_a/pose'
DEFAULT_TOPIC_B = ('/device_b/pose',)
DEFAULT_TOPICS_B_THREE_MARKER = (
    '/device_b/marker1/pose', '/device_b/marker2/pose', '/device_b/marker3/pose')


@dataclass(frozen=True)
class Settings:
    """
    What to calibrate and how.

    Attributes
    ----------
    topic_a : str
        PoseStamped topic of device A (input: tool pose in A's base frame).
    topic_b : tuple of str
        PoseStamped topic(s) of device B (output: marker pose in B's base frame); three
        topics for ``three_marker``.
    model : str
        ``full_pose`` (Ikits eq. 16), ``position_only`` (eq. 18) or ``three_marker`` (eq. 19).
    method : str
        ``ols`` (B.1, errors in B only) or ``tls`` (B.2, errors in both devices).
    sigma_a, sigma_b : tuple of float
        Noise standard deviation of each device: (position m, rotation rad).
    max_gap : float
        Largest distance in time (s) from a B stamp to each of the two A samples it is
        interpolated between.
    time_offset : float
        B's clock minus A's clock, s: A is interpolated at ``t_B - time_offset``. The fixed
        value, or the starting guess when ``estimate_time_offset``.
    estimate_time_offset : bool
        Estimate the offset jointly with T0 and T1 (coarse search over the streams' overlap,
        then least squares); kept at ``time_offset`` when the motion cannot determine it.
    estimate_clock_drift : bool
        Also estimate a linear clock drift κ (τ(t) = τ0 + κ (t - t_mid)).
    robust : bool
        Reject pairs far outside the stated noise (outliers) before the final fit.
    min_pairs : int
        Fewest pairs a calibration accepts.
    max_iterations : int
        Iteration limit of the estimator.
    noise : {'stated', 'auto'}
        ``stated``: the noise is as given (``sigma_a``/``sigma_b``, or ``noise_a``/``noise_b``)
        and the verdict judges the fit against it; ``auto``: each device's noise is estimated
        jointly with the calibration (variance components), the given noise being where the
        components the data cannot separate are held.
    noise_a, noise_b : DeviceNoise, optional
        Full (anisotropic) noise of a device in its base frame, e.g. from a noise file
        (``coreg noise``); overrides ``sigma_a``/``sigma_b``, which then hold its largest
        principal σ (for what needs one number). Not a parameter of a file: the node's
        ``noise_file`` and ``--noise FILE`` give them.

    """

    topic_a: str = DEFAULT_TOPIC_A
    topic_b: tuple = DEFAULT_TOPIC_B
    model: str = 'full_pose'
    method: str = 'tls'
    sigma_a: tuple = (0.0002, 0.0005)
    sigma_b: tuple = (0.0005, 0.002)
    max_gap: float = 0.05
    time_offset: float = 0.0
    estimate_time_offset: bool = True
    estimate_clock_drift: bool = False
    robust: bool = True
    min_pairs: int = 30
    max_iterations: int = 100
    noise: str = 'stated'
    noise_a: Optional[DeviceNoise] = None
    noise_b: Optional[DeviceNoise] = None

    def __post_init__(self):
        if self.model not in MODELS:
            raise ConfigError(f'model {self.model!r} is unknown; use one of {", ".join(MODELS)}')
        if self.method not in METHODS:
            raise ConfigError(
                f'method {self.method!r} is unknown; use one of {", ".join(METHODS)}')
        for name in ('max_gap', 'time_offset', 'min_pairs', 'max_iterations'):
            integer = name in ('min_pairs', 'max_iterations')
            _check_number(name, getattr(self, name), integer=integer)
        for name in ('sigma_a', 'sigma_b'):
            try:
                value = tuple(float(v) for v in getattr(self, name))
            except (TypeError, ValueError):  # a scalar, a string: not the two numbers
                value = ()
            if len(value) != 2 or not all(v > 0 and v < float('inf') for v in value):
                raise ConfigError(
                    f'{name} must be two positive numbers (position m, rotation rad), got '
                    f'{getattr(self, name)!r}')
            if value[0] > MAX_SIGMA_M or value[1] > MAX_SIGMA_RAD:
                raise ConfigError(
                    f'{name} = ({value[0]:g}, {value[1]:g}) is no tracker noise in m and rad '
                    f'(above {MAX_SIGMA_M:g} m or {MAX_SIGMA_RAD:g} rad); give metres and '
                    f'radians, e.g. 0.002 0.0087 for 2 mm and 0.5°')
            object.__setattr__(self, name, value)
        for device in 'ab':
            full = getattr(self, f'noise_{device}')
            if full is not None:
                if not isinstance(full, DeviceNoise):
                    raise ConfigError(f'noise_{device} must be a DeviceNoise (e.g. from a noise '
                                      f'file), got {type(full).__name__}')
                # what needs one number (thresholds, summaries) gets the largest principal σ
                object.__setattr__(self, f'sigma_{device}', full.largest_sigmas())
        if self.noise not in NOISE_MODES:
            raise ConfigError(f'noise must be one of {" | ".join(NOISE_MODES)}, got '
                              f'{self.noise!r} (a noise file is given as noise_file)')
        topics = (self.topic_b,) if isinstance(self.topic_b, str) else tuple(self.topic_b)
        object.__setattr__(self, 'topic_b', topics)
        needed = 3 if self.model == 'three_marker' else 1
        if len(topics) != needed:
            if self.model == 'three_marker' and topics == DEFAULT_TOPIC_B:
                object.__setattr__(self, 'topic_b', DEFAULT_TOPICS_B_THREE_MARKER)
            else:
                raise ConfigError(
                    f'model {self.model} needs {needed} device B topic(s), got {len(topics)}: '
                    f'give `topic_b` {"three topics" if needed == 3 else "one topic"}')
        every = (self.topic_a, *self.topic_b)
        same = [t for t in every if every.count(t) > 1]
        if same:
            raise ConfigError(
                f'topic {same[0]} is given for more than one device: each device (topic_a, '
                f'topic_b) needs its own topic, or A would be calibrated against itself')
        for name in ('estimate_time_offset', 'estimate_clock_drift', 'robust'):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ConfigError(f'{name} must be true or false, got {getattr(self, name)!r}')
            object.__setattr__(self, name, bool(getattr(self, name)))
        if self.estimate_clock_drift and not self.estimate_time_offset:
            # the drift is estimated with the offset: a fixed offset would silently drop it
            raise ConfigError(
                f'`estimate_clock_drift` needs the clock offset estimated too (the drift is '
                f'estimated with it, from time_offset {self.time_offset:g} s as the start): '
                f'set `estimate_time_offset`, or leave the drift out')
        if not self.max_gap > 0:
            raise ConfigError(f'max_gap must be > 0 s, got {self.max_gap}')
        if int(self.min_pairs) < 3:
            raise ConfigError(f'min_pairs must be >= 3, got {self.min_pairs}')
        if int(self.max_iterations) < 1:
            raise ConfigError(f'max_iterations must be >= 1, got {self.max_iterations}')

    @property
    def cov_a(self) -> np.ndarray:
        """Device A's stated noise, 6×6 ROS layout (``noise_a`` if given, else ``sigma_a``)."""
        return noise_covariance(self.device_noise('a'))

    @property
    def cov_b(self) -> np.ndarray:
        """Device B's stated noise, 6×6 ROS layout (``noise_b`` if given, else ``sigma_b``)."""
        return noise_covariance(self.device_noise('b'))

    def device_noise(self, device: str):
        """Device ``'a'`` or ``'b'``'s stated noise: its DeviceNoise, else its σ pair."""
        full = getattr(self, f'noise_{device}')
        return full if full is not None else getattr(self, f'sigma_{device}')

    @property
    def max_gap_ns(self) -> int:
        """Maximum pairing gap in nanoseconds."""
        return int(round(self.max_gap * 1e9))

    @property
    def time_offset_ns(self) -> int:
        """Time offset in nanoseconds."""
        return int(round(self.time_offset * 1e9))

    def updated(self, **changes: Any) -> Settings:
        """Return a copy with the given keys changed (None values are ignored)."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})

    def as_dict(self) -> dict:
        """
        Plain dict of the parameters (lists for tuples), e.g. for YAML or JSON.

        The full noise (``noise_a``, ``noise_b``) is no parameter: ``noise_dict`` gives it.
        """
        return {f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
                for f in fields(self) if f.name not in OBJECT_FIELDS}

    def noise_dict(self) -> dict:
        """Return the full noise given (``noise_a``, ``noise_b`` as 3×3 lists), empty when none."""
        out = {}
        for device in 'ab':
            full = getattr(self, f'noise_{device}')
            if full is not None:
                out[f'device_{device}'] = {'position_covariance': [list(r) for r in full.position],
                                           'rotation_covariance': [list(r) for r in full.rotation]}
        return out


def check_settings(settings: Any) -> Settings:
    """
    Return ``settings`` if it is a ``Settings``; refuse anything else in one line.

    Raises
    ------
    ConfigError
        Naming the type given and how to build the settings.

    """
    if not isinstance(settings, Settings):
        raise ConfigError(f'settings must be a coreg_ros.Settings, e.g. Settings(sigma_a=(2e-4, '
                          f'5e-4), method="ols"), got {type(settings).__name__}; a dict of '
                          f'parameters: settings_from_mapping(d)')
    return settings


def _check_number(name: str, value: Any, integer: bool) -> None:
    """Refuse a value of ``name`` that is not a finite (integer) number, naming an example."""
    kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, kinds) or not np.isfinite(
            value):
        example = {'max_gap': 0.05, 'time_offset': 0.0, 'min_pairs': 30,
                   'max_iterations': 100}[name]
        raise ConfigError(f'{name} must be a finite {"integer" if integer else "number"}, got '
                          f'{value!r}; e.g. {name}={example}')


def settings_from_mapping(values: Mapping[str, Any], base: Settings | None = None) -> Settings:
    """
    Build Settings from a mapping of parameter names, e.g. the ``ros__parameters`` of coreg.yaml.

    Unknown keys that belong to the node only (frame ids, storage paths, QoS) are ignored here.
    """
    known = {f.name for f in fields(Settings)} - set(OBJECT_FIELDS)
    base = base or Settings()
    return base.updated(**{k: v for k, v in values.items() if k in known})
