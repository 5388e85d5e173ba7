"""The estimate and the information of the accumulated motion (effective variance, ``crlb``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.initialize import initialize
from coreg_ros.core.estimator import noise_covariance
from coreg_ros.core.live.guidance.keys import GROUPS, is_rotation_group
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.planning.crlb import CRLB_DIMENSION, model_jacobians
from coreg_ros.core.types import CalibrationResult
import numpy as np

#: Re-linearise (rebuild the information) when T0's rotation estimate moves by more (rad).
RELINEARISE_ROTATION = np.deg2rad(2.0)
#: ... or a marker position estimate moves by more (m).
RELINEARISE_MARKER = 0.005
#: Weak prior that keeps the information invertible before the motion determines everything:
#: σ of a position (m), a rotation (rad) and the clock offset (s). A σ near these is "not yet
#: determined".
WEAK_PRIOR = (1.0, 1.0, 1.0)
#: Pairs linearised at once.
CHUNK = 4096
# --------------------------------------------------------------------------- the estimate


@dataclass(frozen=True)
class Estimate:
    """
    The calibration the information is evaluated at.

    Attributes
    ----------
    model : str
    p0 : ndarray, shape (3,)
        T0 position (A's base in B's base), m.
    q0 : ndarray, shape (4,)
        T0 orientation (w, x, y, z).
    markers : ndarray, shape (k, 3)
        Marker position(s) in A's tool frame, m (k = 3 for three markers).
    q1 : ndarray, shape (4,)
        T1 orientation (w, x, y, z); the identity where the model does not estimate it.

    """

    model: str
    p0: np.ndarray
    q0: np.ndarray
    markers: np.ndarray
    q1: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))

    @classmethod
    def from_parameters(cls, params: Parameters) -> Estimate:
        """From the estimator's parameters."""
        return cls(params.spec.name, params.p0.copy(), quat.canonical(params.q0),
                   params.markers.copy(), quat.canonical(params.q1))

    @classmethod
    def from_result(cls, result: CalibrationResult) -> Estimate:
        """From a calibration result."""
        return cls(result.model, np.asarray(result.base_to_base.position, dtype=float),
                   np.asarray(result.base_to_base.quat_wxyz, dtype=float),
                   np.atleast_2d(np.asarray(result.markers, dtype=float)),
                   np.asarray(result.tool_to_marker.quat_wxyz, dtype=float))

    @classmethod
    def from_pairs(cls, model: str, pairs) -> Estimate:
        """
        Closed-form estimate from pairs (``initialize``: no guess needed).

        Parameters
        ----------
        model : str
            Measurement model name.
        pairs : Pairs or PairBatch
            Paired samples of A and B.

        """
        spec = SPECS[model]
        params = initialize(spec, np.asarray(pairs.pos_a, dtype=float),
                            np.asarray(pairs.quat_a, dtype=float),
                            np.asarray(pairs.pos_b, dtype=float),
                            None if pairs.quat_b is None or not spec.has_q1
                            else np.asarray(pairs.quat_b, dtype=float))
        return cls.from_parameters(params)

    def moved_from(self, other: Estimate) -> bool:
        """Whether the Jacobians at ``self`` differ enough from those at ``other``."""
        angle = float(quat.angle_between(self.q0, other.q0))
        shift = float(np.max(np.linalg.norm(self.markers - other.markers, axis=1)))
        return angle > RELINEARISE_ROTATION or shift > RELINEARISE_MARKER


# --------------------------------------------------------------------------- information


def device_covariances(model: str, sigma_a, sigma_b) -> tuple[np.ndarray, np.ndarray]:
    """
    Noise covariances in the ``crlb`` tangents: A (6×6) and B's measurement (m×m).

    Parameters
    ----------
    model : str
        Measurement model name (sets B's measurement size m).
    sigma_a, sigma_b : (float, float) or DeviceNoise
        Noise standard deviations (position m, rotation rad), or full covariances
        (``noise_model.noise_covariance`` takes either).

    """
    cov_a = noise_covariance(sigma_a)
    cov_b6 = noise_covariance(sigma_b)
    if model == 'full_pose':
        return cov_a, cov_b6
    k = 3 if model == 'three_marker' else 1
    return cov_a, np.kron(np.eye(k), cov_b6[0:3, 0:3])


def jacobians(estimate: Estimate, pos_a: np.ndarray, quat_a: np.ndarray,
              velocity: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """
    B's measurement Jacobians with respect to (ψ[, τ]) and to A's pose.

    Parameters
    ----------
    estimate : Estimate
        The calibration the Jacobians are evaluated at.
    pos_a, quat_a : ndarray, shapes (n, 3), (n, 4)
        A's tool poses.
    velocity : ndarray, shape (n, 6), optional
        A's velocity; when given, the offset's column ``c = -F_x ẋ_A`` is appended (τ: B's
        clock minus A's; the measurement at B stamp t is A's pose at t - τ).

    Returns
    -------
    f : ndarray, shape (n, m, d) or (n, m, d + 1)
    f_x : ndarray, shape (n, m, 6)

    """
    f_psi, f_x = model_jacobians(estimate.model, estimate.p0, estimate.q0, estimate.markers,
                                 pos_a, quat_a)
    if velocity is None:
        return f_psi, f_x
    c = -np.einsum('nmk,nk->nm', f_x, velocity)
    return np.concatenate([f_psi, c[:, :, None]], axis=2), f_x


def effective_covariance(f_x: np.ndarray, cov_a: np.ndarray, cov_b: np.ndarray,
                         scale: Optional[np.ndarray], tls: bool) -> np.ndarray:
    """Σ_b + s F_x Σ_a F_xᵀ per pair, shape (n, m, m) (Σ_b alone, broadcast, without TLS)."""
    n = f_x.shape[0]
    if not tls:
        return np.broadcast_to(cov_b, (n,) + cov_b.shape)
    m = f_x @ cov_a @ np.swapaxes(f_x, 1, 2)
    if scale is not None:
        m = m * np.asarray(scale, dtype=float)[:, None, None]
    return m + cov_b


def information(estimate: Estimate, pos_a, quat_a, velocity, cov_a, cov_b,
                scale: Optional[np.ndarray] = None, tls: bool = True) -> np.ndarray:
    """
    Information of ψ (and τ when ``velocity`` is given) carried by pairs, (D, D).

    Parameters
    ----------
    estimate : Estimate
        The calibration the information is evaluated at.
    pos_a, quat_a : ndarray, shapes (N, 3), (N, 4)
        A's tool poses.
    velocity : ndarray, shape (N, 6) or None
        A's velocity (None: τ is not estimated).
    cov_a, cov_b : ndarray
        ``device_covariances``.
    scale : ndarray, shape (N,), optional
        ``a_var_scale``.
    tls : bool
        A's noise enters (errors in both devices); False: B's noise only (OLS).

    """
    d = CRLB_DIMENSION[estimate.model] + (0 if velocity is None else 1)
    out = np.zeros((d, d))
    n = len(pos_a)
    for start in range(0, n, CHUNK):
        sl = slice(start, min(n, start + CHUNK))
        f, f_x = jacobians(estimate, pos_a[sl], quat_a[sl],
                           None if velocity is None else velocity[sl])
        m = effective_covariance(f_x, cov_a, cov_b, None if scale is None else scale[sl], tls)
        out += np.einsum('nmi,nmj->ij', f, np.linalg.solve(m, f))
    return 0.5 * (out + out.T)


def _weak_prior(model: str, with_time: bool) -> np.ndarray:
    groups = GROUPS[model]
    diag = []
    for g in groups:
        s = WEAK_PRIOR[1] if is_rotation_group(g) else WEAK_PRIOR[0]
        diag += [s ** -2] * 3
    if with_time:
        diag.append(WEAK_PRIOR[2] ** -2)
    return np.diag(diag)


def sigma_groups(model: str, cov: np.ndarray, with_time: bool) -> dict:
    """
    σ per group from a covariance over (ψ[, τ]).

    Returns
    -------
    dict of str to ndarray
        Each group of ``GROUPS[model]`` → σ per axis, shape (3,) (m or rad); ``time_offset``
        → shape (1,) (s) when ``with_time``.

    """
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out = {g: sd[3 * i:3 * i + 3].copy() for i, g in enumerate(GROUPS[model])}
    if with_time:
        out['time_offset'] = sd[-1:].copy()
    return out
