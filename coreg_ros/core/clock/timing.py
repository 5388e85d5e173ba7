"""
The clock offset between the devices: coarse search, joint Gauss-Newton step, observability.

Ikits' model (eq. 16) extended with time: device B's sample stamped ``t`` on B's clock matches
A at ``t - τ(t)`` on A's clock, with ``τ(t) = τ0 + κ (t - t_mid)`` (κ the clock drift,
dimensionless; reported in ppm).

1. **Coarse search** (any offset within the streams' overlap, up to minutes): the angular
   speed of A's tool and of B's marker are equal under a rigid link whatever T0 and T1 are
   (``|ω_B| = |R0 ω_A|``), so their cross-correlation over lags peaks at τ. For a
   position-only B the speeds of the two points are correlated, not equal; the candidates
   are then told apart by the fit.
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

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.clock.offset_sums import structured_offset_sums
from coreg_ros.core.clock.trajectory import Trajectory
from coreg_ros.core.estimator.linearized import Chunk, chunks, PairData
from coreg_ros.core.estimator.problem import CHUNK
from coreg_ros.core.models import Parameters
from coreg_ros.core.types import PoseStream
import numpy as np
from scipy import fft

#: Largest posterior σ of τ (s) for which τ counts as determined by the motion.
MAX_SIGMA_S = 0.010
#: The velocity signature must carry this many times the information A's noise alone would.
MIN_SIGNAL_TO_NOISE = 4.0
#: Candidates of the coarse search that are refined by the fit.
MAX_CANDIDATES = 3
#: Smallest share of the shorter signal two signals must overlap at a lag.
MIN_OVERLAP_SHARE = 0.3
#: Every how many pairs the noise share of the velocity signature is evaluated.
NOISE_STRIDE = 32
#: Half-width (s) of the central differences of the coarse speed signals.
COARSE_HALF_WINDOW = 0.1
#: Largest number of grid samples of one coarse signal (bounds time and memory).
MAX_GRID = 1 << 16


def query_seconds(stamps_b: np.ndarray, tau0: float, kappa: float, reference_ns: int,
                  origin_ns: int) -> np.ndarray:
    """A-clock times (s from ``origin_ns``) at which B samples stamped ``stamps_b`` match A."""
    rel = (np.asarray(stamps_b, dtype=np.int64) - np.int64(origin_ns)).astype(float) * 1e-9
    since_ref = (np.asarray(stamps_b, dtype=np.int64) - np.int64(reference_ns)).astype(
        float) * 1e-9
    return rel - tau0 - kappa * since_ref


# --------------------------------------------------------------------------- coarse search


def _grid_step(*streams: PoseStream) -> float:
    """Grid step (s) of the coarse signals: the coarser device's interval, bounded."""
    steps = [float(np.median(np.diff(s.stamps))) * 1e-9 for s in streams if len(s) > 1]
    step = max(steps + [0.002])
    span = max(float(s.stamps[-1] - s.stamps[0]) * 1e-9 for s in streams)
    return max(step, span / MAX_GRID)


def _frame_of_markers(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray) -> np.ndarray:
    """Orientation (w, x, y, z) of the frame spanned by three marker positions, (n, 4)."""
    x = p2 - p1
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    z = np.cross(x, p3 - p1)
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    y = np.cross(z, x)
    return quat.from_matrix(np.stack([x, y, z], axis=2))


def _speed(stream_or_streams, origin_ns: int, step: float, angular: bool,
           trajectory: Optional[Trajectory] = None):
    """(start s, speed on a uniform grid): |ω| (rad/s) if ``angular`` else |v| (m/s)."""
    streams = stream_or_streams if isinstance(stream_or_streams, (list, tuple)) else [
        stream_or_streams]
    first = streams[0]
    t = (first.stamps - np.int64(origin_ns)).astype(float) * 1e-9
    grid = np.arange(t[0], t[-1], step)
    # a longer window than the calibration uses: the coarse signal needs the shape of the
    # motion, not its detail, and noisy trackers (a degree of orientation noise) need smoothing
    half = max(1.5 * step, COARSE_HALF_WINDOW)
    if len(streams) == 3:
        trajs = [Trajectory((s.stamps - np.int64(origin_ns)).astype(float) * 1e-9, s.position,
                            np.tile([1.0, 0.0, 0.0, 0.0], (len(s), 1))) for s in streams]
        pts = [tr.pose(grid)[0] for tr in trajs]
        traj = Trajectory(grid, pts[0], _frame_of_markers(*pts))
    else:
        traj = trajectory or Trajectory(t, first.position, first.quat_wxyz)
    v, w = traj.velocity(grid, half, linear=not angular, angular=angular)
    return grid, np.linalg.norm(w if angular else v, axis=1)


def _windowed_correlation(a: np.ndarray, b: np.ndarray, min_overlap: int):
    """
    Pearson correlation of a[i] with b[i + k] over the overlap, for every lag k.

    Returns
    -------
    lags : ndarray of int, shape (La + Lb - 1,)
    r : ndarray, shape (La + Lb - 1,)
        -inf where the overlap is shorter than ``min_overlap``.
    overlap : ndarray, shape (La + Lb - 1,)
        Overlap as a share of the shorter signal.

    """
    la, lb = len(a), len(b)
    nfft = fft.next_fast_len(la + lb - 1)
    xc = fft.irfft(np.conj(fft.rfft(a, nfft)) * fft.rfft(b, nfft), nfft)
    lags = np.arange(-(la - 1), lb)
    sab = xc[lags % nfft]
    i0 = np.maximum(0, -lags)
    i1 = np.minimum(la, lb - lags)
    n = (i1 - i0).astype(float)
    ca = np.concatenate([[0.0], np.cumsum(a)])
    ca2 = np.concatenate([[0.0], np.cumsum(a * a)])
    cb = np.concatenate([[0.0], np.cumsum(b)])
    cb2 = np.concatenate([[0.0], np.cumsum(b * b)])
    sa, sa2 = ca[i1] - ca[i0], ca2[i1] - ca2[i0]
    sb, sb2 = cb[i1 + lags] - cb[i0 + lags], cb2[i1 + lags] - cb2[i0 + lags]
    var = (n * sa2 - sa * sa) * (n * sb2 - sb * sb)
    with np.errstate(invalid='ignore', divide='ignore'):
        r = (n * sab - sa * sb) / np.sqrt(np.where(var > 0, var, np.nan))
    r = np.where((n >= min_overlap) & np.isfinite(r), r, -np.inf)
    return lags, r, n / min(la, lb)


def coarse_offsets(stream_a: PoseStream, streams_b: Sequence[PoseStream], *,
                   angular: bool, max_candidates: int = MAX_CANDIDATES,
                   trajectory_a: Optional[Trajectory] = None) -> list:
    """
    Candidate offsets τ (s) from the cross-correlation of the devices' speeds, best first.

    Parameters
    ----------
    stream_a : PoseStream
        Device A (validated: increasing stamps, unit quaternions).
    streams_b : sequence of PoseStream
        Device B: one stream, or three marker streams (their triangle gives an orientation).
    angular : bool
        Correlate angular speeds (B has an orientation, or three markers) rather than the
        speeds of the tool and marker origins (position-only B).
    max_candidates : int
        Largest number of candidate offsets returned.
    trajectory_a : Trajectory, optional
        A's trajectory on its own clock, seconds from its first stamp, if already built.

    Returns
    -------
    list of (float, float)
        (τ s, correlation) of the highest local maxima, refined to a fraction of the grid
        step by a parabola through the peak.

    """
    streams_b = list(streams_b)
    step = _grid_step(stream_a, *streams_b)
    if min(len(stream_a), len(streams_b[0])) < 4:
        return []
    ta, a = _speed(stream_a, int(stream_a.stamps[0]), step, angular, trajectory_a)
    b_arg = streams_b if len(streams_b) == 3 else streams_b[0]
    tb, b = _speed(b_arg, int(streams_b[0].stamps[0]), step, angular)
    if len(a) < 8 or len(b) < 8 or np.std(a) == 0 or np.std(b) == 0:
        return []
    min_overlap = max(8, int(MIN_OVERLAP_SHARE * min(len(a), len(b))))
    lags, r, overlap = _windowed_correlation(a - a.mean(), b - b.mean(), min_overlap)
    inner = (r[1:-1] >= r[:-2]) & (r[1:-1] > r[2:]) & np.isfinite(r[1:-1])
    peaks = np.flatnonzero(inner) + 1
    if peaks.size == 0:
        return []
    # a peak over a short overlap is a weaker witness: rank by r·√(overlap share)
    strength = r[peaks] * np.sqrt(overlap[peaks])
    peaks = peaks[np.argsort(strength)[::-1][:max_candidates]]
    base = float(int(streams_b[0].stamps[0]) - int(stream_a.stamps[0])) * 1e-9
    base += float(tb[0] - ta[0])
    out = []
    for k in peaks:
        y0, y1, y2 = r[k - 1], r[k], r[k + 1]
        curve = y0 - 2 * y1 + y2
        frac = 0.5 * (y0 - y2) / curve if curve < 0 and np.isfinite(y0 + y2) else 0.0
        out.append((base + (lags[k] + float(np.clip(frac, -0.5, 0.5))) * step, float(y1)))
    return out


def offsets_by_block(stream_a: PoseStream, streams_b: Sequence[PoseStream], *, angular: bool,
                     n_blocks: int = 6) -> list:
    """
    Find the best coarse offset of each of ``n_blocks`` consecutive time blocks of B.

    Returns
    -------
    list of (float, float, float)
        (start s, end s, τ s) per block with a candidate, times from B's first stamp.

    """
    first = streams_b[0]
    edges = np.linspace(0, len(first), n_blocks + 1).astype(int)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        if hi - lo < 16:
            continue
        block = [PoseStream(first.stamps[lo:hi], first.position[lo:hi],
                            first.quat_wxyz[lo:hi], first.frame_id)] + list(streams_b[1:])
        found = coarse_offsets(stream_a, block, angular=angular, max_candidates=1)
        if found:
            t0 = float(first.stamps[lo] - first.stamps[0]) * 1e-9
            t1 = float(first.stamps[hi - 1] - first.stamps[0]) * 1e-9
            out.append((t0, t1, found[0][0]))
    return out


def clock_step(blocks: list, tolerance_s: float) -> Optional[str]:
    """
    Describe a clock step in the blocks' offsets, or return None.

    A step: the earlier blocks agree with each other, the later blocks too, and the two runs
    differ by more than ``tolerance_s``.
    """
    taus = np.array([b[2] for b in blocks])
    for k in range(1, len(taus)):
        before, after = taus[:k], taus[k:]
        if (np.ptp(before) < tolerance_s and np.ptp(after) < tolerance_s
                and abs(np.median(after) - np.median(before)) > tolerance_s):
            return (f'the clock offset changes from {np.median(before):.3f} s to '
                    f'{np.median(after):.3f} s between {blocks[k - 1][1]:.1f} s and '
                    f'{blocks[k][0]:.1f} s into the recording (a clock step): split the '
                    f'recording there (coreg fix-bag BAG NEW_BAG --split-at-jump S) and '
                    f'calibrate each part')
    return None


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
                prior_information: Optional[np.ndarray] = None) -> OffsetStep:
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
                        None)
    if step.cov is None:
        step = _offset_step(params, data, velocity, since_ref, param_cov, noise_velocity_cov,
                            np.zeros_like(param_cov) if prior_information is None
                            else prior_information)
    return step


def _offset_step(params, data, velocity, since_ref, param_cov, noise_velocity_cov,
                 own_information: Optional[np.ndarray]) -> OffsetStep:
    """``offset_step`` with H⁻¹ = param_cov, or from the pairs (+ ``own_information``)."""
    k = 1 if since_ref is None else 2
    P = param_cov.shape[0]
    lam, vec = np.linalg.eigh(noise_velocity_cov)
    noise_factor = vec * np.sqrt(np.clip(lam, 0.0, None))  # Σ_v = F Fᵀ
    h_pp = None if own_information is None else own_information.copy()
    sums = None
    if h_pp is None:
        sums = structured_offset_sums(params, data, velocity, since_ref)
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
