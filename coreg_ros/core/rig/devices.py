"""
The devices B_k of a rig as the user gives them, checked before anything is fitted.

Each device has a name, its stream (three marker streams for ``three_marker``), its model, its
stated noise and its base: devices that name the same base are sensors of one device (one T0,
one clock: "one base, several markers"). Refused, each in one line that names the device and
the fix: a device that is A's own stream, two devices that are one stream, a name given twice,
a model that does not match the streams.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core.errors import ConfigError, InputError
from coreg_ros.core.types import MODELS, PoseStream
import numpy as np


@dataclass(frozen=True)
class RigDevice:
    """
    One device B_k of a rig.

    Attributes
    ----------
    name : str
        How the device is called in results and messages.
    streams : tuple of PoseStream
        Its marker pose stream in its base frame, own clock (three streams for
        ``three_marker``).
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    sigma_b : tuple of float, optional
        Its noise (position m, rotation rad); default the settings' ``sigma_b``.
    base : str, optional
        Its base; devices naming the same base share T0 and their clock. Default: its name.
    topics : tuple of str
        Its topic(s), for reports (empty for arrays).

    """

    name: str
    streams: tuple
    model: str = 'full_pose'
    sigma_b: Optional[tuple] = None
    base: Optional[str] = None
    topics: tuple = field(default_factory=tuple)

    @property
    def base_name(self) -> str:
        """Return the base the device belongs to (its own name by default)."""
        return self.base or self.name


def _same_stream(a: PoseStream, b: PoseStream) -> bool:
    return (len(a) == len(b) and np.array_equal(np.asarray(a.stamps), np.asarray(b.stamps))
            and np.array_equal(np.asarray(a.position), np.asarray(b.position)))


def checked_devices(stream_a: PoseStream, devices: Sequence[RigDevice]) -> list:
    """
    Check the rig's devices and return them as a list, or say what is wrong in one line.

    Raises
    ------
    ConfigError
        No device, an empty or repeated name, an unknown model, the wrong number of streams
        for the model.
    InputError
        A device whose stream is A's own, two devices that are one stream.

    """
    devices = list(devices)
    if not devices:
        raise ConfigError('a rig needs at least one device B; give its topic (--topic-b)')
    names = [d.name for d in devices]
    for d in devices:
        if not d.name:
            raise ConfigError('every device of the rig needs a name (devices[].name)')
        if names.count(d.name) > 1:
            raise ConfigError(f'device name {d.name!r} is given {names.count(d.name)} times; '
                              f'give every device its own name')
        if d.model not in MODELS:
            raise ConfigError(f'device {d.name}: unknown model {d.model!r}; use one of '
                              f'{", ".join(MODELS)}')
        want = 3 if d.model == 'three_marker' else 1
        if len(d.streams) != want:
            raise ConfigError(f'device {d.name}: model {d.model} needs {want} stream(s), got '
                              f'{len(d.streams)}')
        if _same_stream(d.streams[0], stream_a):
            raise InputError(f"device {d.name}'s stream is device A's own "
                             f'({d.topics[0] if d.topics else "the same samples"}); give the '
                             f'stream of another device')
    for i, d in enumerate(devices):
        for e in devices[i + 1:]:
            if _same_stream(d.streams[0], e.streams[0]):
                raise InputError(f'devices {d.name} and {e.name} are the same stream; give '
                                 f'each device its own topic')
    return devices


@dataclass(frozen=True)
class DeviceSpec:
    """
    A device B_k as a configuration names it, before its samples are read.

    Attributes
    ----------
    name : str
    topics : tuple of str
        Its PoseStamped topic(s): three for ``three_marker``.
    model : str
    sigma : tuple of float, optional
        Its noise (position m, rotation rad); None: the two-device ``sigma_b``.
    base : str, optional
        Devices with the same base are sensors of one device.

    """

    name: str
    topics: tuple
    model: str
    sigma: Optional[tuple] = None
    base: Optional[str] = None

    def with_streams(self, streams: Sequence[PoseStream]) -> RigDevice:
        """Return the device with its samples (one stream per topic)."""
        return RigDevice(self.name, tuple(streams), self.model, self.sigma, self.base,
                         tuple(self.topics))


def device_specs(values: dict, model: str) -> list:
    """
    Read a rig's devices from checked parameters (``config_schema.check_rig_value``).

    Parameters
    ----------
    values : dict
        ``devices`` (the names, in order) and ``device.<name>.<field>`` keys.
    model : str
        The model of a device that names none (the two-device ``model``).

    Returns
    -------
    list of DeviceSpec
        Empty when no ``devices`` are given (the two-device keys apply).

    Raises
    ------
    ConfigError
        A device without a topic, a device key of a name that ``devices`` does not list.

    """
    names = list(values.get('devices') or [])
    listed = {k.split('.')[1] for k in values if k.startswith('device.')}
    stray = sorted(listed - set(names))
    if stray:
        raise ConfigError(f'device.{stray[0]}.* is given but {stray[0]!r} is not in devices '
                          f'{names}; add it to devices or remove its keys')
    out = []
    for name in names:
        topics = values.get(f'device.{name}.topic')
        if not topics:
            raise ConfigError(f'device {name} has no topic; add device.{name}.topic: '
                              f'[/{name}/pose]')
        sigma = values.get(f'device.{name}.sigma')
        out.append(DeviceSpec(name, tuple(topics), values.get(f'device.{name}.model', model),
                              None if sigma is None else tuple(sigma),
                              values.get(f'device.{name}.base')))
    return out
