"""
The rigid part of a displacement field: what a rigid registration absorbs of it.

Shared by the simulator (a field distortion is sized by its non-rigid part) and the
diagnosis (a fitted field is reported by its non-rigid part; the dipole search regresses on
what the calibration absorbs anyway).
"""

from coreg_ros.core.so3 import skew
import numpy as np


def rigid_columns(q: np.ndarray) -> np.ndarray:
    """
    Columns of a small rigid motion at points q: ``A (t, ω) = t + ω × q``.

    Parameters
    ----------
    q : ndarray, shape (N, 3)
        Points, relative to the centre of the turn.

    Returns
    -------
    ndarray, shape (N, 3, 6)
        ``[I | -[q]×]`` per point (ω × q = -q × ω).

    """
    A = np.zeros((len(q), 3, 6))
    A[:, :, 0:3] = np.eye(3)
    A[:, :, 3:6] = skew(-q)
    return A


def rigid_part(points: np.ndarray, d: np.ndarray) -> np.ndarray:
    """
    Return the part of a displacement field a rigid registration absorbs, ``t + ω × p``.

    Least squares over the points, first order in ω (the fields are millimetres on metres).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Where the field is sampled, m.
    d : ndarray, shape (N, 3)
        The displacement at each point, m.

    Returns
    -------
    ndarray, shape (N, 3)

    """
    q = points - points.mean(axis=0)
    n = len(points)
    A = rigid_columns(q).reshape(3 * n, 6)
    x, *_ = np.linalg.lstsq(A, d.reshape(-1), rcond=None)
    return (A @ x).reshape(n, 3)
