"""
Where a device stands still: its still segments, found from the samples alone.

A device's noise is measured where the pose it reports does not move (``measure``). No noise
level is known beforehand, so stillness is recognised by the *shape* of the spread, not its
size: over a short window (``STILL_WINDOW_S``) and over ``LONG_WINDOWS`` such windows in a row,
the noise of a still device spreads the same (the variance of a stationary signal does not grow
with the window), while motion spreads ``LONG_WINDOWS²`` times more over the long window
(linear motion) and a random walk ``LONG_WINDOWS`` times. A long window is still when its
variance is at most ``STATIONARY_RATIO`` times the mean of its short windows', in position and
in rotation; a sample is still when two still long windows cover it (a motion in a long
window's last short window alone need not raise its ratio); runs of still samples at least
``MIN_STILL_S`` long, trimmed by ``TRIM_S`` at both ends (the last of a motion), are the
still segments. Motion slower than the noise over
a long window is not told from it (and adds less than the noise to the measurement).

The rotation's spread is taken on the quaternions made sign-continuous (four components
spreading about half the angle), which needs no reference orientation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Short window of the stillness test, s (at least ``MIN_WINDOW_SAMPLES`` samples).
STILL_WINDOW_S = 0.5
MIN_WINDOW_SAMPLES = 8
#: Short windows in a long window.
LONG_WINDOWS = 4
#: Largest ratio of the long window's variance to its short windows' mean for stillness
#: (1 for stationary noise; 16 for linear motion, 4 for a random walk; the estimate of a
#: ratio of white noise over 4 × 50 samples scatters by ~0.1).
STATIONARY_RATIO = 1.6
#: Shortest still segment used, s, and what is cut from both ends of each.
MIN_STILL_S = 3.0
TRIM_S = 0.25
#: A gap between samples longer than this many median intervals (and 0.5 s) splits a segment.
SPLIT_GAP_INTERVALS = 10
#: A segment whose consecutive samples are identical this often is a frozen stream.
FROZEN_SHARE = 0.5


@dataclass(frozen=True)
class Segment:
    """
    A still segment of one device's stream: samples ``start`` to ``stop`` (exclusive).

    Attributes
    ----------
    start, stop : int
        Sample indices in the stream.
    t0_ns, t1_ns : int
        Stamps of its first and last sample (the device's clock).

    """

    start: int
    stop: int
    t0_ns: int
    t1_ns: int

    @property
    def n(self) -> int:
        """Return the number of samples."""
        return self.stop - self.start

    @property
    def duration(self) -> float:
        """Return the time from the first to the last sample, s."""
        return (self.t1_ns - self.t0_ns) * 1e-9


def continuous_quaternions(quat_wxyz: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) with each sign chosen nearest its predecessor (q and -q are one)."""
    q = np.asarray(quat_wxyz, dtype=float).copy()
    if len(q) < 2:
        return q
    flips = np.sum(q[1:] * q[:-1], axis=1) < 0.0
    sign = np.cumprod(np.concatenate([[1.0], np.where(flips, -1.0, 1.0)]))
    return q * sign[:, None]


def _window_variance(x: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """Sum the variance over the columns of ``x`` in windows ``[s, s + length)``, from cumsums."""
    c1 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x * x, axis=0)])
    s1 = c1[starts + length] - c1[starts]
    s2 = c2[starts + length] - c2[starts]
    return np.sum(s2 / length - (s1 / length) ** 2, axis=1)


def _still_windows(x: np.ndarray, short: int) -> np.ndarray:
    """Still flags of the long windows starting at every ``short``-th sample (one channel)."""
    x = x - np.mean(x, axis=0)  # rounding of the cumsums: centred once
    long = LONG_WINDOWS * short
    n_long = (len(x) - long) // short + 1
    starts = np.arange(n_long) * short
    v_long = _window_variance(x, starts, long)
    shorts = np.arange(n_long + LONG_WINDOWS - 1) * short
    v_short = _window_variance(x, shorts, short)
    mean_short = np.convolve(v_short, np.ones(LONG_WINDOWS) / LONG_WINDOWS, mode='valid')
    tiny = 1e-30 + 1e-12 * float(np.max(np.abs(x))) ** 2
    return (v_long <= STATIONARY_RATIO * mean_short) | (v_long <= tiny)


def still_mask(stamps: np.ndarray, position: np.ndarray, quat_wxyz=None) -> np.ndarray:
    """
    Flag the samples two still long windows cover (position and, if given, rotation).

    Parameters
    ----------
    stamps : ndarray of int64, shape (N,)
        Sample stamps, ns (increasing).
    position : ndarray, shape (N, 3)
        m.
    quat_wxyz : ndarray, shape (N, 4), optional
        The orientations; None when the device's orientation means nothing (a position-only
        tracker).

    Returns
    -------
    ndarray of bool, shape (N,)

    """
    n = len(stamps)
    out = np.zeros(n, dtype=bool)
    if n < 2:
        return out
    dt = float(np.median(np.diff(stamps))) * 1e-9
    short = max(MIN_WINDOW_SAMPLES, int(round(STILL_WINDOW_S / max(dt, 1e-9))))
    if n < LONG_WINDOWS * short:
        return out
    still = _still_windows(np.asarray(position, dtype=float), short)
    if quat_wxyz is not None:
        still &= _still_windows(continuous_quaternions(quat_wxyz), short)
    long = LONG_WINDOWS * short
    # a sample is still when two still long windows cover it: a motion confined to the last
    # (or first) short window of a long one need not raise its variance ratio, but then the
    # neighbouring long window, which it leaves out, is still alone there
    edges = np.zeros(n + 1)
    first = np.flatnonzero(still) * short
    np.add.at(edges, first, 1.0)
    np.add.at(edges, first + long, -1.0)
    return np.cumsum(edges[:-1]) > 1.5


def runs(mask: np.ndarray) -> list:
    """(start, stop) of the runs of True in a boolean array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(),
                    strict=True))


def segments_of(stamps: np.ndarray, mask: np.ndarray, min_duration: float = MIN_STILL_S,
                trim: float = TRIM_S) -> list:
    """
    Still segments: runs of ``mask`` split at long gaps, trimmed, at least ``min_duration``.

    Parameters
    ----------
    stamps : ndarray of int64, shape (N,)
        Sample stamps, ns.
    mask : ndarray of bool, shape (N,)
        Still samples (``still_mask``).
    min_duration, trim : float
        Shortest segment kept and the time cut from both ends, s.

    Returns
    -------
    list of Segment

    """
    stamps = np.asarray(stamps, dtype=np.int64)
    if len(stamps) < 2:
        return []
    dt = np.diff(stamps)
    gap = max(0.5e9, SPLIT_GAP_INTERVALS * float(np.median(dt)))
    cut = np.concatenate([[False], dt > gap])  # a sample after a long gap starts a new run
    out = []
    for start, stop in runs(mask):
        bounds = [start] + [int(i) for i in np.flatnonzero(cut[start + 1:stop]) + start + 1] \
            + [stop]
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            t = stamps[a:b]
            lo = int(np.searchsorted(t, t[0] + int(trim * 1e9))) + a
            hi = int(np.searchsorted(t, t[-1] - int(trim * 1e9), side='right')) + a
            if hi - lo >= 2 and (stamps[hi - 1] - stamps[lo]) * 1e-9 >= min_duration:
                out.append(Segment(lo, hi, int(stamps[lo]), int(stamps[hi - 1])))
    return out


def window_segment(stamps: np.ndarray, t0_ns: int, t1_ns: int) -> list:
    """Return the samples within ``[t0_ns, t1_ns]`` as one segment (none if fewer than 2)."""
    stamps = np.asarray(stamps, dtype=np.int64)
    lo = int(np.searchsorted(stamps, t0_ns))
    hi = int(np.searchsorted(stamps, t1_ns, side='right'))
    if hi - lo < 2:
        return []
    return [Segment(lo, hi, int(stamps[lo]), int(stamps[hi - 1]))]


def repeated_share(position: np.ndarray, quat_wxyz=None) -> float:
    """Share of consecutive samples identical to their predecessor (bit for bit)."""
    if len(position) < 2:
        return 0.0
    same = np.all(position[1:] == position[:-1], axis=1)
    if quat_wxyz is not None:
        same &= np.all(quat_wxyz[1:] == quat_wxyz[:-1], axis=1)
    return float(np.mean(same))


def longest_still(stamps: np.ndarray, mask: np.ndarray) -> float:
    """Return the longest run of still samples, s (what a refusal can say was found)."""
    best = 0.0
    for a, b in runs(mask):
        best = max(best, float(stamps[b - 1] - stamps[a]) * 1e-9)
    return best
