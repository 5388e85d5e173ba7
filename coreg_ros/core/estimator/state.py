"""
What a fit carries beyond φ: the TLS input estimates, and how to go on from the fit.

``InputState`` holds the estimated inputs of Ikits' eq. 42 (A's poses as parameters). A
``Solution`` carries one resume state (``Resume``), from which a refit of nearly the same pairs
starts next to the last minimum instead of from scratch (``refit``):

- OLS: ``NormalEquations``, the normal equations at the solution (eqs. 32-36) with every
  pair's residuals; a refit with other pairs weighted in or out adds the changed pairs' terms.
- TLS: ``TlsResume``, the input estimates and, on the structured path, the last linearisation
  (``TlsSums``, the damped reduced system of the Schur complement, with its per-pair factors);
  a refit of fewer pairs starts from those sums less the removed pairs' terms (``TlsSeed``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

from coreg_ros.core.estimator import pair_algebra
from coreg_ros.core.estimator.normal_equations_tls import TlsFactors
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

    @property
    def n(self) -> int:
        """Return the number of pairs N."""
        return self.pos_t.shape[1]

    @classmethod
    def of_pair_last(cls, pos_t: np.ndarray, quat_t: np.ndarray) -> InputState:
        """Wrap pair-last arrays (3, N) m and (4, N) unit quaternions without copying them."""
        out = cls.__new__(cls)
        out.pos_t, out.quat_t = pos_t, quat_t
        return out

    def take(self, idx: np.ndarray, lazy: bool = False) -> InputState:
        """
        Return the inputs of the pairs ``idx`` (indices into the N pairs), a copy.

        ``lazy``: gathered when first read (``TakenInputs``); a refit's start, whose first
        step reads it only to step it, without a copy of nearly all pairs' inputs beside
        this state's.
        """
        if lazy:
            return TakenInputs(self, idx)
        return InputState.of_pair_last(np.take(self.pos_t, idx, axis=1),
                                       np.take(self.quat_t, idx, axis=1))

    def stepped(self, dx: np.ndarray) -> InputState:
        """Return the state after the step dx (6, N) = (δp m, δθ rad), pair-last."""
        return InputState.of_pair_last(self.pos_t + dx[0:3],
                                       pair_algebra.rotated(self.quat_t, dx[3:6]))


class TakenInputs(InputState):
    """
    The inputs of the pairs ``idx`` of another state, gathered when first read.

    Until then it holds that state, not a copy: a step (``stepped``) gathers a chunk at a time
    into the stepped state. The numbers are those of ``InputState.take`` to the bit.
    """

    def __init__(self, base: InputState, idx: np.ndarray):
        self._source = (base, idx)

    def __getattr__(self, name: str):
        # only for attributes not set yet: pos_t and quat_t, gathered on first reading
        if name not in ('pos_t', 'quat_t') or self.__dict__.get('_source') is None:
            raise AttributeError(name)
        base, idx = self._source
        self.pos_t = np.take(base.pos_t, idx, axis=1)
        self.quat_t = np.take(base.quat_t, idx, axis=1)
        self._source = None
        return getattr(self, name)

    @property
    def n(self) -> int:
        """Return the number of pairs."""
        return len(self._source[1]) if self._source is not None else self.pos_t.shape[1]

    def stepped(self, dx: np.ndarray) -> InputState:
        """Return the gathered state after the step dx, without gathering it first if not yet."""
        if self._source is None:
            return super().stepped(dx)
        base, idx = self._source
        pos_t = np.take(base.pos_t, idx, axis=1)
        pos_t += dx[0:3]
        return InputState.of_pair_last(pos_t, pair_algebra.rotated(base.quat_t, dx[3:6], idx))


@dataclass(frozen=True)
class NormalEquations:
    """
    OLS normal equations at φ (Ikits eqs. 32-36), priors included: an OLS fit's resume state.

    Attributes
    ----------
    info : ndarray, shape (P, P)
        JᵀJ.
    gradient : ndarray, shape (P,)
        Jᵀr.
    cost : float
        Σ r² (the chi-square, eq. 57).
    residuals : ndarray, shape (N, m)
        Whitened output residuals of every pair of the problem, those of weight 0 too.

    """

    info: np.ndarray
    gradient: np.ndarray
    cost: float
    residuals: np.ndarray


@dataclass(frozen=True)
class TlsSums:
    """
    The damped reduced system ``S δφ = b`` of a TLS linearisation (eqs. 42-49) and its cost.

    Sums over pairs (priors included), so the sums of fewer pairs are these less the others'
    terms (``less``).

    Attributes
    ----------
    S : ndarray, shape (P, P)
        Damped Schur complement (undamped when ``lam`` is 0: the posterior information).
    b : ndarray, shape (P,)
        Right-hand side.
    cost : float
        Σ r² over the output and input residuals at the linearisation point.
    lam : float
        The damping λ the system was made with.

    """

    S: np.ndarray
    b: np.ndarray
    cost: float
    lam: float

    def less(self, S: np.ndarray, b: np.ndarray, cost: float) -> TlsSums:
        """Return these sums less the terms (S, b, cost) of some of their pairs (same λ)."""
        return TlsSums(self.S - S, self.b - b, self.cost - cost, self.lam)


@dataclass(frozen=True)
class TlsResume:
    """
    A TLS fit's resume state: its input estimates and, where kept, its last linearisation.

    Attributes
    ----------
    inputs : InputState
        The estimated inputs of the fit's N pairs at the solution (eq. 42): the start of a
        refit of nearly the same pairs.
    sums : TlsSums or None
        The last linearisation, at (φ, ``inputs``): kept on the structured path while its
        factors are intact (a rejected last trial spends them), else None.
    factors : TlsFactors or None
        That linearisation's per-pair factors (None exactly when ``sums`` is).
    step : ndarray, shape (P,) or None
        A paused fit (``lm.PAUSED``): the step its sums give, where the fit goes next.

    """

    inputs: InputState
    sums: Optional[TlsSums]
    factors: Optional[TlsFactors]
    step: Optional[np.ndarray] = None


@dataclass(frozen=True)
class TlsSeed:
    """
    The first linearisation of a TLS refit, made without a pass over its pairs.

    Attributes
    ----------
    sums : TlsSums
        The reduced system of exactly the refit's pairs at (φ, ``inputs``) with damping
        ``sums.lam`` (e.g. a fit's sums less the removed pairs' terms).
    inputs : InputState
        The refit's pairs' inputs.
    factors : TlsFactors
        The per-pair factors of the fit the sums come from (``n_factored`` pairs), which give
        the first input step; spent (cleared) by it.
    n_factored : int
        The number of pairs of ``factors``.
    kept : ndarray of int or None
        Indices of the refit's pairs among those ``n_factored`` (None: the same pairs).

    """

    sums: TlsSums
    inputs: InputState
    factors: TlsFactors
    n_factored: int
    kept: Optional[np.ndarray] = None


#: How to go on from a fit (``Solution.resume``).
Resume = Union[NormalEquations, TlsResume]
