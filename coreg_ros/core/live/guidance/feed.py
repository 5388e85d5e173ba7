"""Pairs and A's velocity at them, as the guidance and the watchdog consume them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.clock.trajectory import Trajectory, VELOCITY_HALF_WINDOW
from coreg_ros.core.errors import InputError
from coreg_ros.core.types import Pairs
import numpy as np

# --------------------------------------------------------------------------- pairs and velocity


@dataclass(frozen=True)
class PairBatch:
    """
    Pairs with device A's velocity at each pair instant: what guidance and the watchdog take.

    Attributes
    ----------
    stamps : ndarray of int64, shape (N,)
        B's stamps, ns.
    pos_a : ndarray, shape (N, 3)
        A's tool position (interpolated at B's stamps), A's base frame, m.
    quat_a : ndarray, shape (N, 4)
        A's tool orientation, (w, x, y, z).
    pos_b : ndarray, shape (N, 3) or (N, 3, 3)
        B's marker position(s), B's base frame, m.
    quat_b : ndarray, shape (N, 4) or None
        B's marker orientation (full pose only).
    a_var_scale : ndarray, shape (N,) or None
        Factor on A's noise variance per pair (interpolation).
    velocity : ndarray, shape (N, 6)
        A's linear (m/s) and angular velocity (rad/s, A's base frame, left perturbation).

    """

    stamps: np.ndarray
    pos_a: np.ndarray
    quat_a: np.ndarray
    pos_b: np.ndarray
    quat_b: Optional[np.ndarray]
    a_var_scale: Optional[np.ndarray]
    velocity: np.ndarray

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def take(self, index) -> PairBatch:
        """Return the pairs at ``index`` (a slice, mask or integer array)."""
        def sub(x):
            return None if x is None else x[index]
        return PairBatch(self.stamps[index], self.pos_a[index], self.quat_a[index],
                         self.pos_b[index], sub(self.quat_b), sub(self.a_var_scale),
                         self.velocity[index])

    @staticmethod
    def concatenate(batches) -> Optional[PairBatch]:
        """One batch from several (None when there is none)."""
        batches = [b for b in batches if b is not None and len(b)]
        if not batches:
            return None
        if len(batches) == 1:
            return batches[0]

        def cat(name):
            parts = [getattr(b, name) for b in batches]
            return None if any(p is None for p in parts) else np.concatenate(parts)
        return PairBatch(cat('stamps'), cat('pos_a'), cat('quat_a'), cat('pos_b'),
                         cat('quat_b'), cat('a_var_scale'), cat('velocity'))


def _pairs_arrays(pairs: Pairs) -> dict:
    return {'stamps': np.asarray(pairs.stamps, dtype=np.int64),
            'pos_a': np.asarray(pairs.pos_a, dtype=float),
            'quat_a': np.asarray(pairs.quat_a, dtype=float),
            'pos_b': np.asarray(pairs.pos_b, dtype=float),
            'quat_b': None if pairs.quat_b is None else np.asarray(pairs.quat_b, dtype=float),
            'a_var_scale': None if pairs.a_var_scale is None
            else np.asarray(pairs.a_var_scale, dtype=float)}


class PairFeed:
    """
    Turn pairs arriving in batches into ``PairBatch`` es with A's velocity.

    The velocity of a pair is the central difference of A's interpolated poses over
    ±``half`` s along the pair sequence (``Trajectory.velocity``, as the clock-offset estimate
    uses), so a pair is released once the pairs up to ``half`` after it have arrived. Pairs
    whose stamp is not after the last one seen are ignored, so the caller may re-pair an
    overlapping span of its buffers each time.

    Parameters
    ----------
    half : float
        Half-width of the difference window, s.
    max_gap : float, optional
        A window spanning a gap between pairs longer than this (s; at least 2.5 pair
        intervals), or reaching before the first pair, gives zero velocity
        (``Trajectory.velocity``): none is known across a tracking dropout. The settings'
        ``max_gap``, as the clock-offset estimate uses; None: differences across any gap.

    """

    def __init__(self, half: float = VELOCITY_HALF_WINDOW, max_gap: Optional[float] = None):
        self.half = float(half)
        self.max_gap = None if max_gap is None else float(max_gap)
        self._last_stamp: Optional[int] = None
        self._held: Optional[dict] = None  # released context + pending pairs
        self._n_context = 0  # leading pairs of _held already released
        self._origin: Optional[int] = None

    def push(self, pairs: Optional[Pairs], final: bool = False) -> Optional[PairBatch]:
        """
        Add pairs (B stamps increasing); return the pairs now released, or None.

        Parameters
        ----------
        pairs : Pairs or None
            New pairs (None: none, e.g. with ``final``).
        final : bool
            Release everything held (end of the data, or before a gap).

        """
        if pairs is not None and len(pairs):
            new = _pairs_arrays(pairs)
            keep = np.ones(len(new['stamps']), dtype=bool)
            if self._last_stamp is not None:
                keep = new['stamps'] > self._last_stamp
            if keep.any():
                new = {k: None if v is None else v[keep] for k, v in new.items()}
                self._last_stamp = int(new['stamps'][-1])
                if self._origin is None:
                    self._origin = int(new['stamps'][0])
                self._held = new if self._held is None else {
                    k: None if v is None or new[k] is None else np.concatenate([v, new[k]])
                    for k, v in self._held.items()}
        held = self._held
        if held is None or len(held['stamps']) <= self._n_context:
            return None
        t = (held['stamps'] - np.int64(self._origin)).astype(float) * 1e-9
        if final:
            end = len(t)
        else:
            end = int(np.searchsorted(t, t[-1] - self.half, side='right'))
        if end <= self._n_context:
            return None
        release = slice(self._n_context, end)
        if len(t) > 1:
            traj = Trajectory(t, held['pos_a'], held['quat_a'])
            gap = None
            if self.max_gap is not None:
                gap = max(self.max_gap, 2.5 * float(np.median(np.diff(t))))
            v, w = traj.velocity(t[release], self.half, max_gap=gap)
        else:
            v = w = np.zeros((end - self._n_context, 3))
        out = PairBatch(held['stamps'][release], held['pos_a'][release], held['quat_a'][release],
                        held['pos_b'][release],
                        None if held['quat_b'] is None else held['quat_b'][release],
                        None if held['a_var_scale'] is None else held['a_var_scale'][release],
                        np.hstack([v, w]))
        if final:
            self._held, self._n_context = None, 0
        else:
            # keep the released pairs within 3 half-windows as context for later differences
            first = int(np.searchsorted(t, t[end - 1] - 3.0 * self.half, side='left'))
            first = min(first, end)
            self._held = {k: None if v_ is None else v_[first:] for k, v_ in held.items()}
            self._n_context = end - first
        return out


def batch_from_pairs(pairs: Pairs, half: float = VELOCITY_HALF_WINDOW,
                     max_gap: Optional[float] = None) -> PairBatch:
    """All of ``pairs`` with A's velocity (``PairFeed`` at once)."""
    out = PairFeed(half, max_gap).push(pairs, final=True)
    if out is None:
        raise InputError('no pairs')
    return out
