"""
Seeded still recordings: a device held still (at one place or several), its noise known.

What ``coreg noise`` is checked on: a device's pose stream with anisotropic white noise (full
3×3 covariances in its base frame, ``DeviceNoise``), optionally a random walk on top, and
optionally noise growing with the distance from the base's origin (``σ ∝ (r / r_ref)^k``),
the device standing still at ``places`` in turn with smooth moves of ``move_s`` between them.
``add_device_noise`` draws such noise onto any poses (also the noiseless pairs of
``simulate_pairs``, for variance-component checks with anisotropic noise).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.core.types import PoseStream
from coreg_ros.sim.device_noise import add_device_noise
from coreg_ros.sim.devices import DEFAULT_START_NS
from coreg_ros.sim.motion import Motion, random_rotation
import numpy as np


@dataclass(frozen=True)
class StillRecording:
    """
    A simulated still stream and its truth.

    Attributes
    ----------
    stream : PoseStream
    noise : DeviceNoise
        The white noise at ``reference_m`` from the base's origin.
    places : ndarray, shape (K, 3)
        Where the device stood, m.
    still : list of (int, int)
        Stamps (ns) of the start and end of each still stretch.
    reference_m, exponent : float
        σ at distance r is ``(r / reference_m)^exponent`` times the reference noise.
    random_walk : (float, float)
        Random walk intensity of position (m/√s) and rotation (rad/√s).

    """

    stream: PoseStream
    noise: DeviceNoise
    places: np.ndarray
    still: list
    reference_m: float
    exponent: float
    random_walk: tuple

    def noise_at(self, k: int) -> DeviceNoise:
        """Return the white noise where the device stood the k-th time."""
        f = (np.linalg.norm(self.places[k]) / self.reference_m) ** (2.0 * self.exponent)
        return self.noise.scaled(f, f)


def simulate_still(seed: int, noise: DeviceNoise, duration: float = 30.0, rate: float = 100.0,
                   places: Optional[np.ndarray] = None, move_s: float = 2.0,
                   exponent: float = 0.0, reference_m: Optional[float] = None,
                   random_walk: tuple = (0.0, 0.0), start_ns: int = DEFAULT_START_NS,
                   frame_id: str = 'device_base') -> StillRecording:
    """
    Simulate a device standing still at one place or several (moving between them).

    Parameters
    ----------
    seed : int
        Seed of every draw.
    noise : DeviceNoise
        White noise at ``reference_m``.
    duration : float
        Total still time, s (split evenly between the places; the moves come on top).
    rate : float
        Hz.
    places : ndarray, shape (K, 3), optional
        Where the device stands, m in its base frame (default one place 0.5 m out).
    move_s : float
        Duration of each move between places, s.
    exponent : float
        σ grows as ``(r / reference_m)^exponent`` with the distance r from the origin.
    reference_m : float, optional
        Default: the first place's distance.
    random_walk : (float, float)
        Random walk intensity (m/√s, rad/√s) added to the white noise.
    start_ns : int
        Stamp of the first sample, ns.
    frame_id : str
        The stream's frame id.

    Returns
    -------
    StillRecording

    """
    rng = np.random.default_rng(seed)
    places = np.array([[0.3, 0.2, 0.35]]) if places is None else np.asarray(places, float)
    ref = float(np.linalg.norm(places[0])) if reference_m is None else float(reference_m)
    k = len(places)
    hold = duration / k
    q0 = random_rotation(rng)
    t_parts, p_parts, still = [], [], []
    t = 0.0
    dt = 1.0 / rate
    for i in range(k):
        n = int(round(hold * rate))
        ts = t + np.arange(n) * dt
        still.append((start_ns + int(round(ts[0] * 1e9)), start_ns + int(round(ts[-1] * 1e9))))
        t_parts.append(ts)
        p_parts.append(np.repeat(places[i][None], n, axis=0))
        t = ts[-1] + dt
        if i + 1 < k:
            m = int(round(move_s * rate))
            s = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, m + 1) / (m + 1))
            t_parts.append(t + np.arange(m) * dt)
            p_parts.append(places[i] + s[:, None] * (places[i + 1] - places[i]))
            t = t + m * dt
    times = np.concatenate(t_parts)
    position = np.concatenate(p_parts)
    q = np.repeat(q0[None], len(times), axis=0)
    scale = (np.linalg.norm(position, axis=1) / ref) ** exponent
    position, q = add_device_noise(rng, position, q, noise, scale)
    if any(random_walk):
        steps = rng.standard_normal((len(times), 6)) * np.sqrt(dt)
        position = position + random_walk[0] * np.cumsum(steps[:, :3], axis=0)
        q = quat.canonical(quat.multiply(quat.exp(random_walk[1]
                                                  * np.cumsum(steps[:, 3:], axis=0)), q))
    stamps = start_ns + np.round(times * 1e9).astype(np.int64)
    return StillRecording(PoseStream(stamps, position, q, frame_id), noise, places, still, ref,
                          float(exponent), tuple(float(v) for v in random_walk))


def anisotropic_noise(rng: np.random.Generator, sigma: tuple, depth_factor: float = 3.0,
                      axis: Optional[np.ndarray] = None) -> DeviceNoise:
    """
    Return a noise ``depth_factor`` times larger along one axis (an optical tracker's depth).

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the depth axis when not given.
    sigma : (float, float)
        Lateral σ of position (m) and rotation (rad).
    depth_factor : float
        σ along the depth axis over the lateral σ.
    axis : ndarray, shape (3,), optional
        The depth axis in the base frame (random when None).

    """
    if axis is None:
        axis = rng.standard_normal(3)
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    shape = np.eye(3) + (depth_factor ** 2 - 1.0) * np.outer(axis, axis)
    return DeviceNoise.from_covariances(shape * sigma[0] ** 2, shape * sigma[1] ** 2)


@dataclass(frozen=True, eq=False)
class PausedMotion(Motion):
    """
    A motion that stops: A's tool stands still for ``pauses``, then goes on where it stopped.

    Attributes
    ----------
    pauses : tuple of (float, float)
        (start s, duration s) of each pause, in the recording's time (from its origin).

    """

    pauses: tuple = ()

    def warp(self, t_seconds) -> np.ndarray:
        """Return the motion's own time at recording time t: held still through each pause."""
        t = np.atleast_1d(np.asarray(t_seconds, dtype=float))
        held = sum(np.clip(t - start, 0.0, length) for start, length in self.pauses)
        return t - held

    def rotvec(self, t_seconds) -> np.ndarray:  # noqa: D102 - Motion's, at the warped time
        return super().rotvec(self.warp(t_seconds))

    def pose(self, t_seconds) -> tuple:  # noqa: D102 - Motion's, at the warped time
        t = self.warp(t_seconds)
        return super().pose(t)


def paused(motion: Motion, pauses) -> PausedMotion:
    """
    Return ``motion`` with the tool standing still for each (start s, duration s) of ``pauses``.

    For ``simulate_recording(..., motion=paused(make_motion(rng, 'diverse'), [(5, 8)]))``: a
    recording with still parts, where ``coreg noise`` measures both devices.
    """
    values = {f.name: getattr(motion, f.name) for f in fields(Motion)}
    return PausedMotion(**values, pauses=tuple((float(a), float(b)) for a, b in pauses))
