"""
The ten candidate effects as extensions of the measurement model (DESIGN.md §5).

Each effect adds parameters to the model of Ikits eq. 16/18/19 in one of three ways:

- ``time``: device A is evaluated at ``t - s(t; θ)`` instead of t (the pairs' stamps); the
  output error moves by ``-ḟ ∂s/∂θ`` to first order, with ``ḟ = J_x ẋ_A`` the rate of the
  model output. Time offset ``s = τ``; clock drift ``s = τ0 + κ t``.
- ``mean``: the output error e = f - y gains a term ``δe(θ)`` (Jacobian ``∂δe/∂θ``): scale,
  field distortion, link flex, backlash.
- ``variance``: the per-pair covariance of e changes (``variance.py``): noise scale, distance
  noise, timestamp jitter, outliers.

The functions here only build the extra terms; fitting is ``fit.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from coreg_ros.core import quaternion as quat
from coreg_ros.core.diagnosis.data import DiagData

#: The ten effects, in the order of DESIGN.md §5 (same names as the simulator's library).
EFFECT_NAMES = ('time_offset', 'clock_drift', 'timestamp_jitter', 'field_distortion',
                'distance_noise', 'scale', 'link_flex', 'outliers', 'backlash', 'noise_scale')

#: Effects acting on the time axis, on the output error, and on the noise.
TIME_EFFECTS = ('time_offset', 'clock_drift')
MEAN_EFFECTS = ('field_distortion', 'scale', 'link_flex', 'backlash')
VARIANCE_EFFECTS = ('timestamp_jitter', 'distance_noise', 'outliers', 'noise_scale')
#: Effects that change only the noise model (describe the noise, never close the gap).
NOISE_EFFECTS = ('timestamp_jitter', 'distance_noise', 'noise_scale')
#: Effects tied to the workspace (also cross-validated on spatial blocks).
SPATIAL_EFFECTS = ('field_distortion', 'scale', 'distance_noise')
#: Effects that need motion to show (velocity signatures).
MOTION_EFFECTS = ('time_offset', 'clock_drift', 'timestamp_jitter', 'backlash')
#: Pairs where the simpler effect is a special case of the richer one (simpler, richer).
NESTED = (('time_offset', 'clock_drift'), ('noise_scale', 'distance_noise'),
          ('scale', 'field_distortion'))

#: Gravity in A's base frame assumed by the link-flex model (A upright, z up).
GRAVITY_IN_A_BASE = np.array([0.0, 0.0, -1.0])


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

    """

    data: DiagData
    idx: np.ndarray
    params: object
    quat_a: np.ndarray
    f_pos: np.ndarray
    j_x: np.ndarray
    vel: np.ndarray


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


class FieldDistortion(MeanEffect):
    """
    A smooth error field of B around its base: quadratic in the marker position.

    ``d(p) = Θ_p · q(p / r)`` with q the six degree-two monomials and r the largest distance of
    B's markers from B's base; for full pose also a rotation error ``Exp(Θ_r · q(p / r))`` on
    the left of B's orientation (its metric is half of it). Zero at the source and curl-free
    fields included; constant and linear parts are left to T0 (and to ``scale``).
    """

    name = 'field_distortion'

    def setup(self, data):
        """Fix the distance scale r."""
        pts = data.b_points.reshape(-1, 3)
        self.r = float(np.max(np.linalg.norm(pts, axis=1)))
        self.rot = data.spec.has_q1
        self.n = 18 + (18 if self.rot else 0)

    def basis(self, points: np.ndarray) -> np.ndarray:
        """Degree-two monomials of points / r, shape (n, 6)."""
        return _quadratic(points / self.r)

    def apply(self, ctx, theta):
        """Add the field at the model's marker positions."""
        n, k = ctx.f_pos.shape[:2]
        m = ctx.data.m
        J = np.zeros((n, m, self.n))
        for j in range(k):
            q = self.basis(ctx.f_pos[:, j, :])
            for a in range(3):
                J[:, 3 * j + a, 6 * a:6 * a + 6] = q
        if self.rot:
            q = self.basis(ctx.f_pos[:, 0, :])
            for a in range(3):
                J[:, 3 + a, 18 + 6 * a:24 + 6 * a] = 0.5 * q
        return J @ theta, J

    def field(self, points: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Position error (n, 3), m, at B positions (n, 3)."""
        q = self.basis(points)
        return np.stack([q @ theta[6 * a:6 * a + 6] for a in range(3)], axis=1)


class LinkFlex(MeanEffect):
    """
    The marker sags by b along gravity (-z of A's base) times how horizontal the link is.

    ``δp_B = b h R0 ĝ`` with ``h = |ℓ × ĝ|``, ℓ the direction of ``R_A p1`` (p1 the marker
    offset in the tool frame), as a cantilever bends. θ = (b,), m. Its mean over the
    recording is absorbed by p0: b is seen through the variation of h with the orientation.
    """

    name = 'link_flex'
    n = 1

    def apply(self, ctx, theta):
        """Sag at the chunk's tool orientations."""
        p = ctx.params
        Ra = quat.to_matrix(ctx.quat_a)
        p1 = p.markers[0]
        ell = Ra @ (p1 / max(np.linalg.norm(p1), 1e-9))
        h = np.linalg.norm(np.cross(ell, GRAVITY_IN_A_BASE), axis=1)
        g_b = p.R0 @ GRAVITY_IN_A_BASE
        n = len(h)
        J = np.zeros((n, ctx.data.m, 1))
        for j in range(p.spec.n_markers):
            J[:, 3 * j:3 * j + 3, 0] = h[:, None] * g_b
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


def effect_kind(name: str) -> str:
    """``'noise'`` for effects that change only the noise model, else ``'structured'``."""
    return 'noise' if name in NOISE_EFFECTS else 'structured'


def make_mean_effect(name: str, data: DiagData) -> MeanEffect:
    """Instantiate and set up the mean effect ``name`` for the data."""
    cls = {'scale': Scale, 'field_distortion': FieldDistortion, 'link_flex': LinkFlex,
           'backlash': Backlash}[name]
    eff = cls()
    eff.setup(data)
    return eff


def time_parameters(name: str) -> int:
    """Return the number of parameters of a time effect."""
    return {'time_offset': 1, 'clock_drift': 2}[name]


def time_shift(name: str, theta: np.ndarray, t: np.ndarray, duration: float):
    """
    Shift s(t) (s) of the time at which A is evaluated, and ∂s/∂θ (n, k).

    clock drift: θ = (τ0, κ T) with T the recording's duration (for conditioning); so
    ``s = τ0 + κ t``.
    """
    if name == 'time_offset':
        return np.full(t.shape, theta[0]), np.ones((t.size, 1))
    u = t / max(duration, 1e-9)
    return theta[0] + theta[1] * u, np.stack([np.ones_like(u), u], axis=1)
