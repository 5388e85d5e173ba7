"""
Each device's noise measured while collecting, whenever it stands still (the node's ``noise``).

``StillNoiseMonitor`` takes a device's samples as they arrive (in order, any batch size). It
keeps the last ``HISTORY_S`` seconds, finds the still samples there with the test of
``coreg noise`` (``noise.still.still_mask``: a still window's spread does not grow with its
length), and once a sample is ``SETTLE_S`` old (its long window complete) adds it to the
running sums of the still stretch it belongs to: position, and the rotation vector about the
stretch's first orientation (about the base axes, ``R = Exp(δθ) R_first``). A stretch counts
once it lasts ``MIN_STILL_S``; stretches of mostly identical samples are a frozen stream and
set apart. The covariance is pooled within the stretches (each about its own mean). Unlike
``coreg noise`` it neither trims the stretches' ends nor averages in Allan blocks: it is a
running figure; ``coreg noise`` on the saved samples is the reference.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.noise.still import (
    FROZEN_SHARE,
    LONG_WINDOWS,
    MIN_STILL_S,
    still_mask,
    STILL_WINDOW_S,
)
from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.core.types import PoseStream
import numpy as np

#: Seconds of recent samples kept for the stillness test.
HISTORY_S = 4.0 * LONG_WINDOWS * STILL_WINDOW_S
#: A sample's stillness is final once it is this old (its long window has arrived).
SETTLE_S = LONG_WINDOWS * STILL_WINDOW_S
#: A gap longer than this ends a still stretch, s.
GAP_S = 0.5


class _Sums:
    """Running sums of one still stretch: count, first and second moments, repeats."""

    def __init__(self, q_ref: np.ndarray, t0_ns: int):
        self.q_ref = q_ref
        self.t0_ns = t0_ns
        self.t1_ns = t0_ns
        self.n = 0
        self.repeats = 0
        self.s1 = np.zeros(6)
        self.s2 = np.zeros((6, 6))
        self.last: Optional[np.ndarray] = None

    def add(self, stamps, position, quat_wxyz) -> None:
        dth = quat.log(quat.multiply(quat_wxyz, quat.conjugate(self.q_ref)[None, :]))
        x = np.hstack([position, dth])
        self.s1 += x.sum(axis=0)
        self.s2 += x.T @ x
        both = np.hstack([position, quat_wxyz])
        if self.last is None:
            same = np.all(both[1:] == both[:-1], axis=1)
        else:
            same = np.all(both == np.vstack([self.last[None], both[:-1]]), axis=1)
        self.repeats += int(np.sum(same))
        self.last = both[-1]
        self.n += len(x)
        self.t1_ns = int(stamps[-1])

    @property
    def duration(self) -> float:
        return (self.t1_ns - self.t0_ns) * 1e-9

    @property
    def frozen(self) -> bool:
        return self.n > 1 and self.repeats > FROZEN_SHARE * (self.n - 1)

    def scatter(self) -> np.ndarray:
        """Return the stretch's scatter about its mean (6×6)."""
        return self.s2 - np.outer(self.s1, self.s1) / max(self.n, 1)


@dataclass(frozen=True)
class LiveNoise:
    """
    What a monitor has measured so far.

    Attributes
    ----------
    noise : DeviceNoise or None
        The measured noise (None before ``MIN_STILL_S`` of still time).
    still_seconds : float
        Still time measured.
    stretches : int
        Still stretches measured.
    frozen_seconds : float
        Still time set apart as a frozen stream.

    """

    noise: Optional[DeviceNoise]
    still_seconds: float
    stretches: int
    frozen_seconds: float


class StillNoiseMonitor:
    """
    A device's noise measured from its still stretches as samples arrive (module docstring).

    Parameters
    ----------
    rotation : bool
        Whether the device's orientation is measured (False: a position-only tracker; its
        rotation noise stays ``fallback``'s).
    fallback : DeviceNoise
        The noise of a channel not measured.

    """

    def __init__(self, rotation: bool, fallback: DeviceNoise):
        self.rotation = bool(rotation)
        self.fallback = fallback
        self._stamps = np.zeros(0, dtype=np.int64)
        self._pos = np.zeros((0, 3))
        self._quat = np.zeros((0, 4))
        self._settled_ns: Optional[int] = None   # stamp of the last sample settled
        self._open: Optional[_Sums] = None
        self._done: list = []
        self.latest = LiveNoise(None, 0.0, 0, 0.0)

    def add(self, stream: PoseStream) -> LiveNoise:
        """Take new samples (stamped after those before); return the noise measured so far."""
        if len(stream):
            keep = stream.stamps > (self._stamps[-1] if len(self._stamps) else -2 ** 62)
            self._stamps = np.concatenate([self._stamps, stream.stamps[keep]])
            self._pos = np.vstack([self._pos, stream.position[keep]])
            self._quat = np.vstack([self._quat, stream.quat_wxyz[keep]])
            self._settle()
        return self.latest

    def _settle(self) -> None:
        if len(self._stamps) < 2:
            return
        newest = int(self._stamps[-1])
        mask = still_mask(self._stamps, self._pos, self._quat if self.rotation else None)
        settled = self._stamps <= newest - int(SETTLE_S * 1e9)
        if self._settled_ns is not None:
            settled &= self._stamps > self._settled_ns
        idx = np.flatnonzero(settled)
        if len(idx):
            self._consume(idx, mask[idx])
            self._settled_ns = int(self._stamps[idx[-1]])
        # keep the history for the next test
        old = self._stamps < newest - int(HISTORY_S * 1e9)
        if old.any():
            self._stamps, self._pos, self._quat = (self._stamps[~old], self._pos[~old],
                                                   self._quat[~old])
        self.latest = self._measured()

    def _consume(self, idx: np.ndarray, still: np.ndarray) -> None:
        """Add the settled samples ``idx`` to the still stretches (or close one at motion)."""
        start = 0
        for k in range(1, len(idx) + 1):
            ends = k == len(idx) or still[k] != still[start] or (
                self._stamps[idx[k]] - self._stamps[idx[k - 1]] > GAP_S * 1e9)
            if not ends:
                continue
            run = idx[start:k]
            if still[start]:
                gap = self._open is not None and (
                    int(self._stamps[run[0]]) - self._open.t1_ns > GAP_S * 1e9)
                if self._open is None or gap:
                    self._close()
                    self._open = _Sums(self._quat[run[0]].copy(), int(self._stamps[run[0]]))
                self._open.add(self._stamps[run], self._pos[run], self._quat[run])
            else:
                self._close()
            start = k

    def _close(self) -> None:
        if self._open is not None and self._open.duration >= MIN_STILL_S:
            self._done.append(self._open)
        self._open = None

    def _measured(self) -> LiveNoise:
        stretches = list(self._done)
        if self._open is not None and self._open.duration >= MIN_STILL_S:
            stretches.append(self._open)
        good = [s for s in stretches if not s.frozen]
        frozen = sum(s.duration for s in stretches if s.frozen)
        seconds = sum(s.duration for s in good)
        if not good:
            return LiveNoise(None, 0.0, 0, frozen)
        dof = sum(s.n - 1 for s in good)
        cov = sum(s.scatter() for s in good) / max(dof, 1)
        rot = cov[3:6, 3:6] if self.rotation else self.fallback.rotation_cov
        try:
            noise = DeviceNoise.from_covariances(cov[0:3, 0:3], rot)
        except ValueError:  # singular (a stream quantised coarser than its noise)
            noise = None
        return LiveNoise(noise, seconds, len(good), frozen)
