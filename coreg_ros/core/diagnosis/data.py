"""
The data a diagnosis works on: pairs, the noise covariances, A's trajectory and its velocity.

Everything here is derived once from the pairs (and, when given, device A's full stream) and
never changes while candidate effects are fitted.

Time is float seconds from the first paired B stamp (``t``); this is the one place where stamps
become float seconds, only to model effects that are smooth in time (offsets, drift).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.clock.trajectory import Trajectory
from coreg_ros.core.estimator import noise_covariance, output_covariance
from coreg_ros.core.models import ModelSpec, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import Pairs, PoseStream
import numpy as np


@dataclass(eq=False)
class DiagData:
    """
    Pairs prepared for the diagnosis.

    Attributes
    ----------
    spec : ModelSpec
    stamps : ndarray of int64, shape (N,)
        Paired B stamps, ns.
    t : ndarray, shape (N,)
        Seconds since the first paired stamp.
    pos_a, quat_a : ndarray, shapes (N, 3), (N, 4)
        A's tool pose at the pairs, in A's base frame.
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
        B's marker position(s) in B's base frame, m.
    quat_b : ndarray, shape (N, 4) or None
    a_scale : ndarray, shape (N,)
        Factor on A's noise variance per pair (interpolation).
    cov_a : ndarray, shape (6, 6)
        Covariance of A's input noise over (p_A, δ_A), δ_A the rotation vector of the
        perturbation ``q_A ← Exp(δ_A) ⊗ q_A`` (ROS layout; the models' ``J_x`` is with
        respect to δ_A itself, not to the half-angle metric).
    cov_b : ndarray, shape (m, m)
        Metric covariance of B's output noise.
    trajectory : Trajectory
        A's pose as a function of pair time (for time-shift effects).
    vel, omega : ndarray, shape (N, 3)
        A's linear (m/s) and angular (rad/s) velocity at the pairs, A's base frame.
    sigma_a, sigma_b : tuple of float
        Stated noise (position m, rotation rad).

    """

    spec: ModelSpec
    stamps: np.ndarray
    t: np.ndarray
    pos_a: np.ndarray
    quat_a: np.ndarray
    pos_b: np.ndarray
    quat_b: Optional[np.ndarray]
    a_scale: np.ndarray
    cov_a: np.ndarray
    cov_b: np.ndarray
    trajectory: Trajectory
    vel: np.ndarray
    omega: np.ndarray
    sigma_a: tuple
    sigma_b: tuple
    cache: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Return the number of pairs."""
        return int(self.t.shape[0])

    @property
    def m(self) -> int:
        """Residuals per pair."""
        return self.spec.n_res

    @property
    def b_points(self) -> np.ndarray:
        """B's measured marker positions, shape (N, k, 3), m."""
        return self.pos_b[:, None, :] if self.pos_b.ndim == 2 else self.pos_b

    @property
    def speed(self) -> np.ndarray:
        """A's tool speed, m/s, shape (N,)."""
        return np.linalg.norm(self.vel, axis=1)

    @property
    def angular_speed(self) -> np.ndarray:
        """A's tool angular speed, rad/s, shape (N,)."""
        return np.linalg.norm(self.omega, axis=1)

    def subset(self, idx: np.ndarray) -> DiagData:
        """Restrict the data to the pairs idx (the trajectory is kept whole)."""
        return DiagData(self.spec, self.stamps[idx], self.t[idx], self.pos_a[idx],
                        self.quat_a[idx], self.pos_b[idx],
                        None if self.quat_b is None else self.quat_b[idx], self.a_scale[idx],
                        self.cov_a, self.cov_b, self.trajectory, self.vel[idx],
                        self.omega[idx], self.sigma_a, self.sigma_b)


def prepare(pairs: Pairs, settings: Settings, stream_a: Optional[PoseStream] = None,
            cov_a: Optional[np.ndarray] = None, cov_b: Optional[np.ndarray] = None) -> DiagData:
    """
    Build the diagnosis data from pairs (and optionally A's whole stream).

    Parameters
    ----------
    pairs : Pairs
        As made by ``pairing.pair_for`` with ``settings``.
    settings : Settings
        Model and stated noise; ``time_offset`` is the offset the pairs were made with.
    stream_a : PoseStream, optional
        Device A's stream, for re-evaluating A at shifted times and for velocities; the pairs'
        own A poses are used when it is None.
    cov_a, cov_b : ndarray, shape (6, 6), optional
        Full noise covariances (ROS layout) overriding the settings' sigmas.

    Returns
    -------
    DiagData

    """
    spec = SPECS[settings.model]
    stamps = np.asarray(pairs.stamps, dtype=np.int64)
    origin = int(stamps[0])
    t = (stamps - np.int64(origin)).astype(float) * 1e-9
    if stream_a is not None and len(stream_a) >= 2:
        # A's clock plus the offset used in pairing puts A on the pairs' time axis
        t_src = ((np.asarray(stream_a.stamps, dtype=np.int64) - np.int64(origin)
                  + np.int64(settings.time_offset_ns)).astype(float) * 1e-9)
        traj = Trajectory(t_src, stream_a.position, quat.canonical(
            np.asarray(stream_a.quat_wxyz, dtype=float)
            / np.linalg.norm(stream_a.quat_wxyz, axis=1, keepdims=True)))
    else:
        traj = Trajectory(t, pairs.pos_a, pairs.quat_a)
    vel, omega = traj.velocity(t)
    cov_a = noise_covariance(settings.sigma_a) if cov_a is None else cov_a
    cov_b = noise_covariance(settings.sigma_b) if cov_b is None else cov_b
    n = len(pairs)
    a_scale = (np.ones(n) if pairs.a_var_scale is None
               else np.asarray(pairs.a_var_scale, dtype=float))
    quat_b = None if pairs.quat_b is None or not spec.has_q1 else np.asarray(pairs.quat_b, float)
    return DiagData(spec=spec, stamps=stamps, t=t, pos_a=np.asarray(pairs.pos_a, float),
                    quat_a=np.asarray(pairs.quat_a, float),
                    pos_b=np.asarray(pairs.pos_b, float), quat_b=quat_b, a_scale=a_scale,
                    cov_a=np.asarray(cov_a, dtype=float).reshape(6, 6),
                    cov_b=output_covariance(cov_b, spec),
                    trajectory=traj, vel=vel, omega=omega,
                    sigma_a=tuple(settings.sigma_a), sigma_b=tuple(settings.sigma_b))


def time_folds(t: np.ndarray, k: int) -> np.ndarray:
    """Fold index (0..k-1) per pair: k contiguous blocks of equal duration."""
    span = max(float(t[-1] - t[0]), 1e-12)
    return np.minimum(((t - t[0]) / span * k).astype(int), k - 1)


def spatial_folds(points: np.ndarray, k: int, cells: int = 4, seed: int = 0) -> np.ndarray:
    """
    Fold index per pair from a grid of cells over the points, cells dealt to k folds at random.

    Every held-out cell is surrounded by training cells, so a smooth spatial model is tested by
    interpolation into unseen parts of the workspace rather than by extrapolation.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Where each pair is (B's first marker), m.
    k : int
        Number of folds.
    cells : int
        Cells per axis.
    seed : int
        Seed of the cells' random deal.

    """
    assign = np.random.default_rng(seed).permutation(cells ** 3) % k
    return assign[grid_cells(points, cells)]


def grid_cells(points: np.ndarray, cells: int) -> np.ndarray:
    """
    Cell index per point of a ``cells``³ grid over the points (1st to 99th percentile).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The points, m.
    cells : int
        Cells per axis; points beyond the percentiles fall in the edge cells.

    Returns
    -------
    ndarray of int, shape (N,)
        In 0 .. cells³ - 1.

    """
    lo = np.percentile(points, 1, axis=0)
    hi = np.percentile(points, 99, axis=0)
    idx = np.clip(((points - lo) / np.maximum(hi - lo, 1e-9) * cells).astype(int), 0, cells - 1)
    return idx[:, 0] * cells * cells + idx[:, 1] * cells + idx[:, 2]
