"""
A device's noise drawn from full covariances (``DeviceNoise``) onto true poses.

The one home of the draw shared by ``sim.devices`` (recordings with ``noise_a``/``noise_b``),
``sim.still`` (still recordings) and ``sim.noise_trials`` (pairs for ``--noise auto``).
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.noise_model import DeviceNoise
import numpy as np


def add_device_noise(rng: np.random.Generator, position: np.ndarray,
                     quat_wxyz: Optional[np.ndarray], noise: DeviceNoise,
                     scale: Optional[np.ndarray] = None) -> tuple:
    """
    Add Gaussian noise of full covariances (in the base frame) to poses.

    Parameters
    ----------
    rng : numpy.random.Generator
        Draws the noise.
    position : ndarray, shape (N, 3) or (N, k, 3)
        True positions, m (every marker its own noise).
    quat_wxyz : ndarray, shape (N, 4) or None
        True orientations; ``Exp(δθ) ⊗ q`` with ``δθ ~ N(0, Σ_rot)``.
    noise : DeviceNoise
        The covariances (position m², rotation rad², base frame).
    scale : ndarray, shape (N,), optional
        Factor on each sample's standard deviations (noise growing with distance).

    Returns
    -------
    (position, quat_wxyz)

    """
    position = np.array(position, dtype=float)
    s = np.ones(len(position)) if scale is None else np.asarray(scale, dtype=float)
    Lp = np.linalg.cholesky(noise.position_cov)
    dp = rng.standard_normal(position.shape) @ Lp.T
    position = position + dp * s.reshape((-1,) + (1,) * (position.ndim - 1))
    if quat_wxyz is not None:
        Lr = np.linalg.cholesky(noise.rotation_cov)
        dth = rng.standard_normal((len(quat_wxyz), 3)) @ Lr.T * s[:, None]
        quat_wxyz = quat.canonical(quat.multiply(quat.exp(dth), quat_wxyz))
    return position, quat_wxyz
