"""
Changes that stay: where in time a step of B's clock offset fits best.

A clock that jumps (an NTP correction, a driver restart) moves B's offset from τ before to
τ + Δ after some instant. The instant is located once per recording, before the effects are
scored, by a score scan of the base fit (``timeline.step_scan``): the whitened residuals and
columns of the base model with a time offset added (its column is the offset's, −J_x ẋ_A), the
offset's column stepping after each candidate pair; the candidate that gains most is the step.
The ``clock_step`` effect (``effects.clock``) then fits τ and Δ with the instant held
(``terms.StepShift``), starting from the scan's one-step estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core.calibration.observability import WEAK_SHARE
from coreg_ros.core.diagnosis.data import DiagData
from coreg_ros.core.diagnosis.fit import Model, State
from coreg_ros.core.diagnosis.timeline import step_scan
import numpy as np
from scipy import stats

#: Candidate instants scanned (segment boundaries), then refined pair by pair near the best.
SCAN_SEGMENTS = 400
#: A step leaves at least this share of the pairs (and 20) on either side.
MIN_SIDE = 0.05
#: Pairs whose squared error is beyond this chi-square tail are weighed down to it (Huber):
#: a glitch must not pull the instant to itself, while the many pairs a large step puts far
#: off must still point the way together.
GROSS_P = 1e-3


@dataclass(frozen=True)
class ClockStepStart:
    """
    Where B's clock steps, and the fit's start there.

    Attributes
    ----------
    at_s : float
        The instant, s from the first pair (between the last pair before and the first after).
    theta : ndarray, shape (2,)
        One-step estimate of (τ before, Δ), s.
    gain : float
        The scan's one-step gain there, nats.

    """

    at_s: float
    theta: np.ndarray
    gain: float


def locate_clock_step(data: DiagData, state: State, idx: np.ndarray) -> ClockStepStart:
    """
    Locate a step of B's clock offset on the pairs ``idx`` from the base fit ``state``.

    Parameters
    ----------
    data : DiagData
        The pairs.
    state : fit.State
        The base model's state (no effect).
    idx : ndarray of int
        The pairs scanned (the selection pairs), in time order.

    Returns
    -------
    ClockStepStart

    """
    model = Model(data, ('time_offset',))
    st = model.initial_state(state)
    parts = [model.evaluate(st, ch) for ch in model.chunks(idx)]
    z = np.concatenate([p.st.z for p in parts])
    lam = np.concatenate([p.st.lam for p in parts])
    J = np.concatenate([p.Jz for p in parts])
    w = 1.0 / np.sqrt(1.0 + lam)
    r, J = -z * w, J * w[:, :, None]
    quad = np.sum(r ** 2, axis=1)
    limit = stats.chi2.isf(GROSS_P, data.m)
    huber = np.sqrt(np.minimum(1.0, limit / np.maximum(quad, 1e-300)))
    r *= huber[:, None]
    J *= huber[:, None, None]
    n = len(idx)
    side = max(int(MIN_SIDE * n), 20)
    if n < 2 * side + 2:
        return ClockStepStart(float(data.t[idx[n // 2]] - data.t[0]), np.zeros(2), 0.0)
    tau = J[:, :, -1:]
    grid = np.unique(np.linspace(side, n - side, SCAN_SEGMENTS).astype(int))
    coarse = step_scan(r, J, tau, grid, WEAK_SHARE)
    j = int(np.searchsorted(grid, coarse.index))
    lo, hi = grid[max(j - 1, 0)], grid[min(j + 1, len(grid) - 1)]
    fine = step_scan(r, J, tau, np.arange(max(lo, side), min(hi, n - side) + 1), WEAK_SHARE)
    k = fine.index
    # the joint one-step estimate of the offset and the step at the instant found
    C = np.concatenate([J, tau * (np.arange(n) >= k)[:, None, None]], axis=2)
    H = np.einsum('nmi,nmj->ij', C, C)
    g = np.einsum('nmi,nm->i', C, r)
    sol = np.linalg.lstsq(H, g, rcond=1e-12)[0]
    at = 0.5 * (data.t[idx[k - 1]] + data.t[idx[k]]) - data.t[0]
    return ClockStepStart(float(at), np.array([sol[-2], sol[-1]]), fine.gain)
