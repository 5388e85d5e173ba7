"""
A device's sampled pose as a function of time: interpolation and velocity.

Used where a pose is needed between samples or its rate of change is needed: the time-offset
estimation of the calibration (A's interpolated pose moves with its velocity) and the gap
diagnosis. Time is float seconds on a caller-chosen axis (e.g. from the first paired stamp);
pairing itself never uses float seconds.
"""

from __future__ import annotations

from collections.abc import Callable
import threading
from typing import Optional

from coreg_ros.core import quaternion as quat
import numpy as np

#: Half-width of the finite-difference window for velocities, s (at least two A samples).
VELOCITY_HALF_WINDOW = 0.04
#: Times whose velocities are computed at once (bounds the temporaries; cache-sized).
VELOCITY_CHUNK = 1 << 16
#: ``velocity_arriving`` writes in a second thread only beyond this many chunks: below, the
#: reader waits for a large share of the rows, and the thread costs CPU time that the overlap
#: does not give back (the offset estimate at 100k pairs, 2 chunks: 1.45-1.49 × the fixed-offset
#: CPU time with the thread, 1.42-1.44 without).
ARRIVING_CHUNKS = 4


class _RowsWritten:
    """How many rows a writer thread has written; a reader waits for the ones it needs."""

    def __init__(self):
        self._done = 0
        self._error: Optional[BaseException] = None
        self._changed = threading.Condition()

    def run(self, write: Callable[[], object]) -> None:
        try:
            write()
        except BaseException as e:  # noqa: BLE001 - handed to the reader, which raises it
            with self._changed:
                self._error = e
                self._changed.notify_all()

    def advance(self, stop: int) -> None:
        with self._changed:
            self._done = stop
            self._changed.notify_all()

    def wait(self, stop: int) -> None:
        with self._changed:
            self._changed.wait_for(lambda: self._done >= stop or self._error is not None)
            if self._error is not None:
                raise self._error


class Trajectory:
    """
    Device A's tool pose as a function of time, sampled; linear / normalised-lerp interpolation.

    Parameters
    ----------
    t : ndarray, shape (K,)
        Sample times, s (strictly increasing), on the pairs' time axis.
    position : ndarray, shape (K, 3)
        Tool position in A's base frame, m.
    quat_wxyz : ndarray, shape (K, 4)
        Tool orientation in A's base frame, (w, x, y, z).

    """

    def __init__(self, t: np.ndarray, position: np.ndarray, quat_wxyz: np.ndarray):
        t = np.asarray(t, dtype=float)
        position = np.asarray(position, dtype=float)
        q = np.asarray(quat_wxyz, dtype=float)
        if not np.all(np.diff(t) > 0):  # out of order or repeated: sorted, the first kept
            order = np.argsort(t, kind='stable')
            t = t[order]
            keep = np.concatenate([[True], np.diff(t) > 0])
            t, position, q = t[keep], position[order][keep], q[order][keep]
        # samples already in order are held, not copied (a long recording's A is 2M samples)
        self.t, self.position, self.quat = t, position, q
        # continuous sign along the trajectory, so that neighbours interpolate the short way:
        # the signs are kept (8 bytes a sample) and applied to the samples a query reads
        dots = np.einsum('ij,ij->i', q[1:], q[:-1])
        self._sign: Optional[np.ndarray] = None
        if np.any(dots < 0.0):
            self._sign = np.concatenate([[1.0], np.cumprod(np.where(dots < 0.0, -1.0, 1.0))])
        self._step: Optional[float] = None
        self._segments: dict = {}

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Pose at times t (s), shapes (n, 3) and (n, 4); linear extrapolation beyond the ends.

        Orientation by normalised lerp between neighbours (equal to slerp to O(θ³) for the
        small angles between successive samples).
        """
        pos, q, _ = self._interpolated(np.asarray(t, dtype=float))
        return pos, q

    def _interpolated(self, t: np.ndarray, position: bool = True, orientation: bool = True,
                      canonical: bool = True
                      ) -> tuple[Optional[np.ndarray], Optional[np.ndarray], np.ndarray]:
        """
        Return ``pose(t)``'s parts asked (None for the others) and each time's bracket.

        The bracket is the index of the last sample at or before the time (-1: none).
        ``canonical`` False: the quaternions keep the trajectory's continuous sign instead of
        w >= 0 (for a relative rotation whose ``quat.log`` takes the sign anyway).
        """
        before = np.searchsorted(self.t, t, side='right') - 1
        k = np.clip(before, 0, len(self) - 2)
        k1 = k + 1
        # np.take: several times faster than fancy indexing on rows, the same numbers
        t_lo = np.take(self.t, k)
        span = np.take(self.t, k1) - t_lo
        a = ((t - t_lo) / span)[:, None]
        pos = q = None
        if position:
            p_lo = np.take(self.position, k, axis=0)
            pos = p_lo + a * (np.take(self.position, k1, axis=0) - p_lo)
        if orientation:
            q_lo, q_hi = np.take(self.quat, k, axis=0), np.take(self.quat, k1, axis=0)
            if self._sign is not None:
                q_lo *= np.take(self._sign, k)[:, None]
                q_hi *= np.take(self._sign, k1)[:, None]
            q = q_lo + a * (q_hi - q_lo)
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            if canonical:
                q = quat.canonical(q)
        return pos, q, before

    def velocity(self, t: np.ndarray, half: float = VELOCITY_HALF_WINDOW,
                 max_gap: Optional[float] = None, linear: bool = True, angular: bool = True,
                 out: Optional[np.ndarray] = None,
                 written: Optional[Callable[[int], None]] = None):
        """
        Linear (m/s) and angular (rad/s, A's base frame) velocity at t by central differences.

        ``ω = Log(q(t+h) ⊗ q(t-h)*) / 2h``: the rotation acts on the left, in A's base frame,
        as the input perturbation of the models does. With ``max_gap`` (s), a window
        ``[t-h, t+h]`` that reaches past either end or spans a gap between samples longer
        than ``max_gap`` gives zero: no velocity is known there (interpolating across a
        tracking dropout or between recorded still poses would invent one). ``linear`` or
        ``angular`` False: that part is not computed (None), as the coarse offset search,
        which needs one speed, asks. ``out`` (N, 6): both parts are written into it, [v | w]
        (the offset step's layout, without joining two arrays). ``written(stop)`` is called
        once the rows before ``stop`` are written (``velocity_arriving``).
        """
        t = np.asarray(t, dtype=float)
        if len(self) > 1:
            half = max(half, 1.5 * self.median_step())
        if out is not None:
            v, w = out[:, 0:3], out[:, 3:6]
        else:
            v = np.empty((t.shape[0], 3)) if linear else None
            w = np.empty((t.shape[0], 3)) if angular else None
        # in chunks: each time's velocity is its own, and a 2M-pair recording's temporaries
        # (two poses a time) would otherwise take ~600 MB at the peak of the offset search
        for start in range(0, t.shape[0], VELOCITY_CHUNK):
            sl = slice(start, start + VELOCITY_CHUNK)
            self._velocity_into(t[sl], half, max_gap, None if v is None else v[sl],
                                None if w is None else w[sl])
            if written is not None:
                written(min(t.shape[0], start + VELOCITY_CHUNK))
        return v, w

    def velocity_arriving(self, t: np.ndarray, half: float, max_gap: Optional[float],
                          out: np.ndarray) -> Callable[[int], None]:
        """
        Write ``velocity(t, half, max_gap, out=out)`` in a second thread, chunk by chunk.

        Returns ``ready(stop)``, which waits until the rows before ``stop`` are written (and
        raises what the thread raised). The velocity's chunks are whole-array NumPy calls,
        which run outside Python's lock, so a caller that reads the rows in order (the offset
        step's sums) works on the first rows while the next are made: at 2M pairs the two
        take 0.5 instead of 0.73 s on two cores. Up to ``ARRIVING_CHUNKS`` chunks are written
        here, at once.
        """
        if t.shape[0] <= ARRIVING_CHUNKS * VELOCITY_CHUNK:
            self.velocity(t, half, max_gap=max_gap, out=out)
            return lambda stop: None
        rows = _RowsWritten()
        threading.Thread(target=rows.run, daemon=True, name='coreg-velocity', args=(
            lambda: self.velocity(t, half, max_gap=max_gap, out=out, written=rows.advance),
        )).start()
        return rows.wait

    def _velocity_into(self, t: np.ndarray, half: float, max_gap: Optional[float],
                       v: Optional[np.ndarray], w: Optional[np.ndarray]) -> None:
        """Write ``velocity``'s linear part into v and its angular part into w (None: skip)."""
        # the signs of q0 and q1 need no choosing: q1 ⊗ q0* only changes sign with either
        # (exactly), and quat.log gives q and -q one rotation vector
        p1, q1, _ = self._interpolated(t + half, v is not None, w is not None, False)
        p0, q0, lo = self._interpolated(t - half, v is not None, w is not None, False)
        if v is not None:
            v[:] = (p1 - p0) / (2.0 * half)
        if w is not None:
            w[:] = quat.relative_log(q1, q0) / (2.0 * half)
        if max_gap is not None:
            gaps = self._segment_ids(max_gap)
            hi = np.searchsorted(self.t, t + half, side='left')
            known = (lo >= 0) & (hi < len(self))
            known[known] &= gaps[hi[known]] == gaps[lo[known]]
            for x in (v, w):
                if x is not None:
                    x[~known] = 0.0

    def median_step(self) -> float:
        """Median interval between the samples, s (computed once)."""
        if self._step is None:
            self._step = float(np.median(np.diff(self.t)))
        return self._step

    def _segment_ids(self, max_gap: float) -> np.ndarray:
        """Per sample, how many gaps longer than ``max_gap`` (s) precede it (computed once)."""
        ids = self._segments.get(max_gap)
        if ids is None:
            ids = np.concatenate([[0], np.cumsum(np.diff(self.t) > max_gap)])
            self._segments[max_gap] = ids
        return ids
