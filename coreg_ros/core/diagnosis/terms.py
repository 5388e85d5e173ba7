"""
The terms the candidate effects add to the measurement model (docs/design.md §5).

Each effect adds parameters to the model of Ikits eq. 16/18/19 in one of three ways:

- ``time``: device A is evaluated at ``t - s(t; θ)`` instead of t (the pairs' stamps); the
  output error moves by ``-ḟ ∂s/∂θ`` to first order, with ``ḟ = J_x ẋ_A`` the rate of the
  model output. Time offset ``s = τ`` (``OffsetShift``); clock drift ``s = τ0 + κ t``
  (``DriftShift``).
- ``mean``: the output error e = f - y gains a term ``δe(θ)`` (Jacobian ``∂δe/∂θ``): scale,
  field distortion, link flex, backlash (``MeanEffect``).
- ``variance``: the per-pair covariance of e changes (``variance.py``): noise scale, distance
  noise, timestamp jitter, outliers.

The classes here only build the extra terms; which effect uses which term is its class in
``effects/`` (``term``), fitting is ``fit.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.observability import tangent_matrix
from coreg_ros.core.diagnosis.data import DiagData
from coreg_ros.core.rigid import rigid_columns
from coreg_ros.core.so3 import skew
import numpy as np


@dataclass
class Context:
    """
    What a mean effect sees of one chunk of pairs at the current parameters.

    Attributes
    ----------
    data : DiagData
    idx : ndarray of int
        Pairs of the chunk.
    params : Parameters
    quat_a : ndarray, shape (n, 4)
        A's orientation used (after any time shift).
    f_pos : ndarray, shape (n, k, 3)
        Model marker positions in B's base frame, m.
    j_x : ndarray, shape (n, m, 6)
        ∂e/∂(p_A, δ_A).
    vel : ndarray, shape (n, 3)
        A's velocity, m/s, A's base frame.
    j_phi : ndarray, shape (n, m, P), optional
        ∂e/∂φ (chart coordinates).

    """

    data: DiagData
    idx: np.ndarray
    params: object
    quat_a: np.ndarray
    f_pos: np.ndarray
    j_x: np.ndarray
    vel: np.ndarray
    j_phi: Optional[np.ndarray] = None


def _quadratic(u: np.ndarray) -> np.ndarray:
    """Return the six monomials of degree two of u (n, 3): xx, yy, zz, xy, xz, yz."""
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=1)


class MeanEffect:
    """Base of effects that add ``δe(θ)`` to the output error."""

    name = ''
    n = 0

    def setup(self, data: DiagData) -> None:
        """Fix data-dependent constants (scales, centres) from all pairs."""

    def apply(self, ctx: Context, theta: np.ndarray):
        """Return δe (n, m) and ∂δe/∂θ (n, m, k) for the chunk."""
        raise NotImplementedError


class Scale(MeanEffect):
    """
    B's positions scaled by (1 + s) per axis of B's base frame: ``y = (1 + s) ⊙ f``.

    δe = s ⊙ f (positions of every marker), θ = (s_x, s_y, s_z), fractions.
    """

    name = 'scale'
    n = 3

    def apply(self, ctx, theta):
        """Scale the model's marker positions."""
        n, k = ctx.f_pos.shape[:2]
        m = ctx.data.m
        J = np.zeros((n, m, 3))
        for j in range(k):
            rows = slice(3 * j, 3 * j + 3)
            J[:, rows, :] = ctx.f_pos[:, j, :, None] * np.eye(3)
        return J @ theta, J


def _cubic(u: np.ndarray) -> np.ndarray:
    """Return the ten monomials of degree three of u (n, 3)."""
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    return np.stack([x ** 3, y ** 3, z ** 3, x * x * y, x * x * z, y * y * x, y * y * z,
                     z * z * x, z * z * y, x * y * z], axis=1)


class FieldDistortion(MeanEffect):
    """
    A smooth error field of B: quadratic and cubic in the marker position.

    ``d(p) = Θ_p · [q(u), c(u)]`` with ``u = (p - centre) / spread`` (the workspace's centre
    and half-size), q the six degree-two and c the ten degree-three monomials: the cubic
    terms follow the steep side of a field whose source (a dipole-like disturbance) lies near
    the workspace. For full pose also a rotation error ``Exp(Θ_r · [1, u, q(u)])`` and a
    dipole on the left of B's orientation (its metric is half of it). The constant part and a
    rigid turn are left to T0; the linear part a rigid registration cannot absorb is the
    field's too: a field free of sources in the workspace (the gradient of a harmonic
    potential) has a symmetric, trace-free Jacobian, so five such linear terms are fitted (a
    trace, a uniform scale, stays with ``scale``). Its size is reported as the part a rigid
    registration cannot absorb.
    """

    name = 'field_distortion'
    per_axis = 16

    def setup(self, data):
        """Fix the centre and spread of the workspace and the dipole source's position."""
        pts = data.b_points.reshape(-1, 3)
        self.centre = pts.mean(axis=0)
        self.spread = float(np.max(np.linalg.norm(pts - self.centre, axis=1))) or 1.0
        self.rot = data.spec.has_q1
        # one search per recording: every model holding the field shares its source
        if 'dipole_source' not in data.cache:
            data.cache['dipole_source'] = _dipole_source(data, self.centre, self.spread)
        self.source = data.cache['dipole_source']
        self.n_pos = 3 * self.per_axis + 3 + 5
        self.n = self.n_pos + (33 if self.rot else 0)

    def dipole(self, points: np.ndarray) -> np.ndarray:
        """Field of a unit dipole moment along each axis at the source, (n, 3, 3), per m³."""
        return _dipole_matrix(points - self.source) * (0.5 * self.spread) ** 3

    def basis(self, points: np.ndarray) -> np.ndarray:
        """Degree-two and degree-three monomials of the centred positions, shape (n, 16)."""
        u = (points - self.centre) / self.spread
        return np.concatenate([_quadratic(u), _cubic(u)], axis=1)

    def apply(self, ctx, theta):
        """Add the field at the model's marker positions."""
        n, k = ctx.f_pos.shape[:2]
        m = ctx.data.m
        a = self.per_axis
        J = np.zeros((n, m, self.n))
        for j in range(k):
            q = self.basis(ctx.f_pos[:, j, :])
            for ax in range(3):
                J[:, 3 * j + ax, a * ax:a * ax + a] = q
            J[:, 3 * j:3 * j + 3, 3 * a:3 * a + 3] = self.dipole(ctx.f_pos[:, j, :])
            J[:, 3 * j:3 * j + 3, 3 * a + 3:3 * a + 8] = self.linear(ctx.f_pos[:, j, :])
        if self.rot:
            q = _quadratic((ctx.f_pos[:, 0, :] - self.centre) / self.spread)
            for ax in range(3):
                J[:, 3 + ax, self.n_pos + 6 * ax:self.n_pos + 6 * ax + 6] = 0.5 * q
            J[:, 3:6, self.n_pos + 18:self.n_pos + 21] = 0.5 * self.dipole(ctx.f_pos[:, 0, :])
            # a rotation field's constant and linear parts: the orientation's error is not
            # tied to the positions' as T0's turn is, so T0 cannot absorb them
            u = (ctx.f_pos[:, 0, :] - self.centre) / self.spread
            J[:, 3:6, self.n_pos + 21:self.n_pos + 24] = 0.5 * np.eye(3)[None]
            for ax in range(3):
                J[:, 3 + ax, self.n_pos + 24 + 3 * ax:self.n_pos + 27 + 3 * ax] = 0.5 * u
        return J @ theta, J

    def field(self, points: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Position error (n, 3), m, at B positions (n, 3)."""
        q = self.basis(points)
        a = self.per_axis
        poly = np.stack([q @ theta[a * ax:a * ax + a] for ax in range(3)], axis=1)
        return (poly + self.dipole(points) @ theta[3 * a:3 * a + 3]
                + self.linear(points) @ theta[3 * a + 3:3 * a + 8])

    def linear(self, points: np.ndarray) -> np.ndarray:
        """Return the five symmetric trace-free linear maps of the centred positions, (n, 3, 5)."""
        u = (points - self.centre) / self.spread
        x, y, z = u[:, 0], u[:, 1], u[:, 2]
        o = np.zeros_like(x)
        return np.stack([np.stack([x, -y, o], axis=1), np.stack([o, y, -z], axis=1),
                         np.stack([y, x, o], axis=1), np.stack([z, o, x], axis=1),
                         np.stack([o, z, y], axis=1)], axis=2)


def _dipole_matrix(r: np.ndarray) -> np.ndarray:
    """(3 r̂ r̂ᵀ - I) / |r|³ per row of r (n, 3): the field of a unit moment, (n, 3, 3)."""
    dist = np.maximum(np.linalg.norm(r, axis=1), 1e-9)
    rh = r / dist[:, None]
    return (3.0 * rh[:, :, None] * rh[:, None, :] - np.eye(3)[None]) / dist[:, None, None] ** 3


def _dipole_source(data, centre: np.ndarray, spread: float) -> np.ndarray:
    """
    Position of a dipole source that best explains the base residuals, from a grid around.

    Candidates lie in 26 directions at 1.15-3 workspace radii from its centre. For each the
    base position residuals are regressed on the dipole's field together with what the
    calibration absorbs anyway (a translation, a small rotation and a scale about the
    centre); the candidate leaving the least is kept. Far candidates give a smooth field the
    polynomial terms hold already, so a poor pick costs little.
    """
    e = data.cache.get('base_errors')
    pts = data.b_points[:, 0, :]
    far = centre + np.array([0.0, 0.0, 3.0 * spread])
    if e is None:
        return far
    step = max(1, len(pts) // 3000)
    p = pts[::step]
    y = e[::step, 0:3].reshape(-1)
    q = (p - centre) / spread
    n = len(p)
    base = np.zeros((n, 3, 9))
    base[:, :, 0:6] = rigid_columns(q)
    base[:, 0, 6], base[:, 1, 7], base[:, 2, 8] = q[:, 0], q[:, 1], q[:, 2]
    grid = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                     if (i, j, k) != (0, 0, 0)], dtype=float)
    grid /= np.linalg.norm(grid, axis=1, keepdims=True)

    def residual(s):
        A = np.concatenate([base, _dipole_matrix(p - s) * spread ** 3], axis=2)
        A = A.reshape(3 * n, 12)
        x, *_ = np.linalg.lstsq(A, y, rcond=None)
        return y - A @ x

    best, best_ss = far, np.inf
    for d in grid:
        for dist in (1.15, 1.4, 1.8, 3.0):
            s = centre + dist * spread * d
            ss = float(np.sum(residual(s) ** 2))
            if ss < best_ss:
                best, best_ss = s, ss
    # refine (variable projection: the moment solved for at each trial source), kept
    # outside the workspace's sphere so the basis never has a pole among the samples
    from scipy.optimize import least_squares

    def outside(s):
        # between just outside the workspace and three radii: a source further away gives
        # a field the polynomial terms hold already, and its dipole column becomes nearly
        # a combination of theirs (the joint fit then has a direction the data cannot
        # fix, along which the field's non-rigid size wanders)
        v = s - centre
        r = np.linalg.norm(v)
        return centre + v * min(max(r, 1.05 * spread), 3.0 * spread) / max(r, 1e-12)

    try:
        res = least_squares(lambda s: residual(outside(s)), best, x_scale=spread,
                            max_nfev=60, method='trf')
        s = outside(res.x)
        if float(np.sum(residual(s) ** 2)) < best_ss:
            best = s
    except (ValueError, np.linalg.LinAlgError):
        pass
    return best


class LinkFlex(MeanEffect):
    """
    A link that pivots under gravity of unknown direction: the marker sags and tilts.

    With ℓ = R_A p1 / |p1| the link direction in A's base frame, a hinge on the link loaded
    by the weight beyond it turns the marker by ``δθ = ℓ × w`` (w = θ_max ĝ: gravity's
    direction times the largest tilt) and moves it by ``δp = (I - ℓ ℓᵀ) u`` (u = sag ĝ: the
    displacement when the link is horizontal), both in A's base frame, carried into B's by
    R0. Linear in θ = (u, w) (w for full pose only), m and rad; gravity's direction is
    estimated with them (û). Their constant parts are absorbed by T0 and T1: they are seen
    through how the tool's orientation changes the link's direction.
    """

    name = 'link_flex'

    def setup(self, data):
        """Sag only, or sag and tilt (full pose)."""
        self.rot = data.spec.has_q1
        self.n = 3 + (3 if self.rot else 0)

    def apply(self, ctx, theta):
        """Sag and tilt at the chunk's tool orientations."""
        p = ctx.params
        Ra = quat.to_matrix(ctx.quat_a)
        p1 = p.markers[0]
        ell = Ra @ (p1 / max(np.linalg.norm(p1), 1e-9))             # (n, 3)
        n = len(ell)
        proj = np.eye(3)[None] - ell[:, :, None] * ell[:, None, :]   # I - ℓℓᵀ
        J = np.zeros((n, ctx.data.m, self.n))
        sag = np.einsum('ij,njk->nik', p.R0, proj)
        for j in range(p.spec.n_markers):
            J[:, 3 * j:3 * j + 3, 0:3] = sag
        if self.rot:
            J[:, 3:6, 3:6] = 0.5 * np.einsum('ij,njk->nik', p.R0, skew(ell))
        return J @ theta, J


class Backlash(MeanEffect):
    """
    A's position lags b_j behind the motion along each axis j of A's base frame.

    The true position is ``p_A + b ⊙ sgn(v)``, with a smooth sign ``tanh(v / v0)`` (zero
    while an axis turns, where the play leaves the output still), v0 a few times the noise of
    the finite-difference velocity. θ = (b_x, b_y, b_z), m (half the play's width).
    """

    name = 'backlash'
    n = 3

    def setup(self, data):
        """Fix v0 from A's noise and the velocity window."""
        step = np.median(np.diff(data.trajectory.t)) if len(data.trajectory) > 1 else 0.02
        half = max(0.04, 1.5 * step)
        sigma_v = data.sigma_a[0] / (np.sqrt(2.0) * half)
        self.v0 = max(2.0 * sigma_v, 1e-3)

    def apply(self, ctx, theta):
        """Offset A's position along the sign of its velocity."""
        s = np.tanh(ctx.vel / self.v0)
        J = ctx.j_x[:, :, 0:3] * s[:, None, :]
        return J @ theta, J


class TimeShift:
    """Base of effects that shift the time at which A is evaluated: ``t - s(t; θ)``."""

    name = ''
    n = 0

    def setup(self, data: DiagData) -> None:
        """Nothing depends on the data: the shift is a function of time alone."""

    def shift(self, theta: np.ndarray, t: np.ndarray, duration: float):
        """Return the shift s(t) (n,), s, and ∂s/∂θ (n, k)."""
        raise NotImplementedError


class OffsetShift(TimeShift):
    """A constant offset of B's clock: ``s = τ``, θ = (τ,), s."""

    name = 'time_offset'
    n = 1

    def shift(self, theta, t, duration):
        """Shift every pair by τ."""
        return np.full(t.shape, theta[0]), np.ones((t.size, 1))


class DriftShift(TimeShift):
    """
    A clock that drifts: ``s = τ0 + κ t``.

    θ = (τ0, κ T) with T the recording's duration (for conditioning), s.
    """

    name = 'clock_drift'
    n = 2

    def shift(self, theta, t, duration):
        """Shift by the offset at the start plus the drift since."""
        u = t / max(duration, 1e-9)
        return theta[0] + theta[1] * u, np.stack([np.ones_like(u), u], axis=1)


class StepShift(TimeShift):
    """
    A clock that steps at one instant: ``s = τ + Δ·1[t ≥ t_s]``, θ = (τ, Δ), s.

    The instant t_s is located once per recording before the effects are scored
    (``steps.locate_clock_step``, kept in ``data.cache['clock_step']``); the fit starts at the
    scan's one-step estimate of θ.
    """

    name = 'clock_step'
    n = 2

    def setup(self, data: DiagData) -> None:
        """Read the located instant (the middle of the recording if none was located)."""
        found = data.cache.get('clock_step')
        self.at = float(found.at_s) if found is not None else 0.5 * float(data.t[-1])
        self.theta0 = (np.asarray(found.theta, dtype=float) if found is not None
                       else np.zeros(2))

    def start(self) -> np.ndarray:
        """Return the fit's starting θ: the scan's estimate."""
        return self.theta0.copy()

    def shift(self, theta, t, duration):
        """Shift by τ, and by Δ more from the instant on."""
        after = (t >= self.at).astype(float)
        return theta[0] + theta[1] * after, np.stack([np.ones_like(t), after], axis=1)


class PoseStep(MeanEffect):
    """
    T0 or T1 that moves once: from an instant on, the calibration is ψ + Δψ.

    ``δe = 1[t ≥ t_s] J_ψ Δψ``, θ = Δψ in the tangent coordinates ψ of the calibration
    (``calibration.observability.tangent_matrix``: T0's translation in B's base frame, m, its
    rotation about B's base axes, rad, the marker position(s) in A's tool frame, m, T1's
    rotation about A's tool axes, rad). The instant is located once per recording
    (``steps.locate_pose_step``, ``data.cache['pose_step']``).
    """

    name = 'pose_step'

    def setup(self, data):
        """Read the located instant (the middle of the recording if none was located)."""
        found = data.cache.get('pose_step')
        self.at = float(found.at_s) if found is not None else 0.5 * float(data.t[-1])
        self.n = data.spec.n_params

    def apply(self, ctx, theta):
        """Step the calibration from the instant on."""
        after = (ctx.data.t[ctx.idx] >= self.at).astype(float)
        to_tangent = np.linalg.inv(tangent_matrix(ctx.params))
        J = np.matmul(ctx.j_phi, to_tangent) * after[:, None, None]
        return J @ theta, J
