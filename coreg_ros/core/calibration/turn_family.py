"""
The calibrations a turntable cannot tell apart: the whole A side turned about the tool's axis.

When A's tool turns about one fixed line of A's base frame (a turntable: ``T_Ai = G(θ_i)
T_ref`` with G a rotation about that line), every ``G(φ)`` commutes with the motion, so

    T0' = T0 G(φ),    T1' = H(φ)⁻¹ T1,    H(φ) = T_ref⁻¹ G(φ) T_ref

predict the same measurements for every φ: a closed curve of calibrations (a circle of the
lever's radius in T1's position), along which the data say nothing. A linear step cannot
travel it: a prior that fixes the turn (T1's position measured) lies anywhere on the circle
from the closed-form start, and Gauss-Newton steps along the tangent leave the circle by
s²/2r, so the fit would crawl (about √(2 σ r) per step). ``turned`` gives the member of the
curve at an angle (``turn_angles``: the set tried), from which the fit starts at the one the
prior prefers.
"""

from __future__ import annotations

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.initialize import principal_axis, turns_about_one_axis
from coreg_ros.core.models import Parameters
from coreg_ros.core.so3 import skew
import numpy as np

#: Angles tried round the turn (10°: a prior 5° off the start still pulls the fit there).
TURN_ANGLES = 36


def turn_axis(pos_a: np.ndarray, quat_a: np.ndarray) -> tuple | None:
    """
    Return the line A's tool turns about: (axis a, a point c on it, T_ref), or None.

    Parameters
    ----------
    pos_a : ndarray, shape (N, 3)
        A's tool positions, m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientations (w, x, y, z).

    Returns
    -------
    tuple or None
        ``(a, c, (p_ref, R_ref))`` in A's base frame; None when the tool does not turn about
        one axis (``initialize.turns_about_one_axis``).

    """
    Ra = quat.to_matrix(quat_a)
    if not turns_about_one_axis(Ra):
        return None
    a, _ = principal_axis(Ra)
    rot = Ra @ Ra[0].T
    # p_Ai = c + R_i (p_ref - c): (I - R_i) c = p_Ai - R_i p_ref (c along a is free)
    lhs = (np.eye(3) - rot).reshape(-1, 3)
    rhs = (pos_a - np.einsum('nij,j->ni', rot, pos_a[0])).reshape(-1)
    c = np.linalg.lstsq(lhs, rhs, rcond=1e-9)[0]
    return a, c, (pos_a[0].copy(), Ra[0])


def turn_angles(angles: int = TURN_ANGLES) -> np.ndarray:
    """Return ``angles`` evenly spread turns, rad, shape (angles,); the first is 0."""
    return np.linspace(0.0, 2.0 * np.pi, angles, endpoint=False)


def turned(params: Parameters, axis: tuple, phi: float) -> Parameters:
    """
    Return ``params`` turned about A's tool axis by ``phi``.

    Parameters
    ----------
    params : Parameters
        A calibration (the closed-form start).
    axis : tuple
        ``turn_axis``'s answer.
    phi : float
        The turn, rad (0 gives ``params`` itself, up to rounding).

    """
    a, c, (p_ref, R_ref) = axis
    spec = params.spec
    R0, markers = params.R0, np.asarray(params.markers, dtype=float)
    ax = skew(a)
    RG = np.eye(3) + np.sin(phi) * ax + (1.0 - np.cos(phi)) * ax @ ax
    tG = c - RG @ c
    p0 = params.p0 + R0 @ tG
    q0 = quat.from_matrix(R0 @ RG)
    # H⁻¹ on a point m of the tool frame: m' = R_refᵀ (G⁻¹(R_ref m + p_ref) - p_ref)
    world = markers @ R_ref.T + p_ref
    back = (world - c) @ RG + c  # G⁻¹(x) = c + R_Gᵀ (x - c), row-wise
    moved = (back - p_ref) @ R_ref
    q1 = (quat.from_matrix(R_ref.T @ RG.T @ R_ref @ quat.to_matrix(params.q1))
          if spec.has_q1 else None)
    return Parameters.from_transforms(spec, p0, q0, moved, q1)
