"""
The coarse clock offset: the devices' speeds cross-correlated over every lag where they overlap.

The angular speed of A's tool and of B's marker are equal under a rigid link whatever T0 and
T1 are (``|ω_B| = |R0 ω_A|``), so their cross-correlation over lags peaks at τ, any offset
within the streams' overlap (minutes or hours, boot against epoch time: each device's signal is
sampled from its own first stamp). For a position-only B the speeds of the two points are
correlated, not equal; the candidates are then told apart by the fit.

The main peak on its own (``main_peak``): where the fine step (``timing.offset_step``) cannot
pin τ (nearly constant velocity, a motion at the level of the stated noise), the coarse lag is
used when its peak is clear (``offset_search``: its fit beats the fits at every other lag),
with a σ that covers the peak's half width: the peak cannot say more than where it is and how
broad it is. Two devices whose stamps never overlap cannot be paired at all without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.clock.trajectory import Trajectory
from coreg_ros.core.types import PoseStream
import numpy as np
from scipy import fft

#: Candidates of the coarse search that are refined by the fit.
MAX_CANDIDATES = 3
#: Smallest share of the shorter signal two signals must overlap at a lag.
MIN_OVERLAP_SHARE = 0.3
#: Half-width (s) of the central differences of the coarse speed signals.
COARSE_HALF_WINDOW = 0.1
#: Largest number of grid samples of one coarse signal (bounds time and memory).
MAX_GRID = 1 << 16
#: Other peaks closer than this many half widths to the main one are part of it.
SAME_PEAK_WIDTHS = 2.0
#: Where a position-only B's marker may sit in A's tool frame, m: the tool's origin and
#: 0.1 m and 0.2 m along each axis either way (markers are mounted within a tool's reach).
LEVER_POINTS = np.vstack([np.zeros(3)] + [s * np.eye(3) for s in (0.1, -0.1, 0.2, -0.2)])


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


@dataclass(frozen=True)
class SpeedCorrelation:
    """
    The devices' speeds cross-correlated over every lag at which they overlap enough.

    Attributes
    ----------
    lags : ndarray of int, shape (L,)
        Lag in grid steps (B's grid shifted against A's).
    r : ndarray, shape (L,)
        Pearson correlation at each lag; -inf where the overlap is too short.
    overlap : ndarray, shape (L,)
        Overlap as a share of the shorter signal.
    step_s : float
        Grid step, s.
    base_s : float
        τ (s) at lag 0: B's grid start minus A's, each on its own clock.

    """

    lags: np.ndarray
    r: np.ndarray
    overlap: np.ndarray
    step_s: float
    base_s: float

    def tau(self, k: int) -> float:
        """τ (s) at index ``k``, refined to a fraction of the step by a parabola through it."""
        y0, y1, y2 = self.r[k - 1], self.r[k], self.r[k + 1]
        curve = y0 - 2 * y1 + y2
        frac = 0.5 * (y0 - y2) / curve if curve < 0 and np.isfinite(y0 + y2) else 0.0
        return self.base_s + (self.lags[k] + float(np.clip(frac, -0.5, 0.5))) * self.step_s

    def peaks(self) -> np.ndarray:
        """Return the indices of the local maxima, strongest first (r·√(overlap share))."""
        r = self.r
        inner = (r[1:-1] >= r[:-2]) & (r[1:-1] > r[2:]) & np.isfinite(r[1:-1])
        peaks = np.flatnonzero(inner) + 1
        # a peak over a short overlap is a weaker witness: rank by r·√(overlap share)
        strength = r[peaks] * np.sqrt(self.overlap[peaks])
        return peaks[np.argsort(strength)[::-1]]


def speed_correlation(stream_a: PoseStream, streams_b: Sequence[PoseStream], *,
                      angular: bool, trajectory_a: Optional[Trajectory] = None
                      ) -> Optional[SpeedCorrelation]:
    """
    Cross-correlate the devices' speeds at every lag where they overlap, whatever the stamps.

    Each device's speed is sampled on a grid from its own first stamp, so two clocks that
    share no stamps (minutes or hours apart, boot time against epoch time) are compared
    like any others. None when a signal is too short or constant. Arguments as
    ``coarse_offsets``.
    """
    streams_b = list(streams_b)
    step = _grid_step(stream_a, *streams_b)
    if min(len(stream_a), len(streams_b[0])) < 4:
        return None
    ta, a = _speed(stream_a, int(stream_a.stamps[0]), step, angular, trajectory_a)
    b_arg = streams_b if len(streams_b) == 3 else streams_b[0]
    tb, b = _speed(b_arg, int(streams_b[0].stamps[0]), step, angular)
    if len(a) < 8 or len(b) < 8 or np.std(a) == 0 or np.std(b) == 0:
        return None
    min_overlap = max(8, int(MIN_OVERLAP_SHARE * min(len(a), len(b))))
    lags, r, overlap = _windowed_correlation(a - a.mean(), b - b.mean(), min_overlap)
    base = float(int(streams_b[0].stamps[0]) - int(stream_a.stamps[0])) * 1e-9
    base += float(tb[0] - ta[0])
    return SpeedCorrelation(lags, r, overlap, step, base)


def lever_speed_correlation(stream_a: PoseStream, stream_b: PoseStream, *,
                            trajectory_a: Optional[Trajectory] = None,
                            points: np.ndarray = LEVER_POINTS) -> Optional[SpeedCorrelation]:
    """
    Cross-correlate a position-only B's speed with the speeds of points of A's tool.

    The marker's speed is ``|v_A + ω_A × R_A p1|`` with its lever p1 unknown: where the
    rotation moves the marker as much as the translation does, the speed of A's tool origin
    correlates poorly with it, at the right lag too. Correlating with the speed of each of
    ``points`` (tool frame, m) and keeping the best at every lag finds the lag at which some
    point of the tool moves as the marker does.

    Returns
    -------
    SpeedCorrelation or None
        Its ``r`` is the largest correlation over the points at each lag.

    """
    step = _grid_step(stream_a, stream_b)
    if min(len(stream_a), len(stream_b)) < 4:
        return None
    origin = int(stream_a.stamps[0])
    t = (stream_a.stamps - np.int64(origin)).astype(float) * 1e-9
    traj = trajectory_a or Trajectory(t, stream_a.position, stream_a.quat_wxyz)
    grid = np.arange(t[0], t[-1], step)
    v, w = traj.velocity(grid, max(1.5 * step, COARSE_HALF_WINDOW))
    rot = quat.to_matrix(traj.pose(grid)[1])
    tb, b = _speed(stream_b, int(stream_b.stamps[0]), step, False)
    if len(grid) < 8 or len(b) < 8 or np.std(b) == 0:
        return None
    best, lags, overlap = None, None, None
    for point in np.asarray(points, dtype=float):
        a = np.linalg.norm(v + np.cross(w, rot @ point), axis=1)
        if np.std(a) == 0:
            continue
        min_overlap = max(8, int(MIN_OVERLAP_SHARE * min(len(a), len(b))))
        lags, r, overlap = _windowed_correlation(a - a.mean(), b - b.mean(), min_overlap)
        best = r if best is None else np.maximum(best, r)
    if best is None:
        return None
    base = float(int(stream_b.stamps[0]) - origin) * 1e-9 + float(tb[0] - grid[0])
    return SpeedCorrelation(lags, best, overlap, step, base)


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
    corr = speed_correlation(stream_a, streams_b, angular=angular, trajectory_a=trajectory_a)
    if corr is None:
        return []
    return [(corr.tau(k), float(corr.r[k])) for k in corr.peaks()[:max_candidates]]


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


# --------------------------------------------------------------------------- the main peak

@dataclass(frozen=True)
class CoarsePeak:
    """
    The main peak of the speeds' correlation.

    Attributes
    ----------
    tau_s : float
        τ (s, B's clock minus A's) at the peak, refined by a parabola through it.
    r : float
        Correlation at the peak.
    sigma_s : float
        Half width of the peak at half its height (at least one grid step), s: a σ that
        covers where the peak could lie.
    runner_up_r : float
        Correlation of the strongest other peak (-inf when there is none).
    runner_up_tau_s : float or None
        τ of that peak, s.

    """

    tau_s: float
    r: float
    sigma_s: float
    runner_up_r: float = -np.inf
    runner_up_tau_s: Optional[float] = None

    def describe(self) -> str:
        """One phrase: the peak, and the runner-up it is compared with."""
        text = f'r = {self.r:.3f} at {self.tau_s:.3f} s'
        if self.runner_up_tau_s is not None:
            text += f', next r = {self.runner_up_r:.3f} at {self.runner_up_tau_s:.3f} s'
        return text


def _half_width(corr: SpeedCorrelation, k: int) -> float:
    """Half width (s) of the peak at index ``k`` at half its height (at least one step)."""
    r = corr.r
    half = 0.5 * r[k]
    lo = k
    while lo > 0 and np.isfinite(r[lo - 1]) and r[lo - 1] > half:
        lo -= 1
    hi = k
    while hi < len(r) - 1 and np.isfinite(r[hi + 1]) and r[hi + 1] > half:
        hi += 1
    return max(1.0, 0.5 * (hi - lo)) * corr.step_s


def main_peak(corr: Optional[SpeedCorrelation]) -> Optional[CoarsePeak]:
    """Return the strongest peak of ``corr`` with its width and runner-up (None: no peak)."""
    if corr is None:
        return None
    peaks = corr.peaks()
    if peaks.size == 0:
        return None
    k = int(peaks[0])
    tau = corr.tau(k)
    width = _half_width(corr, k)
    others = [int(j) for j in peaks[1:]
              if abs(corr.tau(int(j)) - tau) > SAME_PEAK_WIDTHS * width]
    if not others:
        return CoarsePeak(tau, float(corr.r[k]), width)
    j = max(others, key=lambda i: corr.r[i])
    return CoarsePeak(tau, float(corr.r[k]), width, float(corr.r[j]), corr.tau(j))
