"""
A priori estimates as extra residual rows (Ikits B.3, eqs. 55-56).

A prior adds ``(φ̂ - φ)ᵀ W_φ (φ̂ - φ)`` to the objective (eqs. 28 and 39): whitened, a few more
residual rows and their Jacobian. Both solvers add them to their normal equations (OLS to JᵀJ,
TLS to the Schur complement); ``Prior.terms`` makes the terms from a pose prior: a previous
calibration, a CAD drawing, a measured lever (partial: an infinite variance leaves an axis free).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.errors import InputError
from coreg_ros.core.models import (
    error_rotation_jacobian,
    ModelSpec,
    Parameters,
    S0,
    S1,
    tangent_of_chart,
)
from coreg_ros.core.types import UncertainPose
import numpy as np

#: A prior term returns whitened residual rows (k,) and their Jacobian (k, P) at φ (Ikits B.3).
PriorTerm = Callable[[Parameters], tuple]


def prior_rows(problem, params: Parameters):
    """
    Stacked prior residuals, Jacobian and count (Ikits eqs. 55-56).

    Parameters
    ----------
    problem : Problem
        Its ``priors`` (a list of ``PriorTerm``) and ``spec``.
    params : Parameters
        The φ the terms are evaluated at.

    Returns
    -------
    r : ndarray, shape (k,)
    J : ndarray, shape (k, P)

    """
    P = problem.spec.n_params
    if not problem.priors:
        return np.zeros(0), np.zeros((0, P))
    parts = [term(params) for term in problem.priors]
    return np.concatenate([r for r, _ in parts]), np.concatenate([j for _, j in parts])


@dataclass(frozen=True)
class Prior:
    """
    A priori estimates of T0 and/or T1 (Ikits B.3), each with a 6×6 ROS-layout covariance.

    ``joint_cov`` (12×12 over (T0, T1), ROS layout), when given with both poses, replaces the
    two 6×6 blocks: a previous calibration's T0 and T1 are correlated, and dropping the cross
    terms would misstate the information the prior carries. For models that do not estimate
    q1, only the position part of a T1 prior is used; an infinite variance leaves an axis free.

    ``gravity_sigma`` (rad), when given, says that both devices report z up (against gravity,
    e.g. a visual-inertial odometry against motion capture): T0 takes A's base z to B's base
    z, within that σ of tilt, whatever its yaw (``gravity_term``). With it a yaw-only
    alignment (4 DOF: the translation and the yaw) is determined by a motion that turns
    about z alone.

    ``data_sketch``, when the prior is a previous result that carries one
    (``core.provenance.data_sketch``), identifies the samples it was calibrated on, so that a
    calibration of the same samples refuses it rather than count them twice.
    """

    base_to_base: Optional[UncertainPose] = None
    tool_to_marker: Optional[UncertainPose] = None
    joint_cov: Optional[np.ndarray] = None
    gravity_sigma: Optional[float] = None
    data_sketch: Optional[dict] = None

    def __post_init__(self):
        """Refuse what is not a prior in one line naming the fix (shapes, NaN)."""
        for name in ('base_to_base', 'tool_to_marker'):
            pose = getattr(self, name)
            if pose is not None and not isinstance(pose, UncertainPose):
                raise InputError(f'the prior {name} must be an UncertainPose (position, '
                                 f'quat_wxyz, 6×6 covariance), got {type(pose).__name__}')
            if pose is not None and pose.covariance is not None:
                _check_covariance(pose.covariance, 6, f'the prior covariance of {name}')
        if self.joint_cov is not None:
            _check_covariance(self.joint_cov, 12, 'the prior joint covariance (T0, T1)')

    def poses(self) -> list:
        """(which, pose) for the poses given: 0 for T0, 1 for T1."""
        return [(w, p) for w, p in ((0, self.base_to_base), (1, self.tool_to_marker))
                if p is not None]

    def axes(self, spec: ModelSpec) -> np.ndarray:
        """Constrained components among the 12 of (T0, T1) (``constrained_axes`` of each)."""
        return np.concatenate([np.zeros(0, dtype=int)]
                              + [6 * w + constrained_axes(p, spec, w) for w, p in self.poses()])

    def covariance(self) -> np.ndarray:
        """12×12 covariance of (T0, T1): ``joint_cov`` or the blocks (inf where not given)."""
        if self.joint_cov is not None and len(self.poses()) == 2:
            return np.asarray(self.joint_cov, dtype=float).reshape(12, 12)
        cov = np.diag(np.full(12, np.inf))
        for w, p in self.poses():
            if p.covariance is None:
                raise InputError('a prior needs a covariance; give its 6×6 covariance or '
                                 'sigma per axis')
            cov[6 * w:6 * w + 6, 6 * w:6 * w + 6] = np.asarray(p.covariance,
                                                               dtype=float).reshape(6, 6)
        return cov

    def terms(self, spec: ModelSpec) -> list:
        """Prior terms for the estimator: callables φ -> (whitened rows, Jacobian)."""
        out = [] if self.gravity_sigma is None else [gravity_term(spec, self.gravity_sigma)]
        if not self.poses():
            return out
        for w, p in self.poses():
            if not len(constrained_axes(p, spec, w)):
                raise InputError(
                    f'the prior on {("base_to_base", "tool_to_marker")[w]} constrains nothing '
                    f'{spec.name} estimates (every variance is negative, infinite or of an '
                    f'orientation the model does not estimate); give a variance > 0 for each '
                    f'axis it knows, or leave that pose out')
        keep = self.axes(spec)
        cov = self.covariance()[np.ix_(keep, keep)]
        try:
            L = np.linalg.inv(np.linalg.cholesky(cov))
        except np.linalg.LinAlgError as e:
            low = float(np.min(np.linalg.eigvalsh(0.5 * (cov + cov.T))))
            raise InputError(
                f'the prior covariance is not positive definite (smallest eigenvalue {low:.3g} '
                f'over the axes it constrains); give a symmetric covariance whose eigenvalues '
                f'are all > 0 (a previous result, or sigma per axis), np.inf on the diagonal '
                f'for an axis left free') from e
        rows = [(w, _pose_rows(p, spec, w)) for w, p in self.poses()]

        def term(params: Parameters):
            e = np.zeros(12)
            J = np.zeros((12, spec.n_params))
            for w, fn in rows:
                e[6 * w:6 * w + 6], J[6 * w:6 * w + 6] = fn(params)
            return L @ e[keep], L @ J[keep]

        return [term] + out


def _check_covariance(cov, n: int, what: str) -> None:
    """Refuse a covariance that is not n×n (or n² numbers) or holds NaN."""
    shape = np.shape(cov)
    if int(np.prod(shape)) != n * n:
        raise InputError(f'{what} must be {n}×{n} (ROS layout: x y z, rotation about x y z'
                         f'{" of T0, then T1" if n == 12 else ""}) or {n * n} numbers; got '
                         f'shape {shape}: for axes the prior does not know put np.inf on the '
                         f'diagonal')
    if np.isnan(np.asarray(cov, dtype=float)).any():
        raise InputError(f'{what} holds NaN; give numbers (np.inf on the diagonal for an axis '
                         f'left free)')


def gravity_term(spec: ModelSpec, sigma: float):
    """
    Build the prior term that T0 takes A's base z to B's base z: both devices report z up.

    The rows are the x and y components of ``R0 e_z`` (the tilt between the two z axes, rad
    for small tilts) over ``sigma``; their Jacobian with respect to a rotation ``R0 ← Exp(δθ)
    R0`` is ``-[R0 e_z]×`` (rows x, y), through the chart of q0 (``tangent_of_chart``).

    Parameters
    ----------
    spec : ModelSpec
        The model (for the length of φ).
    sigma : float
        σ of the tilt between the two z axes, rad (> 0).

    """
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f'the gravity alignment needs a σ > 0 (rad), got {sigma!r}; e.g. '
                         f'0.01 for about half a degree of tilt between the two z axes')

    def term(params: Parameters):
        tilt, rows = gravity_tilt(params.R0)
        J = np.zeros((2, spec.n_params))
        J[:, S0] = rows @ tangent_of_chart(params.q0, params.dq0) / sigma
        return tilt / sigma, J

    return term


def gravity_tilt(R0: np.ndarray) -> tuple:
    """
    Return the tilt between the two bases' z axes and its Jacobian.

    Parameters
    ----------
    R0 : ndarray, shape (3, 3)
        T0's rotation (A's base in B's).

    Returns
    -------
    tilt : ndarray, shape (2,)
        The x and y components of ``R0 e_z`` (rad, for small tilts).
    jacobian : ndarray, shape (2, 3)
        With respect to a rotation ``R0 ← Exp(δθ) R0`` about B's fixed axes (the layout of
        the published covariance): rows x, y of ``-[R0 e_z]×``.

    """
    z = np.asarray(R0, dtype=float)[:, 2]  # R0 e_z: A's base z in B's base frame
    return z[0:2].copy(), np.array([[0.0, z[2], -z[1]], [-z[2], 0.0, z[0]]])


def constrained_axes(pose: UncertainPose, spec: ModelSpec, which: int) -> np.ndarray:
    """
    Return the axes (of 0..5) a prior pose constrains: finite variance, estimated by the model.

    An infinite variance marks an axis the prior says nothing about (a partial prior, e.g. a
    CAD position of T1 whose orientation is unknown).
    """
    if pose.covariance is None:
        raise InputError('a prior needs a covariance; give its 6×6 covariance or sigma per axis')
    cov = np.asarray(pose.covariance, dtype=float).reshape(6, 6)
    axes = [i for i in range(6) if np.isfinite(cov[i, i]) and cov[i, i] > 0]
    if which == 1 and not spec.has_q1:
        axes = [i for i in axes if i < 3]
    return np.asarray(axes, dtype=int)


def _pose_rows(pose: UncertainPose, spec: ModelSpec, which: int):
    """Unwhitened rows ``[p - p̂; δθ]`` with ``q = Exp(δθ) ⊗ q̂`` and their Jacobian (6, P)."""
    q_hat = quat.validate_quaternions(pose.quat_wxyz, 'prior orientation')
    p_slice = slice(0, 3) if which == 0 else spec.marker_slice(0)
    with_rotation = which == 0 or spec.has_q1

    def rows(params: Parameters):
        J = np.zeros((6, spec.n_params))
        e = np.zeros(6)
        e[0:3] = params.phi[p_slice] - pose.position
        J[0:3, p_slice] = np.eye(3)
        if with_rotation:
            q = params.q0 if which == 0 else params.q1
            dq = params.dq0 if which == 0 else params.dq1
            e_rot, de_da = error_rotation_jacobian(q[None], q_hat[None])
            e[3:6] = 2.0 * e_rot[0]  # ≈ δθ (the metric is half the angle)
            J[3:6, S0 if which == 0 else S1] = 2.0 * de_da[0] @ tangent_of_chart(q, dq)
        return e, J

    return rows


def gauge_terms(gauge: Prior, spec: ModelSpec) -> list:
    """
    Return the prior terms of a gauge: pins that hold what the data leave free, not knowledge.

    The same rows as ``gauge.terms`` (``calibration.observability.hold_prior``), marked so
    that Marquardt's damping leaves them out of its scale (``gauge_diagonal``).
    """
    terms = gauge.terms(spec)
    for term in terms:
        term.gauge = True
    return terms


def gauge_diagonal(problem, params: Parameters) -> np.ndarray:
    """
    Return diag(JᵀJ) of the gauge's rows (``Gauge``), to leave out of Marquardt's damping scale.

    A gauge's pins are a convention chosen far tighter than the data (``HOLD_TIGHTNESS``);
    damped like information, λ·(1/σ_pin²) on a pinned component is λ/tightness² times what
    the data give it (1e-6 · 1e6: the data's own information at the first λ), a second
    stiffness the steps then crawl against (a turntable, whose held turn couples to every
    component, converged linearly: one pass more than a full-rank rig). The data's diagonal
    still damps that component, as on a full-rank rig.

    Parameters
    ----------
    problem : Problem
        Its ``priors`` (a gauge's terms are marked by ``gauge_terms``).
    params : Parameters
        Where the rows are taken.

    Returns
    -------
    ndarray, shape (P,)
        Zero when the problem has no gauge.

    """
    out = np.zeros(problem.spec.n_params)
    for term in problem.priors:
        if getattr(term, 'gauge', False):
            _, J = term(params)
            out += np.einsum('ij,ij->j', J, J)
    return out
