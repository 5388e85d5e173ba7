"""
The noise file: each device's noise as 3×3 covariances in its base frame (YAML or JSON).

``coreg noise RECORDING --out FILE`` writes it; ``--noise FILE`` (calibrate, diagnose, plan,
validate-diagnosis), the node's ``noise_file`` and ``coreg_ros.calibrate(noise=FILE)`` read it.
Layout::

    coreg_noise:
      version: 1
      units: {position: m, rotation: rad}
      source: measured          # measured (still parts) | estimated (with a calibration)
      recording: /path/to/bag   # where it was measured (informative)
      device_a:
        topic: /device_a/pose   # the topic it was measured on: checked against the settings
        frame_id: device_a_base
        position_covariance: [[..], [..], [..]]   # m², about A's base axes
        rotation_covariance: [[..], [..], [..]]   # rad², rotation vector about A's base axes
        position_sigma_m: [..]      # principal σ, largest first (informative)
        position_axes: [[..], ..]   # their axes as rows (informative)
        rotation_sigma_rad: [..]
        rotation_axes: [[..], ..]
      device_b: {same}

A hand-written file may give ``position_sigma_m`` (one σ: isotropic; or three principal σ with
``position_axes``) instead of the covariance, likewise the rotation; one device may be left
out (it keeps ``sigma_a``/``sigma_b``). The ``noise`` section of ``coreg calibrate --json``
(``--noise auto``) is read too. A file in other units, for other topics, with a σ that is not
positive or a covariance that is not positive definite is refused with the reason.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Optional

from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.core.noise_model import checked_covariance, DeviceNoise, UNITS
from coreg_ros.core.settings import Settings
import numpy as np

#: Version of the layout written.
VERSION = 1
#: The top-level key of a noise file.
KEY = 'coreg_noise'


@dataclass(frozen=True)
class NoiseFile:
    """
    A noise file read and checked.

    Attributes
    ----------
    path : str
    device_a, device_b : DeviceNoise or None
        None: the file does not give that device.
    topics : dict
        ``{'a': topic or None, 'b': tuple of topics or None}`` as the file names them.
    source : str

    """

    path: str
    device_a: Optional[DeviceNoise]
    device_b: Optional[DeviceNoise]
    topics: dict
    source: str = ''


def _refuse(path, what: str) -> ConfigError:
    return ConfigError(f'noise file {path}: {what}')


def _channel(path, block: Mapping, device: str, channel: str) -> np.ndarray:
    """One channel's covariance from a device block: the covariance, or σ (and axes)."""
    unit = UNITS[channel]
    cov = block.get(f'{channel}_covariance')
    sigma = block.get(f'{channel}_sigma_{unit}')
    where = f'device {device.upper()} {channel}'
    if cov is not None:
        value = cov
    elif sigma is not None:
        s = np.asarray(sigma, dtype=float) if _numbers(sigma) else None
        if s is None:
            raise _refuse(path, f'{channel}_sigma_{unit} of device {device.upper()} must be '
                                f'numbers, got {sigma!r}')
        if s.ndim == 0:
            value = s
        else:
            axes = block.get(f'{channel}_axes')
            if axes is None or np.shape(axes) != (3, 3) or s.shape != (3,):
                raise _refuse(path, f'{channel}_sigma_{unit} of device {device.upper()} is a '
                                    f'list: give its principal axes as {channel}_axes (3 rows), '
                                    f'or one σ, or {channel}_covariance')
            a = np.asarray(axes, dtype=float)
            a = a / np.linalg.norm(a, axis=1, keepdims=True)
            if not np.all(s > 0):
                raise _refuse(path, f'{where}: standard deviations must be positive, got '
                                    f'{s.tolist()}')
            value = a.T @ np.diag(s ** 2) @ a
    else:
        raise _refuse(path, f'device {device.upper()} gives no {channel} noise: add '
                            f'{channel}_covariance (3×3, {unit}²) or {channel}_sigma_{unit}')
    if not _numbers(value):
        raise _refuse(path, f'{where} covariance must be numbers, got {value!r}')
    try:
        return checked_covariance(value, where, channel)
    except ConfigError as e:
        raise _refuse(path, str(e)) from e


def _numbers(value) -> bool:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return a.dtype.kind == 'f'


def _device(path, block: Any, device: str) -> Optional[DeviceNoise]:
    if block is None:
        return None
    if not isinstance(block, Mapping):
        raise _refuse(path, f'device_{device} must be a mapping with position_covariance and '
                            f'rotation_covariance')
    pos = _channel(path, block, device, 'position')
    rot = _channel(path, block, device, 'rotation')
    return DeviceNoise.from_covariances(pos, rot, device.upper())


def _check_units(path, units: Any) -> None:
    if units is None:
        return
    if not isinstance(units, Mapping):
        raise _refuse(path, f'units must be {{position: m, rotation: rad}}, got {units!r}')
    for channel, unit in UNITS.items():
        given = units.get(channel, unit)
        if str(given).strip().lower() != unit:
            factor = {'mm': '1e-3 on σ, 1e-6 on covariances',
                      'cm': '1e-2 on σ, 1e-4 on covariances',
                      'deg': 'π/180 on σ, (π/180)² on covariances',
                      'degree': 'π/180 on σ', 'degrees': 'π/180 on σ'}.get(
                str(given).strip().lower(), 'the factor to SI')
            raise _refuse(path, f'its {channel} noise is in {given}; coreg reads {unit} '
                                f'(convert with {factor}, or measure again with coreg noise)')


def noise_from_dict(doc: Any, path: str = '<noise>') -> NoiseFile:
    """
    Read a noise document (layout in the module docstring); one-line refusals.

    Raises
    ------
    ConfigError
        Other units, no device, a σ not positive, a covariance not positive definite.

    """
    if isinstance(doc, Mapping) and KEY in doc:
        doc = doc[KEY]
    elif isinstance(doc, Mapping) and isinstance(doc.get('noise'), Mapping):
        doc = doc['noise']  # the noise section of coreg calibrate --json
    if not isinstance(doc, Mapping) or not ({'device_a', 'device_b'} & set(doc)):
        raise _refuse(path, f'no device_a or device_b noise; write one with coreg noise '
                            f'RECORDING --out FILE (top-level key {KEY})')
    version = doc.get('version', VERSION)
    if not isinstance(version, int) or version > VERSION:
        raise _refuse(path, f'version {version!r} is newer than this coreg reads ({VERSION}); '
                            f'update coreg_ros')
    _check_units(path, doc.get('units'))
    devices = {d: _device(path, doc.get(f'device_{d}'), d) for d in 'ab'}
    topics = {}
    for d in 'ab':
        block = doc.get(f'device_{d}')
        topic = block.get('topic') if isinstance(block, Mapping) else None
        if isinstance(topic, (list, tuple)):
            topic = tuple(str(t) for t in topic)
        elif topic:
            topic = (str(topic),) if d == 'b' else str(topic)
        topics[d] = topic or None
    return NoiseFile(str(path), devices['a'], devices['b'], topics, str(doc.get('source', '')))


def load_noise_file(path) -> NoiseFile:
    """Read a noise file (YAML or JSON); one-line errors naming the file."""
    from coreg_ros.files.parameters import yaml_loader
    import yaml

    try:
        with open(path, encoding='utf-8') as f:
            doc = yaml.load(f, Loader=yaml_loader())  # noqa: S506 - a SafeLoader
    except OSError as e:
        raise InputError(f'cannot read the noise file {path}: {e.strerror}') from e
    except yaml.YAMLError as e:
        raise InputError(f'the noise file {path} is neither YAML nor JSON ({e}); write one '
                         f'with coreg noise RECORDING --out FILE') from e
    return noise_from_dict(doc, str(path))


def with_noise_file(settings: Settings, noise: NoiseFile) -> Settings:
    """
    Return the settings with the file's noise (``noise_a``, ``noise_b``), topics checked.

    Raises
    ------
    ConfigError
        The file was measured on other topics than the settings calibrate.

    """
    for d, used in (('a', settings.topic_a), ('b', tuple(settings.topic_b))):
        named = noise.topics[d]
        if named is not None and named != used and getattr(noise, f'device_{d}') is not None:
            flag = f'--topic-{d}'
            shown = named if isinstance(named, str) else ' '.join(named)
            now = used if isinstance(used, str) else ' '.join(used)
            raise _refuse(noise.path, f'device {d.upper()} noise is for topic {shown}, but '
                                      f'device {d.upper()} is {now}: measure these topics '
                                      f'(coreg noise BAG {flag} {now} --out FILE) or give '
                                      f'{flag} {shown}')
    changes = {f'noise_{d}': getattr(noise, f'device_{d}') for d in 'ab'
               if getattr(noise, f'device_{d}') is not None}
    return replace(settings, **changes)


def device_block(noise: DeviceNoise, topic=None, frame_id: str = '', extra=None) -> dict:
    """Return the YAML block of one device (covariances, then principal σ and axes to read)."""
    out = {}
    if topic:
        out['topic'] = list(topic) if isinstance(topic, (list, tuple)) and len(topic) > 1 \
            else (topic[0] if isinstance(topic, (list, tuple)) else topic)
    if frame_id:
        out['frame_id'] = frame_id
    for channel in ('position', 'rotation'):
        out[f'{channel}_covariance'] = [list(r) for r in getattr(noise, channel)]
    for channel in ('position', 'rotation'):
        sigma, axes = noise.principal(channel)
        out[f'{channel}_sigma_{UNITS[channel]}'] = [float(v) for v in sigma]
        out[f'{channel}_axes'] = [[float(v) for v in row] for row in axes]
    out.update(extra or {})
    return out


def noise_document(blocks: dict, source: str, recording: str = '') -> dict:
    """Return the whole noise file: ``{coreg_noise: {version, units, source, device_a, ..}}``."""
    body = {'version': VERSION, 'units': dict(UNITS), 'source': source}
    if recording:
        body['recording'] = recording
    body.update(blocks)
    return {KEY: body}


def write_noise_file(path, document: dict):
    """Write a noise document atomically (YAML; ``.json`` names get JSON)."""
    from coreg_ros.files.atomic import write_atomic, write_json
    import yaml

    if str(path).endswith('.json'):
        return write_json(path, document)
    # rows of numbers on one line each: a 3×3 covariance reads as one
    return write_atomic(path, yaml.safe_dump(document, sort_keys=False, default_flow_style=None,
                                             width=120))
