"""
Unknown covariance components (negative diagonal, ``covariance.UNKNOWN``): infinite variance.

Every output that depends on an unknown input is marked unknown too; fusion gives it zero
information.
"""

from __future__ import annotations

from collections.abc import Sequence

from coreg_ros.core.errors import InputError
from coreg_ros.core.estimator.posterior import UNKNOWN
from coreg_ros.core.types import UncertainPose
import numpy as np

#: Below this absolute value a Jacobian entry does not propagate an unknown component.
_ZERO = 1e-12


def _unknown_mask(cov: np.ndarray) -> np.ndarray:
    """Components (..., n) whose diagonal is negative (not known)."""
    return np.diagonal(cov, axis1=-2, axis2=-1) < 0.0


def _known_part(cov: np.ndarray) -> np.ndarray:
    """Covariance with unknown rows/columns zeroed (their variance excluded from products)."""
    cov = np.array(cov, dtype=float)
    unk = _unknown_mask(cov)
    if unk.any():
        cov = np.where(unk[..., :, None] | unk[..., None, :], 0.0, cov)
    return cov


def _mark_unknown(cov: np.ndarray, jacobians: Sequence[np.ndarray],
                  unknowns: Sequence[np.ndarray]) -> np.ndarray:
    """Mark outputs depending on an unknown input: rows/cols 0, diagonal UNKNOWN."""
    out_unk = np.zeros(cov.shape[:-1], dtype=bool)
    for J, unk in zip(jacobians, unknowns, strict=True):
        if unk.any():
            touches = (np.abs(J) > _ZERO) & unk[..., None, :]
            out_unk |= touches.any(axis=-1)
    if out_unk.any():
        cov = np.where(out_unk[..., :, None] | out_unk[..., None, :], 0.0, cov)
        idx = np.arange(cov.shape[-1])
        cov[..., idx, idx] = np.where(out_unk, UNKNOWN, cov[..., idx, idx])
    return cov


def _symmetric(c: np.ndarray) -> np.ndarray:
    return 0.5 * (c + np.swapaxes(c, -1, -2))


def _cov_or_zero(pose: UncertainPose) -> np.ndarray:
    if pose.covariance is None:
        return np.zeros((6, 6))
    cov = np.asarray(pose.covariance, dtype=float)
    if cov.size != 36:
        raise InputError(f'a pose covariance must have 36 entries (6×6), got shape {cov.shape}')
    return cov.reshape(6, 6)
