"""
Changes that stay: where in time a step of the clock, the calibration or the noise fits best.

A clock that jumps (an NTP correction, a driver restart) moves B's offset from τ before to
τ + Δ after some instant; a bumped base moves T0, a marker that slips moves T1; metal
brought near an EM tracker raises its noise. Each instant is located once per recording,
before the effects are scored, from the base fit:

- clock and pose steps by a score scan (``timeline.step_scan``): the whitened residuals and
  columns of the base model (with a time offset for the clock: its column −J_x ẋ_A), the
  stepping columns (the offset's, or all of the calibration's in the tangent coordinates)
  after each candidate pair; the candidate that gains most is the step;
- a noise step by the likelihood ratio of a change of the noise's variance at each split.

The effects (``clock_step``, ``pose_step``, ``noise_step``) then fit their sizes with the
instant held (``terms.StepShift``, ``terms.PoseStep``, the noise model's ``log_f``).
"""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core.calibration.observability import tangent_matrix, WEAK_SHARE
from coreg_ros.core.diagnosis.data import DiagData
from coreg_ros.core.diagnosis.fit import Model, State
from coreg_ros.core.diagnosis.timeline import step_scan
from coreg_ros.core.distributions import chi2_isf
import numpy as np

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
    n = len(idx)
    side, grid = _scan_grid(n)
    if n < 2 * side + 2:
        return ClockStepStart(float(data.t[idx[n // 2]] - data.t[0]), np.zeros(2), 0.0)
    r, J = _whitened(data, state, idx, ('time_offset',))
    tau = J[:, :, -1:]
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


@dataclass(frozen=True)
class Instant:
    """
    Where a change in time fits best.

    Attributes
    ----------
    at_s : float
        The instant, s from the first pair.
    gain : float
        The scan's gain there, nats.

    """

    at_s: float
    gain: float


def _scan_grid(n: int) -> tuple:
    """Return the pairs kept on either side and the coarse candidate splits."""
    side = max(int(MIN_SIDE * n), 20)
    return side, np.unique(np.linspace(side, n - side, SCAN_SEGMENTS).astype(int))


def _whitened(data: DiagData, state: State, idx: np.ndarray, names: tuple) -> tuple:
    """Whitened residuals (n, m) and columns (n, m, p) of a model at the base state, Huber."""
    model = Model(data, names)
    st = model.initial_state(state)
    parts = [model.evaluate(st, ch) for ch in model.chunks(idx)]
    z = np.concatenate([p.st.z for p in parts])
    lam = np.concatenate([p.st.lam for p in parts])
    J = np.concatenate([p.Jz for p in parts])
    w = 1.0 / np.sqrt(1.0 + lam)
    r, J = -z * w, J * w[:, :, None]
    quad = np.sum(r ** 2, axis=1)
    huber = np.sqrt(np.minimum(1.0, chi2_isf(GROSS_P, data.m) / np.maximum(quad, 1e-300)))
    return r * huber[:, None], J * huber[:, None, None]


def locate_pose_step(data: DiagData, state: State, idx: np.ndarray) -> Instant:
    """
    Locate a step of the calibration (T0 or T1 moved) on the pairs ``idx`` from the base fit.

    Parameters
    ----------
    data : DiagData
        The pairs.
    state : fit.State
        The base model's state.
    idx : ndarray of int
        The pairs scanned, in time order.

    Returns
    -------
    Instant

    """
    n = len(idx)
    side, grid = _scan_grid(n)
    if n < 2 * side + 2:
        return Instant(float(data.t[idx[n // 2]] - data.t[0]), 0.0)
    # a constant clock offset among the common columns: its errors must not pass for a step
    r, X = _whitened(data, state, idx, ('time_offset',))
    J = np.matmul(X[:, :, :-1], np.linalg.inv(tangent_matrix(state.params)))
    coarse = step_scan(r, X, J, grid, WEAK_SHARE)
    j = int(np.searchsorted(grid, coarse.index))
    lo, hi = grid[max(j - 1, 0)], grid[min(j + 1, len(grid) - 1)]
    fine = step_scan(r, X, J, np.arange(max(lo, side), min(hi, n - side) + 1), WEAK_SHARE)
    k = fine.index
    return Instant(float(0.5 * (data.t[idx[k - 1]] + data.t[idx[k]]) - data.t[0]), fine.gain)


def locate_noise_step(data: DiagData, quad: np.ndarray, idx: np.ndarray) -> Instant:
    """
    Locate a step of the noise's variance from the base fit's squared errors ``quad``.

    The likelihood ratio of a variance s₁² before and s₂² after each split against one
    s², ``½ m (N ln s² - k ln s₁² - (N - k) ln s₂²)``, on the squared errors capped at the
    ``GROSS_P`` tail (glitches do not make a noise level).

    Parameters
    ----------
    data : DiagData
        The pairs.
    quad : ndarray, shape (N,)
        The base fit's squared normalised error per pair (all pairs).
    idx : ndarray of int
        The pairs scanned, in time order.

    Returns
    -------
    Instant

    """
    m = data.m
    q = np.minimum(quad[idx], chi2_isf(GROSS_P, m))
    n = len(q)
    side, _ = _scan_grid(n)
    if n < 2 * side + 2:
        return Instant(float(data.t[idx[n // 2]] - data.t[0]), 0.0)
    c = np.cumsum(q)
    k = np.arange(side, n - side)
    s1 = c[k - 1] / (k * m)
    s2 = (c[-1] - c[k - 1]) / ((n - k) * m)
    s = c[-1] / (n * m)
    lr = 0.5 * m * (n * np.log(s) - k * np.log(s1) - (n - k) * np.log(s2))
    best = int(np.argmax(lr))
    kk = int(k[best])
    return Instant(float(0.5 * (data.t[idx[kk - 1]] + data.t[idx[kk]]) - data.t[0]),
                   float(lr[best]))
