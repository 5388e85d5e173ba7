"""
The clock offset between the devices: coarse search, joint Gauss-Newton step, observability.

Ikits' model (eq. 16) extended with time: device B's sample stamped ``t`` on B's clock matches
A at ``t - τ(t)`` on A's clock, with ``τ(t) = τ0 + κ (t - t_mid)`` (κ the clock drift,
dimensionless; reported in ppm).

1. **Coarse search** (``coarse``, any offset within the streams' overlap, whatever the
   stamps): the devices' speeds cross-correlated over lags peak at τ.
2. **Joint step**: with φ at its optimum for the current τ, the offset's column per pair is
   ``c = -F_x ẋ_A`` (``linearized``). Eliminating φ (Schur complement on the information of
   φ, priors included) gives τ's information ``S = h_ττ - h_φτᵀ H⁻¹ h_φτ``, the step
   ``δτ = -S⁻¹ Σ cᵀ W e`` and ``dφ/dτ = -H⁻¹ h_φτ``. The covariance of φ with τ marginalised
   is ``H⁻¹ + (dφ/dτ) S⁻¹ (dφ/dτ)ᵀ``: the transforms carry τ's uncertainty.
3. **Observability**: τ is determined only if the motion's velocity signature is well above
   what A's noise alone would put into the finite-difference velocity, and S leaves τ a
   useful σ; otherwise the given value is kept and the reason is said.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.clock.coarse import (  # noqa: F401 (importers of its first home)
    clock_step,
    coarse_offsets,
    MAX_CANDIDATES,
    offsets_by_block,
    speed_correlation,
    SpeedCorrelation,
)
from coreg_ros.core.clock.offset_sums import structured_offset_sums
from coreg_ros.core.clock.trajectory import Trajectory
from coreg_ros.core.estimator.linearized import Chunk, chunks, PairData
from coreg_ros.core.estimator.problem import CHUNK
from coreg_ros.core.models import Parameters
import numpy as np

#: Largest posterior σ of τ (s) for which τ counts as determined by the motion.
MAX_SIGMA_S = 0.010
#: The velocity signature must carry this many times the information A's noise alone would.
MIN_SIGNAL_TO_NOISE = 4.0
#: Every how many pairs the noise share of the velocity signature is evaluated.
NOISE_STRIDE = 32
#: Longest half window (s) of A's velocity in the offset step: where A's stated noise
#: dominates the short window's velocity, the window is doubled up to this (human and robot
#: motions keep their shape over it; a still recording stays at its noise at every window).
MAX_VELOCITY_HALF_WINDOW = 0.8
#: A longer window is used once its velocity carries this many times the information A's
#: noise alone would (the noise inflates τ's information by its share).
LONG_WINDOW_SIGNAL_TO_NOISE = 16.0


def query_seconds(stamps_b: np.ndarray, tau0: float, kappa: float, reference_ns: int,
                  origin_ns: int) -> np.ndarray:
    """A-clock times (s from ``origin_ns``) at which B samples stamped ``stamps_b`` match A."""
    rel = (np.asarray(stamps_b, dtype=np.int64) - np.int64(origin_ns)).astype(float) * 1e-9
    since_ref = (np.asarray(stamps_b, dtype=np.int64) - np.int64(reference_ns)).astype(
        float) * 1e-9
    return rel - tau0 - kappa * since_ref


# --------------------------------------------------------------------------- joint step


@dataclass(frozen=True)
class OffsetStep:
    """
    The time parameters' Gauss-Newton step at a fitted φ, and what it says about τ.

    Attributes
    ----------
    delta : ndarray, shape (k,)
        Step of (τ0[, κ]) (s, dimensionless).
    cov : ndarray, shape (k, k) or None
        Covariance of (τ0[, κ]) with φ eliminated (S⁻¹); None if S is not positive.
    dphi : ndarray, shape (P, k)
        dφ/d(τ0[, κ]) = -H⁻¹ h_φτ.
    signal_to_noise : float
        h_ττ over what A's noise alone would contribute through the finite differences.

    """

    delta: np.ndarray
    cov: Optional[np.ndarray]
    dphi: np.ndarray
    signal_to_noise: float

    @property
    def sigma(self) -> float:
        """Posterior σ of τ0, s (inf when not determined)."""
        return float('inf') if self.cov is None else float(np.sqrt(self.cov[0, 0]))

    def determined(self) -> tuple[bool, str]:
        """Whether the motion determines τ, and if not, why (one phrase)."""
        if self.signal_to_noise < MIN_SIGNAL_TO_NOISE:
            return False, ('the recording is (nearly) still: its velocity is at the level of '
                           "A's noise")
        if self.cov is None or not self.sigma < MAX_SIGMA_S:
            return False, (f'the motion leaves τ a σ of {self.sigma * 1e3:.3g} ms (over '
                           f'{MAX_SIGMA_S * 1e3:g} ms): nearly constant velocity, whose shift '
                           f'in time the transforms absorb')
        return True, ''

    def marginal_cov(self, param_cov: np.ndarray) -> np.ndarray:
        """Covariance of φ with the time parameters marginalised (P×P)."""
        if self.cov is None:
            return param_cov
        return param_cov + self.dphi @ self.cov @ self.dphi.T


def velocity_noise_cov(cov_a: np.ndarray, half: float) -> np.ndarray:
    """
    Covariance (6×6, m/s and rad/s) that A's noise puts into a central-difference velocity.

    ``(x(t+h) - x(t-h)) / 2h`` of two independent samples has variance ``2 Σ / (2h)²``, with
    Σ = ``cov_a`` A's noise in the ROS layout (position m², rotation angle rad²).
    """
    return np.asarray(cov_a, dtype=float).reshape(6, 6) * (2.0 / (2.0 * half) ** 2)


def offset_step(params: Parameters, data: PairData, velocity: np.ndarray,
                since_ref: Optional[np.ndarray], param_cov: np.ndarray,
                noise_velocity_cov: np.ndarray,
                prior_information: Optional[np.ndarray] = None,
                ready: Optional[Callable[[int], None]] = None) -> OffsetStep:
    """
    Gauss-Newton step of the time parameters with φ eliminated.

    Parameters
    ----------
    params : Parameters
        φ fitted at the current τ (its gradient is zero there).
    data : PairData
        The pairs used by the fit (inliers), paired at the current τ.
    velocity : ndarray, shape (N, 6)
        A's linear (m/s) and angular velocity (rad/s, A's base frame, left perturbation) at
        the A times of the pairs.
    since_ref : ndarray, shape (N,), optional
        ``t_B - t_mid`` (s) per pair when the drift κ is estimated too.
    param_cov : ndarray, shape (P, P)
        H⁻¹, the posterior covariance of φ at fixed τ (priors included).
    noise_velocity_cov : ndarray, shape (6, 6)
        What A's noise alone puts into ``velocity`` (``velocity_noise_cov``).
    prior_information : ndarray, shape (P, P), optional
        JᵀJ of the prior rows at φ, for the fallback below.
    ready : callable, optional
        ``ready(stop)`` waits until the rows of ``velocity`` before ``stop`` are written
        (``Trajectory.velocity_arriving``); None: all are.

    Returns
    -------
    OffsetStep

    Notes
    -----
    φ is eliminated with the estimator's own H (TLS: its Schur complement), the τ blocks come
    from the per-pair effective covariance. When large input noise makes the two differ
    enough that S is not positive, φ is eliminated with the effective-covariance H of the
    same linearisation instead (one more pass), which is positive by construction.

    """
    step = _offset_step(params, data, velocity, since_ref, param_cov, noise_velocity_cov,
                        None, ready)
    if step.cov is None:
        step = _offset_step(params, data, velocity, since_ref, param_cov, noise_velocity_cov,
                            np.zeros_like(param_cov) if prior_information is None
                            else prior_information)
    return step


def _offset_step(params, data, velocity, since_ref, param_cov, noise_velocity_cov,
                 own_information: Optional[np.ndarray], ready=None) -> OffsetStep:
    """``offset_step`` with H⁻¹ = param_cov, or from the pairs (+ ``own_information``)."""
    k = 1 if since_ref is None else 2
    P = param_cov.shape[0]
    lam, vec = np.linalg.eigh(noise_velocity_cov)
    noise_factor = vec * np.sqrt(np.clip(lam, 0.0, None))  # Σ_v = F Fᵀ
    h_pp = None if own_information is None else own_information.copy()
    sums = None
    if h_pp is None:
        sums = structured_offset_sums(params, data, velocity, since_ref, ready)
    if ready is not None:
        ready(len(velocity))  # every row, for what follows
    if sums is not None:  # closed form (offset_sums); the noise share on the generic path
        h_tt, h_pt, g_t = sums
        noise_tt = _velocity_noise(params, data, velocity, noise_factor)
    else:
        h_tt, h_pt, g_t, noise_tt = _generic_sums(params, data, velocity, since_ref, k, P,
                                                  h_pp, noise_factor)
    h_inv = param_cov
    if h_pp is not None:
        try:
            h_inv = np.linalg.inv(0.5 * (h_pp + h_pp.T))
        except np.linalg.LinAlgError:
            h_inv = param_cov
    S = h_tt - h_pt.T @ h_inv @ h_pt
    S = 0.5 * (S + S.T)
    dphi = -h_inv @ h_pt
    snr = float(h_tt[0, 0] / noise_tt) if noise_tt > 0 else float('inf')
    try:
        np.linalg.cholesky(S)
        cov = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return OffsetStep(np.zeros(k), None, dphi, snr)
    return OffsetStep(-cov @ g_t, cov, dphi, snr)


def velocity_step(trajectory: Trajectory, t_a: np.ndarray, half: float,
                  max_gap: Optional[float], params: Parameters, data: PairData,
                  since_ref: Optional[np.ndarray], param_cov: np.ndarray, cov_a: np.ndarray,
                  prior_information: Optional[np.ndarray] = None) -> tuple[OffsetStep, float]:
    """
    Make the offset step with A's velocity over the shortest window that shows the motion.

    The stillness test judges the motion recorded: a velocity at the level of A's stated
    noise over the window ``half`` may be a clear motion over a longer one (noisy trackers,
    low rates), while white noise stays at its level at every window. The window is doubled
    up to ``MAX_VELOCITY_HALF_WINDOW`` until its velocity carries
    ``LONG_WINDOW_SIGNAL_TO_NOISE`` times what A's noise alone would; if none does, the step
    over ``half`` is returned (and says the recording is still).

    Parameters
    ----------
    trajectory : Trajectory
        A's tool poses on A's clock (s from its origin).
    t_a : ndarray, shape (N,)
        The pairs' A-clock times, s on the trajectory's axis.
    half : float
        The first half window, s.
    max_gap : float, optional
        Longest gap between A samples a window may span, s (``Trajectory.velocity``).
    params, data, since_ref, param_cov, prior_information
        As ``offset_step``.
    cov_a : ndarray, shape (6, 6)
        A's noise covariance, ROS layout.

    Returns
    -------
    step : OffsetStep
    half : float
        The half window (s) of the velocity the step was made with.

    """
    def step_over(h):
        velocity = np.empty((len(t_a), 6))  # [v | w], written in place (92 MB at 2M pairs)
        # made in a second thread while the step's sums read the rows already made
        ready = trajectory.velocity_arriving(t_a, h, max_gap, velocity)
        return offset_step(params, data, velocity, since_ref, param_cov,
                           velocity_noise_cov(cov_a, h), prior_information, ready=ready)

    step, used = step_over(half), half
    longer = half
    while step.signal_to_noise < MIN_SIGNAL_TO_NOISE and 2.0 * longer <= MAX_VELOCITY_HALF_WINDOW:
        longer *= 2.0
        candidate = step_over(longer)
        if candidate.cov is not None and candidate.signal_to_noise >= LONG_WINDOW_SIGNAL_TO_NOISE:
            step, used = candidate, longer
    return step, used


def _generic_sums(params, data, velocity, since_ref, k: int, P: int,
                  h_pp: Optional[np.ndarray], noise_factor: np.ndarray) -> tuple:
    """
    h_ττ, h_φτ, g_τ and the noise share from every pair's Jacobians (``linearized``).

    Any model and noise; with ``h_pp`` (P×P, updated in place) also Σ J_φᵀ W J_φ.
    """
    h_tt = np.zeros((k, k))
    h_pt = np.zeros((P, k))
    g_t = np.zeros(k)
    noise_tt = 0.0
    for ch in chunks(params, data):
        c = -np.einsum('nij,nj->ni', ch.j_x, velocity[ch.sl])
        cols = c[:, :, None] if k == 1 else np.stack(
            [c, c * since_ref[ch.sl, None]], axis=2)
        if h_pp is None:
            wc = ch.weighted(cols)
        else:
            w = ch.weighted(np.concatenate([cols, ch.j_phi], axis=2))
            wc = w[:, :, :k]
            h_pp += np.einsum('nmp,nmq->pq', ch.j_phi, w[:, :, k:])
        h_tt += np.einsum('nmi,nmj->ij', cols, wc)
        h_pt += np.einsum('nmp,nmk->pk', ch.j_phi, wc)
        g_t += np.einsum('nm,nmk->k', ch.e, wc)
        noise_tt += _noise_share(ch, velocity[ch.sl], noise_factor)
    return h_tt, h_pt, g_t, noise_tt


def _noise_share(ch: Chunk, velocity: np.ndarray, noise_factor: np.ndarray) -> float:
    """
    NOISE_STRIDE Σ tr(Σ⁻¹ F_x Σ_v F_xᵀ) over every NOISE_STRIDE-th pair of the chunk.

    Only the pairs whose velocity is known count; only a threshold depends on it.
    """
    pick = np.arange(0, ch.j_x.shape[0], NOISE_STRIDE)
    pick = pick[np.any(velocity[pick] != 0.0, axis=1)]
    jl = ch.j_x[pick] @ noise_factor
    sub = Chunk(ch.sl, ch.e, ch.j_phi, ch.j_x, ch.cov if ch.cov.ndim == 2 else ch.cov[pick])
    return NOISE_STRIDE * float(np.einsum('nmk,nmk->', jl, sub.weighted(jl)))


def _velocity_noise(params, data: PairData, velocity: np.ndarray,
                    noise_factor: np.ndarray) -> float:
    """Return the noise share of ``_generic_sums`` alone, linearising only the pairs it uses."""
    noise_tt = 0.0
    for start in range(0, len(data), CHUNK):
        idx = np.arange(start, min(start + CHUNK, len(data)), NOISE_STRIDE)
        idx = idx[np.any(velocity[idx] != 0.0, axis=1)]
        if not idx.size:
            continue
        (ch,) = chunks(params, data.take(idx), chunk=idx.size)
        jl = ch.j_x @ noise_factor
        noise_tt += NOISE_STRIDE * float(np.einsum('nmk,nmk->', jl, ch.weighted(jl)))
    return noise_tt
