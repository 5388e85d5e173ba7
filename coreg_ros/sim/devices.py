"""
Seeded synthetic devices: recordings of two unsynchronised trackers, and synchronised pairs.

Device A reports its tool pose in its base frame; device B reports its marker pose(s) in its
base frame through the model of ``coreg_ros.sim.truth`` (Ikits eqs. 16, 18, 19). Both devices
stamp on one common clock at their own rates and random phases; each device's true pose is the
motion evaluated at its own stamps (exact continuous time, no interpolation). Noise is Gaussian,
independent per device and sample: position ``p + N(0, σ_pos² I)`` in the base frame, rotation
``q_meas = Exp(δθ) ⊗ q_true`` with ``δθ ~ N(0, σ_rot² I)`` about the fixed base-frame axes (the
``PoseWithCovariance`` convention of docs/design.md §3).

The same seed gives bit-identical output. The randomness of the truth, the motion, the stamp
phases, each device's noise and the effects comes from separate streams spawned from the seed,
so passing a fixed ``truth`` or ``motion`` does not change the other draws.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Optional, Union

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.memory import check_memory
from coreg_ros.core.settings import DEFAULT_TOPIC_A, DEFAULT_TOPIC_B, DEFAULT_TOPICS_B_THREE_MARKER
from coreg_ros.core.types import MODELS, Pairs, PoseStream
from coreg_ros.sim.device_noise import add_device_noise
from coreg_ros.sim.injection import apply_effects, effect_stage, EffectContext, STAGES
from coreg_ros.sim.motion import make_motion, Motion
from coreg_ros.sim.truth import random_truth, Truth, validate_sigma
import numpy as np

#: Default origin of simulated time: 2023-11-14T22:13:20Z, in nanoseconds.
DEFAULT_START_NS = 1_700_000_000_000_000_000
#: ``header.frame_id`` of the simulated devices' messages.
FRAME_A = 'device_a_base'
FRAME_B = 'device_b_base'
#: Default noise (position m, rotation rad), the same as ``coreg_ros.core.settings``.
DEFAULT_SIGMA_A = (0.0002, 0.0005)
DEFAULT_SIGMA_B = (0.0005, 0.002)
#: Shortest span of the motion sampled by ``simulate_pairs``, s.
MIN_PAIRS_DURATION = 60.0
#: Peak bytes the simulator allocates per sample of one stream (measured: 200-290 B with the
#: motion, the noise and the copies; rounded up).
BYTES_PER_SAMPLE = 320

_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


@dataclass(frozen=True, eq=False)
class SimRecording:
    """
    A simulated recording: one stream per topic and the truth behind it.

    Attributes
    ----------
    streams : dict of str to PoseStream
        ``topics_a`` → A's tool poses in ``device_a_base``; each of ``topics_b`` → B's marker
        poses in ``device_b_base`` (identity orientation for ``position_only`` and
        ``three_marker``, whose B reports positions only). The three marker topics share stamps.
    truth : Truth
        The true calibration, device noise and applied effects.
    topics_a : str
        Topic of device A.
    topics_b : tuple of str
        Topic(s) of device B (three for ``three_marker``, marker 1 first).
    motion : Motion, optional
        A's tool motion; ``motion.pose((stamps - start_ns) * 1e-9)`` is the true pose.
    start_ns : int
        Origin of the motion's time on the common clock, ns.
    duration : float
        Length of the recording, s.
    seed : int, optional
        The seed it was made from.

    """

    streams: dict
    truth: Truth
    topics_a: str
    topics_b: tuple
    motion: Optional[Motion] = None
    start_ns: int = DEFAULT_START_NS
    duration: float = 0.0
    seed: Optional[int] = None

    @property
    def stream_a(self) -> PoseStream:
        """Device A's stream."""
        return self.streams[self.topics_a]

    @property
    def streams_b(self) -> tuple:
        """Device B's stream(s), in the order of ``topics_b``."""
        return tuple(self.streams[t] for t in self.topics_b)


def check_allocation(n_samples: float, what: str, fix: str,
                     max_bytes: Optional[int] = None) -> None:
    """
    Refuse a simulation of ``n_samples`` samples that would not fit in memory (before it runs).

    ``core.memory.check_memory`` at ``BYTES_PER_SAMPLE``; ``what`` and ``fix`` name the
    recording and the options to lower; ``max_bytes`` defaults to ``memory_limit()``.

    Raises
    ------
    InputError
        One line with the estimate and the limit.

    """
    check_memory(n_samples, BYTES_PER_SAMPLE, what, fix, max_bytes)


def _check_seed(seed) -> int:
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f'seed: expected an integer >= 0, got {seed!r}; pass e.g. --seed 1')
    return int(seed)


def _check_model(model: str) -> None:
    if model not in MODELS:
        raise ConfigError(f'model: unknown model {model!r}; use one of {MODELS}')


def _resolve_truth(truth: Optional[Truth], model: str, rng: np.random.Generator,
                   sigma_a: tuple, sigma_b: tuple) -> Truth:
    if truth is None:
        return random_truth(rng, model, sigma_a=sigma_a, sigma_b=sigma_b)
    if not isinstance(truth, Truth):
        raise ConfigError(f'truth: expected a Truth or None, got {type(truth).__name__}')
    if truth.model != model:
        raise ConfigError(f'truth: made for model {truth.model!r} but model={model!r}; pass '
                          f'the same model or a truth from random_truth(rng, {model!r})')
    return replace(truth, sigma_a=sigma_a, sigma_b=sigma_b)


def _resolve_motion(motion: Union[str, Motion], rng: np.random.Generator) -> Motion:
    if isinstance(motion, Motion):
        return motion
    if isinstance(motion, str):
        return make_motion(rng, motion)
    raise ConfigError(f'motion: expected a preset name or a Motion, got {type(motion).__name__}')


def add_pose_noise(rng: np.random.Generator, position: np.ndarray, quat_wxyz: Optional[np.ndarray],
                   sigma: tuple) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """
    Add Gaussian device noise to poses expressed in a device's base frame.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the noise.
    position : ndarray, shape (N, 3) or (N, k, 3)
        True positions, m; every marker gets its own noise.
    quat_wxyz : ndarray, shape (N, 4), optional
        True orientations (w, x, y, z); None for a position-only device.
    sigma : tuple of float
        (position m, rotation rad) standard deviations; zero adds no noise at all.

    Returns
    -------
    position : ndarray
        ``position + N(0, σ_pos² I)``.
    quat_wxyz : ndarray or None
        ``Exp(δθ) ⊗ q_true`` with ``δθ ~ N(0, σ_rot² I)`` in the base frame, w >= 0.

    """
    sigma_pos, sigma_rot = sigma
    position = np.array(position, dtype=float)
    dp = rng.standard_normal(np.shape(position))
    if sigma_pos > 0.0:
        position = position + sigma_pos * dp
    if quat_wxyz is not None:
        dtheta = rng.standard_normal((np.shape(quat_wxyz)[0], 3))
        if sigma_rot > 0.0:
            quat_wxyz = quat.canonical(quat.multiply(quat.exp(sigma_rot * dtheta), quat_wxyz))
    return position, quat_wxyz


def _device_noise(rng: np.random.Generator, position, quat_wxyz, noise) -> tuple:
    """Add a device's noise: a σ pair (``add_pose_noise``) or a DeviceNoise (full covariances)."""
    if isinstance(noise, tuple):
        return add_pose_noise(rng, position, quat_wxyz, noise)
    return add_device_noise(rng, position, quat_wxyz, noise)


def _stamps(rng: np.random.Generator, rate: float, duration_ns: int, start_ns: int) -> np.ndarray:
    """Stamps at ``rate`` Hz with a random phase in [0, period), within [0, duration), int64 ns."""
    period = 1e9 / rate
    phase = rng.uniform(0.0, period)
    k = np.arange(int(np.ceil(duration_ns / period)) + 1)
    offsets = np.round(phase + k * period).astype(np.int64)
    return np.int64(start_ns) + offsets[offsets < duration_ns]


def _seconds(stamps: np.ndarray, start_ns: int) -> np.ndarray:
    return (stamps - np.int64(start_ns)).astype(float) * 1e-9


def _streams_b(model: str, topics_b: tuple, stamps: np.ndarray, position: np.ndarray,
               quat_wxyz: np.ndarray) -> dict:
    """B's streams from positions (N, k, 3) and orientations (N, 4)."""
    if model != 'full_pose':
        quat_wxyz = np.broadcast_to(_IDENTITY, (stamps.shape[0], 4)).copy()
    return {topic: PoseStream(stamps=stamps.copy(), position=np.ascontiguousarray(position[:, j]),
                              quat_wxyz=quat_wxyz.copy(), frame_id=FRAME_B)
            for j, topic in enumerate(topics_b)}


def _check_same_stamps(streams: dict, reference: dict, stage: str) -> None:
    for topic, ref in reference.items():
        if not np.array_equal(streams[topic].stamps, ref.stamps):
            raise ConfigError(f'effects: a {stage!r} effect changed the stamps or samples of '
                              f"{topic}; give it stage 'measured' instead")


def simulate_recording(seed: int, duration: float, model: str = 'full_pose', *,
                       rate_a: float = 100.0, rate_b: float = 50.0,
                       sigma_a=DEFAULT_SIGMA_A, sigma_b=DEFAULT_SIGMA_B,
                       motion: Union[str, Motion] = 'diverse', truth: Optional[Truth] = None,
                       start_ns: int = DEFAULT_START_NS,
                       effects: Sequence = (), max_bytes: Optional[int] = None,
                       noise_a=None, noise_b=None) -> SimRecording:
    """
    Simulate a recording of devices A and B tracking one rigidly linked body.

    Parameters
    ----------
    seed : int
        Seed (>= 0); the same seed and arguments give bit-identical output.
    duration : float
        Length of the recording, s. Stamps lie in ``[start_ns, start_ns + duration)``.
    model : str
        ``full_pose`` (B reports its marker pose), ``position_only`` (B reports a position;
        its orientation is the identity and meaningless) or ``three_marker`` (three B topics,
        one per marker, same stamps, identity orientation).
    rate_a, rate_b : float
        Sample rates of A and B, Hz. Each device starts at its own random phase within one
        period: the devices are not synchronised, but both stamp on the same clock.
    sigma_a, sigma_b : tuple of float
        Noise standard deviations (position m, rotation rad) of A and B; zero means none.
    motion : str or Motion
        A preset of ``make_motion`` (``MOTION_PRESETS``: ``'diverse'``, the restricted rigs
        ``'scara'``, ``'planar'``, ``'gantry'``, ``'turntable'``, and ``'single_axis'``,
        ``'no_rotation'``, ``'static'``) or a ``Motion``.
    truth : Truth, optional
        The calibration to simulate (its model must equal ``model``; its sigmas are replaced
        by ``sigma_a``, ``sigma_b``). Drawn by ``random_truth`` when None.
    start_ns : int
        Origin of the motion's time and of the recording on the common clock, ns.
    effects : sequence of Effect
        Unmodelled effects (``coreg_ros.sim.injected``), applied stage by stage
        (``coreg_ros.sim.injection.STAGES``: before the noise, on the noise, after the noise),
        in the given order within a stage; ``Truth.effects`` lists them in the order applied.
        Empty by default: the recording follows the model exactly.
    noise_a, noise_b : DeviceNoise, optional
        Full (anisotropic) noise of a device in its base frame instead of ``sigma_a`` /
        ``sigma_b``, which then hold its largest σ for the truth and for the effects that
        draw noise of their own (``noise_scale``, ``distance_noise``: isotropic at that σ).
    max_bytes : int, optional
        Refuse a recording whose estimated memory (``BYTES_PER_SAMPLE`` per sample) exceeds
        this; default ``memory_limit()`` (4 GiB or half the RAM).

    Returns
    -------
    SimRecording

    Raises
    ------
    ConfigError
        For a negative or non-integer seed, an unknown model or motion preset, a non-positive
        duration or rate, a negative sigma or a truth made for another model.
    InputError
        If the recording would need more memory than ``max_bytes`` (checked before
        allocating; the message gives the estimate).

    """
    seed = _check_seed(seed)
    _check_model(model)
    effects = tuple(effects)
    sigma_a = noise_a.largest_sigmas() if noise_a is not None else sigma_a
    sigma_b = noise_b.largest_sigmas() if noise_b is not None else sigma_b
    sigma_a = validate_sigma(sigma_a, 'sigma_a')
    sigma_b = validate_sigma(sigma_b, 'sigma_b')
    if not (np.isfinite(duration) and duration > 0.0):
        raise ConfigError(f'duration: expected a positive number of seconds, got {duration!r}')
    for name, rate in (('rate_a', rate_a), ('rate_b', rate_b)):
        if not (np.isfinite(rate) and 0.0 < rate <= 1e9):
            raise ConfigError(f'{name}: expected a rate in Hz in (0, 1e9], got {rate!r}')
    n_topics_b = 3 if model == 'three_marker' else 1
    check_allocation((rate_a + n_topics_b * rate_b) * duration,
                     f'a recording of {duration:g} s at {rate_a:g} Hz (A) and {rate_b:g} Hz (B)',
                     '--rate-a/--rate-b/--duration', max_bytes)
    seq_truth, seq_motion, seq_stamps, seq_a, seq_b, seq_effects = (
        np.random.SeedSequence(seed).spawn(6))
    truth = _resolve_truth(truth, model, np.random.default_rng(seq_truth), sigma_a, sigma_b)
    motion = _resolve_motion(motion, np.random.default_rng(seq_motion))
    topic_a = DEFAULT_TOPIC_A
    topics_b = DEFAULT_TOPICS_B_THREE_MARKER if model == 'three_marker' else DEFAULT_TOPIC_B
    topics_b = tuple(topics_b)

    rng_stamps = np.random.default_rng(seq_stamps)
    duration_ns = int(round(duration * 1e9))
    stamps_a = _stamps(rng_stamps, rate_a, duration_ns, start_ns)
    stamps_b = _stamps(rng_stamps, rate_b, duration_ns, start_ns)

    pos_a, q_a = motion.pose(_seconds(stamps_a, start_ns))
    pos_b, q_b = truth.device_b(*motion.pose(_seconds(stamps_b, start_ns)))
    true_streams = {topic_a: PoseStream(stamps_a.copy(), pos_a, q_a, FRAME_A)}
    true_streams.update(_streams_b(model, topics_b, stamps_b, pos_b, q_b))

    staged = {stage: [e for e in effects if effect_stage(e) == stage] for stage in STAGES}
    context = EffectContext(truth=truth, motion=motion, start_ns=int(start_ns), topic_a=topic_a,
                            topics_b=topics_b, true_streams=true_streams, sigma_a=sigma_a,
                            sigma_b=sigma_b)
    clean_streams, described = true_streams, ()
    if staged['clean']:
        # physics before the device noise: the noise is added to the changed poses
        clean_streams, described = apply_effects(true_streams, staged['clean'], context,
                                                 seq_effects)
        _check_same_stamps(clean_streams, true_streams, 'clean')
        pos_a, q_a = clean_streams[topic_a].position, clean_streams[topic_a].quat_wxyz
        pos_b = np.stack([clean_streams[t].position for t in topics_b], axis=1)
        if model == 'full_pose':
            q_b = clean_streams[topics_b[0]].quat_wxyz

    noisy_a = _device_noise(np.random.default_rng(seq_a), pos_a, q_a, noise_a or sigma_a)
    noisy_b = _device_noise(np.random.default_rng(seq_b), pos_b,
                            q_b if model == 'full_pose' else None, noise_b or sigma_b)
    streams = {topic_a: PoseStream(stamps_a, noisy_a[0], noisy_a[1], FRAME_A)}
    streams.update(_streams_b(model, topics_b, stamps_b, noisy_b[0],
                              q_b if noisy_b[1] is None else noisy_b[1]))

    later = staged['noise'] + staged['measured']
    if later:
        context = replace(context, clean_streams=clean_streams)
        streams, more = apply_effects(streams, staged['noise'], context, seq_effects)
        _check_same_stamps(streams, true_streams, 'noise')
        streams, rest = apply_effects(streams, staged['measured'], context, seq_effects)
        described = described + more + rest
    if effects:
        truth = replace(truth, effects=described)
    return SimRecording(streams=streams, truth=truth, topics_a=topic_a, topics_b=topics_b,
                        motion=motion, start_ns=int(start_ns), duration=float(duration),
                        seed=int(seed))


def simulate_pairs(rng: np.random.Generator, n: int, model: str = 'full_pose', *,
                   sigma_a=DEFAULT_SIGMA_A, sigma_b=DEFAULT_SIGMA_B,
                   truth: Optional[Truth] = None, motion: Union[str, Motion] = 'diverse',
                   duration: Optional[float] = None,
                   start_ns: int = DEFAULT_START_NS) -> tuple[Pairs, Pairs, Truth]:
    """
    Simultaneous pairs of A and B samples, for Monte Carlo checks of the estimator.

    A and B are sampled at the same instants (no interpolation), evenly spread over the motion,
    then perturbed by independent device noise. Draws from ``rng`` in the order truth (if
    None), motion (if a preset name), A's noise, B's noise.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws everything, in the order above.
    n : int
        Number of pairs (>= 1).
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    sigma_a, sigma_b : tuple of float
        Noise standard deviations (position m, rotation rad); zero means no noise on that
        device.
    truth : Truth, optional
        Calibration to simulate; drawn by ``random_truth`` when None.
    motion : str or Motion
        Preset name of ``make_motion`` or a ``Motion``.
    duration : float, optional
        Span of the sample times, s; default ``max(60, n / 100)`` so that the motion is
        diverse at any n (and at most 100 pairs per second).
    start_ns : int
        Stamp of the first pair, ns (also the motion's time origin).

    Returns
    -------
    noisy : Pairs
        ``stamps`` (n,) int64 ns; ``pos_a`` (n, 3) and ``quat_a`` (n, 4) in A's base frame;
        ``pos_b`` (n, 3), or (n, 3, 3) for ``three_marker`` (axis 1 the marker), in B's base
        frame; ``quat_b`` (n, 4) for ``full_pose``, else None.
    noiseless : Pairs
        The same without noise: the model equation holds exactly.
    truth : Truth

    """
    _check_model(model)
    sigma_a = validate_sigma(sigma_a, 'sigma_a')
    sigma_b = validate_sigma(sigma_b, 'sigma_b')
    n = int(n)
    if n < 1:
        raise ConfigError(f'n: expected at least one pair, got {n}')
    check_allocation(2.0 * n * (4 if model == 'three_marker' else 2), f'{n} simulated pairs',
                     'the number of pairs')
    if duration is None:
        duration = max(MIN_PAIRS_DURATION, n / 100.0)
    if not (np.isfinite(duration) and duration > 0.0):
        raise ConfigError(f'duration: expected a positive number of seconds, got {duration!r}')
    truth = _resolve_truth(truth, model, rng, sigma_a, sigma_b)
    motion = _resolve_motion(motion, rng)

    stamps = np.int64(start_ns) + np.round(np.arange(n) * (duration * 1e9 / n)).astype(np.int64)
    pos_a, q_a = motion.pose(_seconds(stamps, start_ns))
    pos_b, q_b = truth.device_b(pos_a, q_a)
    pos_b = pos_b if model == 'three_marker' else pos_b[:, 0]
    q_b = q_b if model == 'full_pose' else None

    noisy_pos_a, noisy_q_a = add_pose_noise(rng, pos_a, q_a, sigma_a)
    noisy_pos_b, noisy_q_b = add_pose_noise(rng, pos_b, q_b, sigma_b)
    noisy = Pairs(stamps=stamps, pos_a=noisy_pos_a, quat_a=noisy_q_a, pos_b=noisy_pos_b,
                  quat_b=noisy_q_b)
    noiseless = Pairs(stamps=stamps.copy(), pos_a=pos_a, quat_a=q_a, pos_b=pos_b, quat_b=q_b)
    return noisy, noiseless, truth
