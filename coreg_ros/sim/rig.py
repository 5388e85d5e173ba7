"""
Seeded recordings of a whole rig: device A and several devices B_k on one rigid body.

Each device B_k has its own truth (T0_k, T1_k, Ikits eqs. 16, 18, 19), model, noise, rate and
clock: its stamps are the true instants plus its clock offset τ_k (B's clock minus A's), so
clocks minutes or hours apart share no stamps. Sensors of one device (the same ``base``) share
its base T0, its clock and its sampling instants (one EM field generator sampling all of its
sensors together); each has its own T1. The motion and A are ``devices.simulate_recording``'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Optional, Union

from coreg_ros.core.errors import ConfigError
from coreg_ros.core.types import MODELS, PoseStream
from coreg_ros.sim.devices import (
    _seconds,
    _stamps,
    add_pose_noise,
    check_allocation,
    DEFAULT_SIGMA_A,
    DEFAULT_START_NS,
    FRAME_A,
)
from coreg_ros.sim.motion import make_motion, Motion
from coreg_ros.sim.truth import random_truth, Truth, validate_sigma
import numpy as np


@dataclass(frozen=True)
class SimDevice:
    """
    One device B_k of a simulated rig.

    Attributes
    ----------
    name : str
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    rate : float
        Hz (sensors of one base sample at their first device's rate).
    sigma : tuple of float
        Noise (position m, rotation rad).
    clock_offset : float
        τ_k, s: B_k's clock minus A's (sensors of one base share their first device's).
    base : str, optional
        Devices with the same base are sensors of one device; default: the device's name.

    """

    name: str
    model: str = 'full_pose'
    rate: float = 50.0
    sigma: tuple = (0.0005, 0.002)
    clock_offset: float = 0.0
    base: Optional[str] = None

    @property
    def base_name(self) -> str:
        """Return the base this device is a sensor of (its own name by default)."""
        return self.base or self.name


@dataclass(frozen=True, eq=False)
class SimRig:
    """
    A simulated rig recording.

    Attributes
    ----------
    stream_a : PoseStream
        A's tool poses in A's base frame, A's clock.
    streams : list of list of PoseStream
        Per device, its stream (three marker streams for ``three_marker``), its own clock.
    truths : list of Truth
        Per device; sensors of one base share p0, q0.
    devices : tuple of SimDevice
    motion : Motion

    """

    stream_a: PoseStream
    streams: list
    truths: list
    devices: tuple
    motion: Motion


def simulate_rig(seed: int, duration: float, devices: Sequence[SimDevice], *,
                 rate_a: float = 100.0, sigma_a=DEFAULT_SIGMA_A,
                 motion: Union[str, Motion] = 'diverse',
                 start_ns: int = DEFAULT_START_NS) -> SimRig:
    """
    Simulate device A and the devices B_k tracking one rigidly linked body.

    Parameters
    ----------
    seed : int
        The same seed and arguments give bit-identical output.
    duration : float
        s; A's stamps lie in ``[start_ns, start_ns + duration)`` on A's clock.
    devices : sequence of SimDevice
        The devices B_k.
    rate_a : float
        A's rate, Hz.
    sigma_a : tuple of float
        A's noise (position m, rotation rad).
    motion : str or Motion
        A ``make_motion`` preset or a motion.
    start_ns : int
        Origin of the motion and of A's clock, ns.

    Returns
    -------
    SimRig

    """
    devices = tuple(devices)
    if not devices:
        raise ConfigError('devices: a rig needs at least one device B')
    for d in devices:
        if d.model not in MODELS:
            raise ConfigError(f'device {d.name}: unknown model {d.model!r}; use one of {MODELS}')
        validate_sigma(d.sigma, f'device {d.name} sigma')
    sigma_a = validate_sigma(sigma_a, 'sigma_a')
    check_allocation((rate_a + sum(3 * d.rate if d.model == 'three_marker' else d.rate
                                   for d in devices)) * duration,
                     f'a rig recording of {duration:g} s', 'the duration or the rates')
    seqs = np.random.SeedSequence(int(seed)).spawn(3 + 2 * len(devices))
    rng_motion, rng_stamps, rng_a = (np.random.default_rng(s) for s in seqs[:3])
    motion = make_motion(rng_motion, motion) if isinstance(motion, str) else motion
    duration_ns = int(round(duration * 1e9))
    stamps_a = _stamps(rng_stamps, rate_a, duration_ns, start_ns)
    pos_a, q_a = motion.pose(_seconds(stamps_a, start_ns))
    noisy_a = add_pose_noise(rng_a, pos_a, q_a, sigma_a)
    stream_a = PoseStream(stamps_a, noisy_a[0], noisy_a[1], FRAME_A)

    instants, bases, truths, streams = {}, {}, [], []
    for k, d in enumerate(devices):
        rng_truth, rng_noise = (np.random.default_rng(s) for s in seqs[3 + 2 * k:5 + 2 * k])
        truth = random_truth(rng_truth, d.model, sigma_a=sigma_a, sigma_b=tuple(d.sigma))
        base = d.base_name
        if base in bases:  # a sensor of a device already drawn: its base, clock and instants
            lead = bases[base]
            truth = replace(truth, p0=lead[0].p0, q0=lead[0].q0)
            true_ns, offset = instants[base], lead[1]
        else:
            true_ns = _stamps(rng_stamps, d.rate, duration_ns, start_ns)
            instants[base], offset = true_ns, float(d.clock_offset)
            bases[base] = (truth, offset)
        streams.append(_device_streams(truth, d, motion, true_ns, offset, start_ns, rng_noise))
        truths.append(truth)
    return SimRig(stream_a, streams, truths, devices, motion)


def _device_streams(truth: Truth, device: SimDevice, motion: Motion, true_ns: np.ndarray,
                    offset_s: float, start_ns: int, rng: np.random.Generator) -> list:
    """Return the device's stream(s), stamped on its own clock (true instant + τ)."""
    pos_b, q_b = truth.device_b(*motion.pose(_seconds(true_ns, start_ns)))
    full = device.model == 'full_pose'
    noisy_pos, noisy_q = add_pose_noise(rng, pos_b, q_b if full else None, tuple(device.sigma))
    stamps = true_ns + np.int64(round(offset_s * 1e9))
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (len(stamps), 1))
    frame = f'{device.base_name}_base'
    return [PoseStream(stamps.copy(), np.ascontiguousarray(noisy_pos[:, j]),
                       noisy_q if full else identity.copy(), frame)
            for j in range(noisy_pos.shape[1])]
