"""Ellipsoids and axis cones of uncertain poses, and how to draw them (Hoff & Vincent §3.3)."""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import InputError
from coreg_ros.core.quaternion import to_matrix as _rotation
from coreg_ros.core.so3 import skew
from coreg_ros.core.types import UncertainPose
from coreg_ros.core.uncertainty._unknown import (
    _cov_or_zero,
    _symmetric,
)
from coreg_ros.core.uncertainty.consistency import coverage_probability
import numpy as np


@dataclass(frozen=True)
class Ellipsoid:
    """
    Uncertainty ellipsoid ``{z : zᵀ C⁻¹ z ≤ k²}`` of a 3×3 covariance (Hoff §3.3).

    Attributes
    ----------
    semi_axes : ndarray, shape (3,)
        Semi-axis lengths k·√λ, largest first (units of √C, e.g. m).
    axes : ndarray, shape (3, 3)
        Unit direction of each semi-axis, as columns, in the covariance's frame.
    n_sigma : float
        k.
    probability : float
        Probability that the error lies inside (≈ 0.971 for k = 3).

    """

    semi_axes: np.ndarray
    axes: np.ndarray
    n_sigma: float
    probability: float

    def surface(self, center=(0.0, 0.0, 0.0), n: int = 24):
        """Mesh (X, Y, Z), each shape (n, n), of the ellipsoid surface around ``center``."""
        u = np.linspace(0.0, 2.0 * np.pi, n)
        v = np.linspace(0.0, np.pi, n)
        sphere = np.stack([np.outer(np.cos(u), np.sin(v)), np.outer(np.sin(u), np.sin(v)),
                           np.outer(np.ones_like(u), np.cos(v))], axis=-1)
        pts = (sphere * self.semi_axes) @ self.axes.T + np.asarray(center, dtype=float)
        return pts[..., 0], pts[..., 1], pts[..., 2]


def ellipsoid_axes(cov, n_sigma: float = 3.0) -> Ellipsoid:
    """
    Principal axes of the ``n_sigma`` ellipsoid of a covariance (eigen-decomposition).

    Parameters
    ----------
    cov : array_like, shape (3, 3)
        E.g. the position block of a pose covariance (Hoff eq. 9), m².
    n_sigma : float
        k of ``zᵀ C⁻¹ z ≤ k²`` (3 by default, as Hoff).

    Returns
    -------
    Ellipsoid

    """
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (3, 3):
        raise InputError(f'ellipsoid_axes needs a 3×3 covariance, got {cov.shape}')
    if (np.diag(cov) < 0).any():
        raise InputError('the covariance has unknown components (negative diagonal); no '
                         'ellipsoid can be drawn')
    lam, vec = np.linalg.eigh(_symmetric(cov))
    order = np.argsort(lam)[::-1]
    lam = np.clip(lam[order], 0.0, None)
    vec = vec[:, order]
    vec = vec * np.where(np.linalg.det(vec) < 0, -1.0, 1.0)  # right-handed
    return Ellipsoid(semi_axes=float(n_sigma) * np.sqrt(lam), axes=vec, n_sigma=float(n_sigma),
                     probability=coverage_probability(n_sigma, 3))


@dataclass(frozen=True)
class AxisCone:
    """
    Uncertainty of the direction of one axis of a frame (Hoff §3.3, Fig. 1).

    Attributes
    ----------
    index : int
        0, 1, 2 for the frame's x, y, z axis.
    direction : ndarray, shape (3,)
        The axis a = R e in the parent frame (unit).
    covariance : ndarray, shape (3, 3)
        ``C_a = [a]× C_θ [a]×ᵀ``, rank 2 (flat along a), of the unit axis' tip.
    half_angles : ndarray, shape (2,)
        Cone half-angles ``atan(k √λ)`` of the ``n_sigma`` ellipse at the tip, rad, largest
        first.
    ellipse_axes : ndarray, shape (3, 2)
        Unit directions (perpendicular to a) of those half-angles, as columns.
    n_sigma : float
    probability : float
        Probability that the tip lies inside the ellipse (2-D; ≈ 0.989 for k = 3).

    """

    index: int
    direction: np.ndarray
    covariance: np.ndarray
    half_angles: np.ndarray
    ellipse_axes: np.ndarray
    n_sigma: float
    probability: float


def axis_covariance(q, cov_rot) -> np.ndarray:
    """
    Covariance of each unit axis a_i = R e_i of a frame: ``[a]× C_θ [a]×ᵀ``, shape (..., 3, 3, 3).

    With ``R_true = Exp(δθ) R``, the axis moves by ``δθ × a = -[a]× δθ`` to first order.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Orientation of the frame (w, x, y, z).
    cov_rot : array_like, shape (..., 3, 3)
        Rotation block of the pose covariance, rad².

    Returns
    -------
    ndarray, shape (..., 3, 3, 3)
        Index -3 is the axis (x, y, z).

    """
    R = _rotation(q)
    A = skew(np.swapaxes(R, -1, -2))  # (..., 3 axes, 3, 3): [a_i]×
    c = np.asarray(cov_rot, dtype=float)[..., None, :, :]
    return A @ c @ np.swapaxes(A, -1, -2)


def axis_cones(pose: UncertainPose, n_sigma: float = 3.0) -> list[AxisCone]:
    """
    Compute the three axis cones of Hoff's Fig. 1 for a pose with covariance.

    Parameters
    ----------
    pose : UncertainPose
        Orientation and ROS-layout covariance (its rotation block must be known).
    n_sigma : float
        Size of the ellipse at each axis tip.

    Returns
    -------
    list of AxisCone
        For the x, y and z axes.

    """
    cov = _cov_or_zero(pose)
    if (np.diag(cov)[3:6] < 0).any():
        raise InputError('the orientation is not estimated (unknown covariance); no axis '
                         'cones can be drawn')
    R = _rotation(pose.quat_wxyz)
    cones = []
    for i, c_a in enumerate(axis_covariance(pose.quat_wxyz, cov[3:6, 3:6])):
        a = R[:, i]
        lam, vec = np.linalg.eigh(_symmetric(c_a))
        # the eigenvector along a has eigenvalue 0; keep the two perpendicular ones
        perp = np.argsort(np.abs(vec.T @ a))[:2]
        lam, vec = lam[perp], vec[:, perp]
        order = np.argsort(lam)[::-1]
        lam = np.clip(lam[order], 0.0, None)
        cones.append(AxisCone(index=i, direction=a, covariance=c_a,
                              half_angles=np.arctan(float(n_sigma) * np.sqrt(lam)),
                              ellipse_axes=vec[:, order], n_sigma=float(n_sigma),
                              probability=coverage_probability(n_sigma, 2)))
    return cones


# --------------------------------------------------------------------------- display geometry

def ellipsoid_orientation(ell: Ellipsoid) -> np.ndarray:
    """
    Orientation (w, x, y, z) whose rotation matrix has the ellipsoid's axes as columns.

    With it, a unit sphere scaled by ``2 · semi_axes`` (diameters, e.g. an RViz SPHERE
    marker's ``scale``) and rotated is the ellipsoid. Shape (4,).
    """
    return quat.from_matrix(ell.axes)


def cone_mesh(cone: AxisCone, length: float = 1.0, gain: float = 1.0, n: int = 24,
              origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """
    Triangles of an axis cone (Hoff Fig. 1): apex at the frame origin, elliptical rim at the tip.

    Parameters
    ----------
    cone : AxisCone
        The cone to draw.
    length : float
        Drawn axis length, m.
    gain : float
        Magnification of tan(half-angle), so that milliradian cones can be seen.
    n : int
        Segments of the rim.
    origin : array_like, shape (3,)
        Frame origin in the parent frame, m.

    Returns
    -------
    ndarray, shape (n, 3, 3)
        Triangle k is (apex, rim_k, rim_k+1), e.g. for an RViz TRIANGLE_LIST marker.

    """
    t = np.linspace(0.0, 2.0 * np.pi, int(n) + 1)
    ext = float(gain) * np.tan(cone.half_angles)
    rim = (cone.direction[None, :] + np.cos(t)[:, None] * ext[0] * cone.ellipse_axes[:, 0]
           + np.sin(t)[:, None] * ext[1] * cone.ellipse_axes[:, 1]) * float(length)
    rim = rim + np.asarray(origin, dtype=float)
    apex = np.broadcast_to(np.asarray(origin, dtype=float), (int(n), 3))
    return np.stack([apex, rim[:-1], rim[1:]], axis=1)
