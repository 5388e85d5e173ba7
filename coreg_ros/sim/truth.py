"""
The true calibration of a simulation and the measurement model that maps A's poses to B's.

Model (Ikits eq. 16): ``T_bbase_bmarker(t) = T0 · T_abase_atool(t) · T1`` with
``T0 = T_bbase_abase`` (pose of A's base in B's base: p0, q0) and ``T1 = T_atool_bmarker``
(pose of B's marker in A's tool frame: p1, q1). Position ``p_B = p0 + R0 (p_A + R_A p1)``,
orientation ``q_B = q0 ⊗ q_A ⊗ q1``. For three markers (eq. 19) each marker j at p_j in A's
tool frame is seen at ``p_Bj = p0 + R0 (p_A + R_A p_j)``.
"""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import ConfigError
from coreg_ros.core.types import MODELS
from coreg_ros.sim.motion import random_rotation, random_unit
import numpy as np

#: Range of the length of the tool-to-marker offset p1, m.
MARKER_OFFSET = (0.05, 0.20)
#: Range of the distance between any two of the three markers, m.
MARKER_SPACING = (0.05, 0.15)
#: Smallest interior angle of the three-marker triangle, rad (keeps it far from collinear).
MIN_MARKER_ANGLE = np.deg2rad(30.0)
#: Half-width of the box p0 is drawn from, m.
BASE_BOX = 1.0


def validate_sigma(value, name: str = 'sigma') -> tuple:
    """
    Check a device noise pair and return it as ``(position m, rotation rad)`` floats.

    Raises ``ConfigError`` unless it has two finite, non-negative entries.
    """
    s = tuple(float(v) for v in np.asarray(value, dtype=float).reshape(-1))
    if len(s) != 2 or not all(np.isfinite(v) and v >= 0.0 for v in s):
        raise ConfigError(f'{name}: expected (position m, rotation rad), both >= 0, got {value!r}')
    return s


def _pose_dict(position: np.ndarray, q: np.ndarray) -> dict:
    w, x, y, z = (float(v) for v in q)
    return {'position': [float(v) for v in position],
            'orientation': {'w': w, 'x': x, 'y': y, 'z': z}}


def _pose_from_dict(d: dict) -> tuple[np.ndarray, np.ndarray]:
    o = d['orientation']
    return np.asarray(d['position'], dtype=float), np.array([o['w'], o['x'], o['y'], o['z']])


@dataclass(frozen=True, eq=False)
class Truth:
    """
    The true parameters of a simulated recording.

    Attributes
    ----------
    p0 : ndarray, shape (3,)
        Position of A's base frame in B's base frame (T0 = T_bbase_abase), m.
    q0 : ndarray, shape (4,)
        Orientation of A's base frame in B's base frame, (w, x, y, z), w >= 0.
    p1 : ndarray, shape (3,)
        Position of B's marker (marker 1) in A's tool frame (T1 = T_atool_bmarker), m.
    q1 : ndarray, shape (4,)
        Orientation of B's marker frame in A's tool frame, (w, x, y, z), w >= 0. Only
        observable with ``full_pose``; drawn for every model all the same.
    markers : ndarray, shape (k, 3)
        Marker positions in A's tool frame, m: ``[p1]`` (k = 1), or p1, p2, p3 for
        ``three_marker`` (k = 3).
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    sigma_a, sigma_b : tuple of float
        Noise standard deviations (position m, rotation rad) of devices A and B.
    effects : tuple of dict
        Descriptions of the unmodelled effects applied to the recording (empty: none).

    """

    p0: np.ndarray
    q0: np.ndarray
    p1: np.ndarray
    q1: np.ndarray
    markers: np.ndarray
    model: str = 'full_pose'
    sigma_a: tuple = (0.0, 0.0)
    sigma_b: tuple = (0.0, 0.0)
    effects: tuple = ()

    def __post_init__(self):
        if self.model not in MODELS:
            raise ConfigError(f'model: unknown model {self.model!r}; use one of {MODELS}')
        k = 3 if self.model == 'three_marker' else 1
        arrays = {'p0': (3,), 'q0': (4,), 'p1': (3,), 'q1': (4,), 'markers': (k, 3)}
        for name, shape in arrays.items():
            a = np.array(getattr(self, name), dtype=float)
            if a.shape != shape or not np.isfinite(a).all():
                raise ConfigError(f'truth.{name}: expected finite values of shape {shape} for '
                                  f'model {self.model!r}, got shape {a.shape}')
            if name in ('q0', 'q1'):
                a = quat.validate_quaternions(a, f'truth.{name}')
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        if not np.allclose(self.markers[0], self.p1, rtol=0.0, atol=1e-12):
            raise ConfigError('truth.markers: the first marker must be p1')
        object.__setattr__(self, 'sigma_a', validate_sigma(self.sigma_a, 'sigma_a'))
        object.__setattr__(self, 'sigma_b', validate_sigma(self.sigma_b, 'sigma_b'))
        object.__setattr__(self, 'effects', tuple(self.effects))

    def as_dict(self) -> dict:
        """
        JSON-friendly form.

        Keys: ``base_to_base`` and ``tool_to_marker`` (each ``{'position': [x, y, z],
        'orientation': {'w', 'x', 'y', 'z'}}``), ``markers`` (list of [x, y, z]), ``model``,
        ``sigma_a``, ``sigma_b`` (lists [position m, rotation rad]), ``effects`` (list of dict).

        """
        return {
            'base_to_base': _pose_dict(self.p0, self.q0),
            'tool_to_marker': _pose_dict(self.p1, self.q1),
            'markers': self.markers.tolist(),
            'model': self.model,
            'sigma_a': list(self.sigma_a),
            'sigma_b': list(self.sigma_b),
            'effects': [dict(e) for e in self.effects],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Truth:
        """Inverse of ``as_dict``."""
        p0, q0 = _pose_from_dict(d['base_to_base'])
        p1, q1 = _pose_from_dict(d['tool_to_marker'])
        return cls(p0=p0, q0=q0, p1=p1, q1=q1, markers=np.asarray(d['markers'], dtype=float),
                   model=d['model'], sigma_a=tuple(d['sigma_a']), sigma_b=tuple(d['sigma_b']),
                   effects=tuple(d.get('effects', ())))

    def device_b(self, position_a, quat_a) -> tuple[np.ndarray, np.ndarray]:
        """
        Noise-free poses of B's marker(s) in B's base frame from A's tool poses (Ikits eq. 16).

        Parameters
        ----------
        position_a : array_like, shape (N, 3)
            Tool position in A's base frame, m.
        quat_a : array_like, shape (N, 4)
            Tool orientation in A's base frame, (w, x, y, z).

        Returns
        -------
        position_b : ndarray, shape (N, k, 3)
            ``p_Bj = p0 + R0 (p_A + R_A p_j)`` for each marker j, in B's base frame, m.
        quat_b : ndarray, shape (N, 4)
            ``q_B = q0 ⊗ q_A ⊗ q1``, canonical (w >= 0): the marker frame's orientation in B's
            base frame (meaningful for ``full_pose`` only).

        """
        position_a = np.asarray(position_a, dtype=float)
        quat_a = np.asarray(quat_a, dtype=float)
        r0 = quat.to_matrix(self.q0)
        ra = quat.to_matrix(quat_a)
        in_a = position_a[:, None, :] + np.einsum('nij,kj->nki', ra, self.markers)
        position_b = self.p0 + np.einsum('ij,nkj->nki', r0, in_a)
        quat_b = quat.canonical(quat.multiply(quat.multiply(self.q0, quat_a), self.q1))
        return position_b, quat_b


def _min_angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    """Smallest interior angle (rad) of the triangle abc."""
    angles = []
    for p, q, r in ((a, b, c), (b, c, a), (c, a, b)):
        u, v = q - p, r - p
        cos = np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v))
        angles.append(np.arccos(np.clip(cos, -1.0, 1.0)))
    return float(min(angles))


def random_truth(rng: np.random.Generator, model: str = 'full_pose', *,
                 sigma_a=(0.0, 0.0), sigma_b=(0.0, 0.0)) -> Truth:
    """
    Draw a random true calibration.

    q0 and q1 are uniform over all of SO(3) (near-180° rotations included); p0 is uniform in
    the box ±1 m; p1 has a length uniform in 5-20 cm and a uniformly random direction. For
    ``three_marker``, p2 and p3 are drawn so that every two markers are 5-15 cm apart and every
    interior angle of the triangle p1 p2 p3 is at least 30° (far from collinear).

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    model : str
        ``full_pose``, ``position_only`` or ``three_marker``.
    sigma_a, sigma_b : tuple of float
        Noise standard deviations (position m, rotation rad) recorded in the truth.

    Returns
    -------
    Truth

    """
    if model not in MODELS:
        raise ConfigError(f'model: unknown model {model!r}; use one of {MODELS}')
    q0 = random_rotation(rng)
    q1 = random_rotation(rng)
    p0 = rng.uniform(-BASE_BOX, BASE_BOX, size=3)
    p1 = rng.uniform(*MARKER_OFFSET) * random_unit(rng)
    markers = p1[None, :]
    if model == 'three_marker':
        while True:
            p2 = p1 + rng.uniform(*MARKER_SPACING) * random_unit(rng)
            p3 = p1 + rng.uniform(*MARKER_SPACING) * random_unit(rng)
            d23 = np.linalg.norm(p3 - p2)
            if (MARKER_SPACING[0] <= d23 <= MARKER_SPACING[1]
                    and _min_angle(p1, p2, p3) >= MIN_MARKER_ANGLE):
                break
        markers = np.stack([p1, p2, p3])
    return Truth(p0=p0, q0=q0, p1=p1, q1=q1, markers=markers, model=model, sigma_a=sigma_a,
                 sigma_b=sigma_b)
