"""
The state a TLS fit carries beyond φ: its input estimates and a linearisation to go on from.

``InputState`` holds the estimated inputs of Ikits' eq. 42 (A's poses as parameters);
``TlsSums`` a linearisation (the damped reduced system of the Schur complement), from which a
refit of fewer pairs starts without a pass over all of them.
"""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core.estimator import pair_algebra
import numpy as np


class InputState:
    """
    The TLS estimates of the inputs x_i = (p_A, q_A), stored pair-last: (3, N) and (4, N).

    ``pos`` and ``quat`` are the (N, 3) and (N, 4) views. Each orientation is stepped
    multiplicatively, ``q ← Exp(δ) ⊗ q``: a chart centred at the current estimate (the limit
    of §3.1's re-charting), so no per-pair chart bookkeeping is needed and every input block
    is equally well conditioned.
    """

    def __init__(self, pos: np.ndarray, quats: np.ndarray):
        self.pos_t = np.ascontiguousarray(np.asarray(pos, dtype=float).T)
        self.quat_t = np.ascontiguousarray(np.asarray(quats, dtype=float).T)

    @property
    def pos(self) -> np.ndarray:
        """Input positions, (N, 3) view."""
        return self.pos_t.T

    @property
    def quat(self) -> np.ndarray:
        """Input orientations, (N, 4) view."""
        return self.quat_t.T

    @classmethod
    def _pair_last(cls, pos_t: np.ndarray, quat_t: np.ndarray) -> InputState:
        """Wrap pair-last arrays (3, N) and (4, N) without copying them."""
        out = cls.__new__(cls)
        out.pos_t, out.quat_t = pos_t, quat_t
        return out

    def stepped(self, dx: np.ndarray) -> InputState:
        """Return the state after the step dx (6, N) = (δp, δθ), pair-last."""
        return InputState._pair_last(self.pos_t + dx[0:3],
                                     pair_algebra.rotated(self.quat_t, dx[3:6]))


@dataclass(frozen=True)
class TlsSums:
    """
    A TLS linearisation kept for a refit: the damped reduced system, the cost, the damping.

    The sums are over pairs; a refit of the same pairs less a few starts from these sums less
    the removed pairs' terms (``solve_tls(seed=...)``), with the kept pairs' factors for its
    first input step, instead of a pass over all pairs.
    """

    S: np.ndarray
    b: np.ndarray
    cost: float
    lam: float
    factors: object   # normal_equations_tls.TlsFactors over the fit's pairs
