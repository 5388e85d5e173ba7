"""
coreg_node with a rig's devices list (issue 23): one channel per device B_k, each with A.

A parameter file's ``devices: [optical, em]`` and ``device.<name>.{topic, model, sigma, base}``
(the keys ``coreg calibrate --config`` reads) make the node subscribe to A and to every
device's topic(s) once, and calibrate, guide and watch each device against A in a channel of
its own: ``~/<name>/base_to_base``, ``~/<name>/tool_to_marker``, ``~/<name>/fused_pose``,
``~/<name>/uncertainty_markers``, ``~/<name>/calibration_stale``, and /diagnostics statuses
named ``<node>/<name>`` (guidance says which device lacks what, the watchdog which device
moved). Every device's frames are its own (``<name>_base``, ``<name>_marker``); on /tf_static
A's base is the parent of every device's base (tf2's one-parent rule).

Each device is calibrated with A alone, as ``coreg calibrate`` calibrates a rig whose devices
share neither base nor clock: the joint fit of such a rig is exactly its devices' fits.
Sensors that share a base are calibrated each with its own T0 here; their joint fit (one T0,
cross terms, loops) is ``coreg calibrate BAG --config FILE`` on the node's saved samples.
"""

from __future__ import annotations

from dataclasses import replace

from coreg_ros.core.rig.devices import DeviceSpec
from coreg_ros.core.settings import Settings
from coreg_ros.ros.parameters import NodeConfig, ParameterView


class DeviceView:
    """
    A node's current parameters as one device of its rig sees them.

    Everything is the node's but the calibration settings' ``topic_b``, ``model`` and
    ``sigma_b``, which are the device's (its ``sigma`` if given, else the node's ``sigma_b``),
    and the noise in use, which is the device's own (``live_noise.NoiseSources``).

    Parameters
    ----------
    view : ParameterView
        The node's parameters (without noise sources).
    spec : DeviceSpec
        The device.
    noise : live_noise.NoiseSources, optional
        The device's noise sources (what it measured while still, its last estimate).

    """

    def __init__(self, view: ParameterView, spec: DeviceSpec, noise=None):
        self._view = view
        self.spec = spec
        self.noise = noise

    def __call__(self, name: str):
        """Return the current value of the node's parameter ``name``."""
        return self._view(name)

    def settings(self) -> Settings:
        """Return the calibration settings of this device against A, with its noise in use."""
        settings = device_settings(self._view.settings(), self.spec)
        return settings if self.noise is None else self.noise.apply(settings)


def device_settings(settings: Settings, spec: DeviceSpec) -> Settings:
    """Return ``settings`` with the device's topics, model and noise (the rest the node's)."""
    return settings.updated(topic_b=tuple(spec.topics), model=spec.model, sigma_b=spec.sigma)


def device_config(config: NodeConfig, spec: DeviceSpec) -> NodeConfig:
    """
    Return the node's configuration as one device's channel uses it.

    Its settings (``device_settings``) and its own frames: ``<name>_base`` for B's base and
    ``<name>_marker`` for its marker (A's frames are the node's).
    """
    return replace(config, settings=device_settings(config.settings, spec),
                   frame_base_b=f'{spec.name}_base', frame_marker=f'{spec.name}_marker',
                   devices=())


def rig_topics(devices) -> tuple:
    """Return every device's topics, each once, in the devices' order."""
    return tuple(dict.fromkeys(t for spec in devices for t in spec.topics))
