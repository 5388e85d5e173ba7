"""
Smooth 6-DOF motion of device A's tool in A's base frame, as a continuous function of time.

A motion is a sum of sinusoids: the position is ``centre + Σ_k a_k sin(2π f_k t + φ_k)`` per
axis, the orientation ``q_mean ⊗ Exp(r(t))`` with the rotation vector r(t) (rad, in the tool
frame of ``q_mean``) a sum of sinusoids per axis. Being analytic, it can be evaluated at any
device's own stamps (exact continuous time), so the simulated devices need no interpolation.

The frequencies are kept low (position 0.05-0.3 Hz, rotation 0.03-0.2 Hz): linear
interpolation between 100 Hz samples then errs by under 10 µm and 0.02 mrad, far below
the default device noise (``coreg_ros.core.settings``: 0.2-0.5 mm, 0.5-2 mrad).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
import numpy as np

#: Names of the motion presets of ``make_motion``: free motion, the motions of rigs that cannot
#: move in every direction (a SCARA arm, a mobile robot on a floor, a Cartesian gantry, a
#: turntable), and the degenerate ones.
MOTION_PRESETS = ('diverse', 'scara', 'planar', 'gantry', 'turntable', 'single_axis',
                  'no_rotation', 'static')
#: Presets whose motion leaves part of the calibration unobservable (what they can show).
RESTRICTED_PRESETS = ('scara', 'planar', 'gantry', 'turntable', 'single_axis', 'no_rotation')

#: Range of the per-axis position amplitude (sum of the sinusoids' amplitudes), m.
POSITION_AMPLITUDE = (0.10, 0.15)
#: Range of the position frequencies, Hz.
POSITION_FREQUENCY = (0.05, 0.3)
#: Range of the per-axis rotation-vector amplitude (sum of the sinusoids' amplitudes), rad.
ROTATION_AMPLITUDE = (0.6, 0.9)
#: Range of the rotation frequencies, Hz.
ROTATION_FREQUENCY = (0.03, 0.2)


def _frozen(a, shape: tuple) -> np.ndarray:
    a = np.array(a, dtype=float)
    if a.shape != shape:
        raise ConfigError(f'motion: expected an array of shape {shape}, got {a.shape}')
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Motion:
    """
    Pose of A's tool frame in A's base frame, a smooth function of time.

    Each of the six channels j is ``Σ_k amp[j, k] sin(2π freq[j, k] t + phase[j, k])``, t in
    seconds from the motion's origin (the recording's ``start_ns``).

    Attributes
    ----------
    centre : ndarray, shape (3,)
        Mean position of the tool in A's base frame, m.
    pos_amp, pos_freq, pos_phase : ndarray, shape (3, K)
        Position sinusoids per axis of A's base frame: amplitude m, frequency Hz, phase rad.
    q_mean : ndarray, shape (4,)
        Mean orientation of the tool in A's base frame, (w, x, y, z).
    rot_amp, rot_freq, rot_phase : ndarray, shape (3, K)
        Rotation-vector sinusoids per axis of the tool frame at ``q_mean``: amplitude rad,
        frequency Hz, phase rad.
    preset : str
        Name of the preset that made it, or ``'custom'``.
    pivot : ndarray, shape (3,), optional
        A point of A's base frame the tool turns about (a turntable): the tool's rotation
        relative to ``q_mean`` also carries ``centre`` about ``pivot``; the position sinusoids
        add to that. None: positions are the sinusoids alone.

    """

    centre: np.ndarray
    pos_amp: np.ndarray
    pos_freq: np.ndarray
    pos_phase: np.ndarray
    q_mean: np.ndarray
    rot_amp: np.ndarray
    rot_freq: np.ndarray
    rot_phase: np.ndarray
    preset: str = 'custom'
    pivot: Optional[np.ndarray] = None

    def __post_init__(self):
        kp = np.shape(self.pos_amp)[-1] if np.ndim(self.pos_amp) == 2 else -1
        kr = np.shape(self.rot_amp)[-1] if np.ndim(self.rot_amp) == 2 else -1
        object.__setattr__(self, 'centre', _frozen(self.centre, (3,)))
        for name, k in (('pos_amp', kp), ('pos_freq', kp), ('pos_phase', kp),
                        ('rot_amp', kr), ('rot_freq', kr), ('rot_phase', kr)):
            object.__setattr__(self, name, _frozen(getattr(self, name), (3, k)))
        q = quat.canonical(_frozen(self.q_mean, (4,)))
        q = q / np.linalg.norm(q)
        q.setflags(write=False)
        object.__setattr__(self, 'q_mean', q)
        if self.pivot is not None:
            object.__setattr__(self, 'pivot', _frozen(self.pivot, (3,)))

    @staticmethod
    def _sines(t: np.ndarray, amp: np.ndarray, freq: np.ndarray, phase: np.ndarray) -> np.ndarray:
        """Sum of sinusoids per channel at times t (N,): shape (N, 3)."""
        arg = 2.0 * np.pi * t[:, None, None] * freq + phase
        return np.sum(amp * np.sin(arg), axis=-1)

    def rotvec(self, t_seconds) -> np.ndarray:
        """
        Rotation vector r(t) of the tool relative to ``q_mean``, shape (N, 3), rad.

        Expressed in the tool frame at ``q_mean``: ``q(t) = q_mean ⊗ Exp(r(t))``.
        """
        t = np.atleast_1d(np.asarray(t_seconds, dtype=float))
        return self._sines(t, self.rot_amp, self.rot_freq, self.rot_phase)

    def pose(self, t_seconds) -> tuple[np.ndarray, np.ndarray]:
        """
        Pose of A's tool frame in A's base frame at the given times.

        Parameters
        ----------
        t_seconds : array_like, shape (N,)
            Times in seconds from the motion's origin.

        Returns
        -------
        position : ndarray, shape (N, 3)
            Tool position in A's base frame, m.
        quat_wxyz : ndarray, shape (N, 4)
            Tool orientation in A's base frame, (w, x, y, z), canonical (w >= 0).

        """
        t = np.atleast_1d(np.asarray(t_seconds, dtype=float))
        position = self.centre + self._sines(t, self.pos_amp, self.pos_freq, self.pos_phase)
        q = quat.multiply(self.q_mean, quat.exp(self.rotvec(t)))
        if self.pivot is not None:
            # the tool's rotation relative to q_mean, in A's base frame, turns the lever from
            # the pivot to the centre
            turn = quat.to_matrix(quat.multiply(q, quat.conjugate(self.q_mean)))
            position += np.einsum('nij,j->ni', turn, self.centre - self.pivot) - (
                self.centre - self.pivot)
        return position, quat.canonical(q)

    def as_dict(self) -> dict:
        """JSON-friendly description (lists of floats)."""
        return {
            'preset': self.preset,
            'centre': self.centre.tolist(),
            'pos_amp': self.pos_amp.tolist(),
            'pos_freq': self.pos_freq.tolist(),
            'pos_phase': self.pos_phase.tolist(),
            'q_mean': self.q_mean.tolist(),
            'rot_amp': self.rot_amp.tolist(),
            'rot_freq': self.rot_freq.tolist(),
            'rot_phase': self.rot_phase.tolist(),
            'pivot': None if self.pivot is None else self.pivot.tolist(),
        }


def random_rotation(rng: np.random.Generator, size=None) -> np.ndarray:
    """
    Rotations drawn uniformly over all of SO(3) (Haar measure), including near 180°.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the rotations.
    size : int, optional
        Number of rotations; None for a single one.

    Returns
    -------
    q : ndarray, shape (4,) or (size, 4)
        Unit quaternions (w, x, y, z), canonical (w >= 0).

    """
    shape = (4,) if size is None else (int(size), 4)
    g = rng.standard_normal(shape)
    return quat.canonical(g / np.linalg.norm(g, axis=-1, keepdims=True))


def random_unit(rng: np.random.Generator) -> np.ndarray:
    """Return a direction drawn uniformly on the unit sphere, shape (3,)."""
    g = rng.standard_normal(3)
    return g / np.linalg.norm(g)


def _split_sines(rng: np.random.Generator, totals: np.ndarray, n_terms: int,
                 freq_range: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-axis sinusoids whose amplitudes sum to ``totals`` (3,): amp, freq, phase (3, K)."""
    weights = rng.dirichlet(np.full(n_terms, 2.0), size=3)
    freq = rng.uniform(*freq_range, size=(3, n_terms))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=(3, n_terms))
    return totals[:, None] * weights, freq, phase


def make_motion(rng: np.random.Generator, preset: str = 'diverse') -> Motion:
    """
    Draw a random smooth motion of A's tool from a preset.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness; the same generator state gives the same motion.
    preset : str
        - ``'diverse'``: position = centre + 2-3 sinusoids per axis (0.05-0.3 Hz, per-axis
          amplitude 0.10-0.15 m); orientation = ``q_mean ⊗ Exp(r(t))`` with 2-3 sinusoids per
          rotation axis (0.03-0.2 Hz, per-axis amplitude 0.6-0.9 rad), so the relative
          rotations span all three axes.
        - ``'scara'``: a SCARA arm: translation as ``'diverse'``, rotation about A's base z axis
          only (the tool's yaw); T1's offset along that axis is unobservable.
        - ``'planar'``: a mobile robot on a floor: yaw about A's base z axis and translation in
          A's base x and y only (z constant); as ``'scara'``, one direction is unobservable.
        - ``'gantry'``: a Cartesian gantry: translation as ``'diverse'``, constant orientation;
          T1's position is unobservable against T0's translation (three directions).
        - ``'turntable'``: the tool on a turntable: it turns about A's base z axis through a
          fixed point 0.2-0.4 m away, nothing else; T1's offset along the axis and the split
          of the rotation about it between T0 and T1 are unobservable.
        - ``'single_axis'``: translation as ``'diverse'``; rotation about one fixed random axis
          only (r(t) = u s(t)), which leaves part of the hand-eye problem unobservable.
        - ``'no_rotation'``: translation as ``'diverse'``, constant orientation ``q_mean``.
        - ``'static'``: no motion at all (pose constant at ``centre``, ``q_mean``).

    Returns
    -------
    Motion

    Raises
    ------
    ConfigError
        If the preset is unknown.

    """
    if preset not in MOTION_PRESETS:
        raise ConfigError(f'motion: unknown preset {preset!r}; use one of {MOTION_PRESETS}')
    # Every preset consumes the same draws in the same order (the presets differ only in what
    # they keep), so a preset's motion shares its centre and q_mean with the others' for a seed.
    centre = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(0.2, 0.5)])
    q_mean = random_rotation(rng)
    n_pos, n_rot = (int(k) for k in rng.integers(2, 4, size=2))
    pos = _split_sines(rng, rng.uniform(*POSITION_AMPLITUDE, size=3), n_pos, POSITION_FREQUENCY)
    rot = _split_sines(rng, rng.uniform(*ROTATION_AMPLITUDE, size=3), n_rot, ROTATION_FREQUENCY)
    axis = random_unit(rng)
    single_total = rng.uniform(*ROTATION_AMPLITUDE) * np.sqrt(3.0)
    pos_amp, pos_freq, pos_phase = pos
    rot_amp, rot_freq, rot_phase = rot
    pivot = None
    if preset in ('scara', 'planar', 'turntable'):
        # about A's base z axis: in the tool frame of q_mean that is R(q_mean)ᵀ e_z
        axis = quat.to_matrix(q_mean).T @ np.array([0.0, 0.0, 1.0])
        preset_axis = 'single_axis'
    else:
        preset_axis = preset
    if preset_axis == 'single_axis':
        # r(t) = axis · s(t), s a sum of sinusoids: the same (freq, phase) on every axis.
        rot_amp = axis[:, None] * (single_total * rot_amp[0] / np.sum(rot_amp[0]))
        rot_freq = np.broadcast_to(rot_freq[0], (3, n_rot))
        rot_phase = np.broadcast_to(rot_phase[0], (3, n_rot))
    if preset in ('no_rotation', 'gantry', 'static'):
        rot_amp = np.zeros_like(rot_amp)
    if preset == 'planar':
        pos_amp = pos_amp * np.array([1.0, 1.0, 0.0])[:, None]
    if preset in ('static', 'turntable'):
        pos_amp = np.zeros_like(pos_amp)
    if preset == 'turntable':
        # the pivot drawn after every shared draw, so the other presets keep their motion
        radius, angle = rng.uniform(0.2, 0.4), rng.uniform(0.0, 2.0 * np.pi)
        pivot = centre - radius * np.array([np.cos(angle), np.sin(angle), 0.0])
    return Motion(centre=centre, pos_amp=pos_amp, pos_freq=pos_freq, pos_phase=pos_phase,
                  q_mean=q_mean, rot_amp=rot_amp, rot_freq=rot_freq, rot_phase=rot_phase,
                  preset=preset, pivot=pivot)
