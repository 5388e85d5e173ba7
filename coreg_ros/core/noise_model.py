"""
A device's noise: 3×3 position and rotation covariances in the device's own base frame.

The estimator's noise (``estimator.problem``) is a 6×6 covariance in the ROS layout: position
(m²) and the rotation vector δθ (rad²) with ``R_measured = Exp(δθ) · R_true``, both about the
fixed axes of the device's base frame (A's for device A, B's for device B; Ikits' input
perturbation and output error are taken there, ``models.linearize``). ``DeviceNoise`` holds the
two 3×3 blocks (no position-rotation cross term: no tracker reports one and none is measured),
so that a tracker noisier in depth than laterally is stated as it is. The isotropic
``(position m, rotation rad)`` pair of ``Settings.sigma_a`` is the special case
``DeviceNoise.isotropic``.

``noise_covariance`` is the one conversion of every form a noise is given in (a σ pair, a
``DeviceNoise``, a 6×6 array) to the 6×6 covariance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union

from coreg_ros.core.errors import ConfigError
import numpy as np

#: Channels of a device's noise, in the order of the ROS layout.
CHANNELS = ('position', 'rotation')
#: Units of the channels' standard deviations.
UNITS = {'position': 'm', 'rotation': 'rad'}
#: Largest noise σ taken as meant (position m, rotation rad): beyond it the numbers are in
#: other units (mm, degrees), as no tracker that could be coregistered is that noisy.
MAX_SIGMA = {'position': 1.0, 'rotation': 0.5}
#: Smallest eigenvalue of a covariance, relative to its largest, taken as positive definite
#: (below it the matrix is singular to rounding: a σ of 1e-6 of the largest).
MIN_EIGEN_SHARE = 1e-12


def _matrix(value, what: str) -> np.ndarray:
    """Return a 3×3 covariance from a 3×3 array, 3 per-axis σ (diagonal) or one σ (isotropic)."""
    a = np.asarray(value, dtype=float)
    if a.shape == ():
        a = np.full(3, float(a))
    if a.shape == (3,):
        if not np.all(np.isfinite(a)) or not np.all(a > 0):
            raise ConfigError(f'{what}: standard deviations must be positive numbers, got '
                              f'{a.tolist()}')
        return np.diag(a ** 2)
    if a.shape != (3, 3):
        raise ConfigError(f'{what} must be a 3×3 covariance, 3 standard deviations or one, got '
                          f'shape {a.shape}')
    return a


def checked_covariance(value, what: str, channel: str) -> np.ndarray:
    """
    Return a 3×3 covariance after checking it is one: finite, symmetric, positive definite.

    Parameters
    ----------
    value : array_like
        A 3×3 covariance, three per-axis standard deviations or one standard deviation.
    what : str
        How to name it in a refusal (``"device A position"``).
    channel : {'position', 'rotation'}
        Sets the unit check (``MAX_SIGMA``).

    Raises
    ------
    ConfigError
        One line naming the problem and the fix.

    """
    a = _matrix(value, what)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f'{what} covariance holds a non-finite number; give finite m²/rad²')
    scale = max(float(np.max(np.abs(a))), 1e-300)
    if np.max(np.abs(a - a.T)) > 1e-9 * scale:
        raise ConfigError(f'{what} covariance is not symmetric; a covariance equals its '
                          f'transpose')
    a = 0.5 * (a + a.T)
    lam = np.linalg.eigvalsh(a)
    if not lam[0] > MIN_EIGEN_SHARE * max(lam[-1], 0.0) or not lam[-1] > 0:
        raise ConfigError(f'{what} covariance is not positive definite (eigenvalues '
                          f'{", ".join(f"{v:.3g}" for v in lam)}): every direction needs a '
                          f'positive variance (a σ of zero says the device is exact)')
    top = float(np.sqrt(lam[-1]))
    if top > MAX_SIGMA[channel]:
        unit = UNITS[channel]
        raise ConfigError(f'{what} σ up to {top:g} {unit} is no tracker noise (above '
                          f'{MAX_SIGMA[channel]:g} {unit}); give {unit}'
                          + ('², not mm²' if channel == 'position' else '², not degrees²'))
    return a


@dataclass(frozen=True)
class DeviceNoise:
    """
    A device's noise: position and rotation covariances in its base frame.

    Attributes
    ----------
    position : tuple of tuple of float, 3×3
        Position covariance, m², about the device's base axes.
    rotation : tuple of tuple of float, 3×3
        Rotation-vector covariance, rad², about the device's base axes (``R_measured =
        Exp(δθ) · R_true``).

    Notes
    -----
    Stored as nested tuples so that ``Settings`` (which holds two) stays hashable; the arrays
    are ``position_cov`` and ``rotation_cov``.

    """

    position: tuple
    rotation: tuple

    @classmethod
    def from_covariances(cls, position, rotation, device: str = '') -> DeviceNoise:
        """Build from two 3×3 covariances (or σ, see ``checked_covariance``), checked."""
        name = f'device {device} ' if device else ''
        pos = checked_covariance(position, f'{name}position', 'position')
        rot = checked_covariance(rotation, f'{name}rotation', 'rotation')
        return cls(_tuple(pos), _tuple(rot))

    @classmethod
    def isotropic(cls, sigma) -> DeviceNoise:
        """Return the noise of a ``(position m, rotation rad)`` pair of standard deviations."""
        pos, rot = float(sigma[0]), float(sigma[1])
        return cls(_tuple(np.eye(3) * pos ** 2), _tuple(np.eye(3) * rot ** 2))

    @property
    def position_cov(self) -> np.ndarray:
        """Position covariance (3, 3), m²."""
        return np.array(self.position, dtype=float)

    @property
    def rotation_cov(self) -> np.ndarray:
        """Rotation covariance (3, 3), rad²."""
        return np.array(self.rotation, dtype=float)

    def channel(self, name: str) -> np.ndarray:
        """Return the 3×3 covariance of ``'position'`` or ``'rotation'``."""
        return self.position_cov if name == 'position' else self.rotation_cov

    def covariance(self) -> np.ndarray:
        """Return the 6×6 covariance in the ROS layout (position m², rotation rad²)."""
        out = np.zeros((6, 6))
        out[0:3, 0:3] = self.position_cov
        out[3:6, 3:6] = self.rotation_cov
        return out

    def principal(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """
        Principal standard deviations and axes of a channel, largest first.

        Returns
        -------
        sigma : ndarray, shape (3,)
            m or rad.
        axes : ndarray, shape (3, 3)
            Unit axes as rows, in the device's base frame (each with its largest component
            positive, so that the axes of two estimates compare).

        """
        return principal_axes(self.channel(name))

    def largest_sigmas(self) -> tuple[float, float]:
        """Return the largest principal σ of position (m) and rotation (rad)."""
        return (float(self.principal('position')[0][0]),
                float(self.principal('rotation')[0][0]))

    def scaled(self, position: float = 1.0, rotation: float = 1.0) -> DeviceNoise:
        """Return the same shapes, the variances multiplied by ``position`` and ``rotation``."""
        return DeviceNoise(_tuple(self.position_cov * position),
                           _tuple(self.rotation_cov * rotation))


def principal_axes(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Principal standard deviations (largest first) and unit axes (rows) of a 3×3 covariance.

    Each axis is signed so that its largest component is positive.
    """
    lam, vec = np.linalg.eigh(0.5 * (cov + np.asarray(cov).T))
    order = np.argsort(lam)[::-1]
    lam, axes = lam[order], vec[:, order].T
    signs = np.sign(axes[np.arange(3), np.argmax(np.abs(axes), axis=1)])
    return np.sqrt(np.maximum(lam, 0.0)), axes * signs[:, None]


def _tuple(a: np.ndarray) -> tuple:
    a = np.asarray(a, dtype=float)
    return tuple(tuple(float(v) for v in row) for row in 0.5 * (a + a.T))


NoiseLike = Union[tuple, list, np.ndarray, DeviceNoise]


def noise_covariance(noise: NoiseLike) -> np.ndarray:
    """
    6×6 covariance (ROS layout) of a device's noise, however it is given.

    Parameters
    ----------
    noise : (float, float), DeviceNoise or array_like (6, 6)
        Isotropic standard deviations (position m, rotation rad), a ``DeviceNoise``, or the
        covariance itself (returned as it is).

    """
    if isinstance(noise, DeviceNoise):
        return noise.covariance()
    s = np.asarray(noise, dtype=float)
    if s.shape == (6, 6):
        return s
    if s.shape != (2,):
        raise ValueError(f'a noise must be (position m, rotation rad), a DeviceNoise or a 6×6 '
                         f'covariance, got shape {s.shape}')
    pos, rot = float(s[0]), float(s[1])
    return np.diag([pos ** 2] * 3 + [rot ** 2] * 3)


def largest_sigmas(noise: NoiseLike) -> tuple[float, float]:
    """Return the largest position (m) and rotation (rad) σ of a noise given in any form."""
    if not isinstance(noise, DeviceNoise) and np.shape(noise) == (2,):
        return float(noise[0]), float(noise[1])
    cov = noise_covariance(noise)
    return (float(np.sqrt(np.max(np.linalg.eigvalsh(cov[0:3, 0:3])))),
            float(np.sqrt(np.max(np.linalg.eigvalsh(cov[3:6, 3:6])))))
