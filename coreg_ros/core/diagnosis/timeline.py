"""
Changes in time: the time scale that tells a burst of glitches from a change.

Pairs an outlier model sets aside are grouped into runs in time (``flagged_runs``). A glitch
strikes a few samples and is gone (a marker occluded for a moment, a reflection); a change
stays, or lasts seconds (metal brought near an EM sensor, a marker that slipped). So a run is
a **change** when it lasts at least ``CHANGE_S`` and ``CHANGE_SAMPLES`` samples and is far
denser than random glitches would make it: in glitch episodes (samples flagged in a row, the
unit a glitch strikes in: a burst of five samples is one episode) at the recording's episode
rate, or because a single episode itself lasts that long; shorter runs are **bursts**, whose
lengths are reported with the outliers. Runs are what is counted when
the flagged pairs are tested for clustering in time or in the workspace: a burst of five
samples is one glitch episode, not five independent ones.
"""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core.diagnosis.record import Record
from coreg_ros.core.distributions import scipy_stats
import numpy as np

#: A run of flagged pairs lasting at least this long (s) ...
CHANGE_S = 1.0
#: ... and this many samples is a change, not a burst of glitches ...
CHANGE_SAMPLES = 10
#: ... when random flagging at the overall share would make so dense a run with at most this
#: probability anywhere in the recording.
CHANGE_P = 1e-6
#: Flagged pairs are merged into one run across gaps up to the length at which random
#: flagging would merge them with this probability (adapts to the share flagged).
MERGE_P = 0.5


@dataclass(frozen=True, kw_only=True)
class FlaggedRuns(Record):
    """
    The flagged pairs grouped in time.

    Attributes
    ----------
    runs : int
        Runs (a run: flagged pairs at most ``merge_gap`` samples apart).
    merge_gap : int
        The largest gap (samples) merged.
    changes : list of [float, float]
        Runs that are changes: from, to, s from the first pair.
    median_length, max_length : int
        Samples in a row flagged (adjacent flagged pairs).
    bursts : bool
        Flagged pairs come several in a row (median two or more), none of them a change.

    """

    runs: int
    merge_gap: int
    changes: list
    median_length: int
    max_length: int
    bursts: bool


def run_bounds(flagged: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the first and last index of each run of flagged pairs at most ``gap`` apart.

    Parameters
    ----------
    flagged : ndarray of bool, shape (N,)
        In time order.
    gap : int
        Largest gap in samples between two flagged pairs of one run (1: adjacent only).

    Returns
    -------
    first, last : ndarray of int, shape (R,)

    """
    idx = np.flatnonzero(flagged)
    if idx.size == 0:
        return idx, idx
    cut = np.flatnonzero(np.diff(idx) > gap)
    first = idx[np.concatenate([[0], cut + 1])]
    last = idx[np.concatenate([cut, [idx.size - 1]])]
    return first, last


def merge_gap(share: float) -> int:
    """Largest gap (samples) random flagging at ``share`` bridges with probability MERGE_P."""
    if share <= 0.0 or share >= 1.0:
        return 1
    return max(1, int(np.log(1.0 - MERGE_P) / np.log(1.0 - share)))


def flagged_runs(t: np.ndarray, flagged: np.ndarray) -> FlaggedRuns:
    """
    Group the flagged pairs into runs; tell the changes among them from bursts.

    Parameters
    ----------
    t : ndarray, shape (N,)
        Time of each pair, s, increasing.
    flagged : ndarray of bool, shape (N,)
        Pairs the outlier model set aside.

    Returns
    -------
    FlaggedRuns

    """
    n = len(flagged)
    k = int(flagged.sum())
    share = k / max(n, 1)
    gap = merge_gap(share)
    first, last = run_bounds(flagged, gap)
    if first.size == 0:
        return FlaggedRuns(runs=0, merge_gap=gap, changes=[], median_length=0, max_length=0,
                           bursts=False)
    length = last - first + 1
    span = t[last] - t[first]
    # the episodes: samples flagged in a row. Glitches strike episodes at random (a burst of
    # a few samples is one), so a run's density is judged in episodes at the episode rate:
    # counted in samples, two bursts a second apart would read as a change
    a, b = run_bounds(flagged, 1)
    row = b - a + 1
    lo = np.searchsorted(a, first, side='left')
    episodes = np.searchsorted(a, last, side='right') - lo
    # so many episodes in a run anywhere in the recording by chance: binomial tail, times
    # the places
    tail = scipy_stats().binom.sf(episodes - 1, length, a.size / max(n, 1)) * n
    # a single episode of a change's number of samples is no glitch either: a glitch strikes
    # a few (each run holds the episodes from lo on, in order)
    lasting = row >= CHANGE_SAMPLES
    dense = (tail < CHANGE_P) | (np.maximum.reduceat(lasting, lo) if lo.size else lasting[:0])
    change = (span >= CHANGE_S) & (length >= CHANGE_SAMPLES) & dense
    changes = [[float(t[f] - t[0]), float(t[la] - t[0])]
               for f, la in zip(first[change], last[change], strict=True)]
    return FlaggedRuns(runs=int(first.size), merge_gap=gap, changes=changes,
                       median_length=int(np.median(row)), max_length=int(row.max()),
                       bursts=bool(not changes and np.median(row) >= 2))


@dataclass(frozen=True)
class StepScan:
    """
    Where a step in some parameters fits best, and how much it gains there.

    Attributes
    ----------
    index : int
        The first pair after the step (of the pairs scanned).
    gain : float
        Its one-step log-likelihood gain, nats.
    step : ndarray, shape (q,)
        The step's one-step estimate.
    profile : ndarray, shape (K,)
        The gain at each candidate split.

    """

    index: int
    gain: float
    step: np.ndarray
    profile: np.ndarray


def _pinv_psd(A: np.ndarray, weak: float) -> np.ndarray:
    """Pseudo-inverse of a PSD matrix along the directions it determines (unit diagonal)."""
    d = np.sqrt(np.clip(np.diag(A), 0.0, None))
    s = np.where(d > 0, d, 1.0)
    w, V = np.linalg.eigh(A / np.outer(s, s))
    keep = w > weak * max(float(w[-1]), 0.0)
    return (V[:, keep] / w[keep]) @ V[:, keep].T / np.outer(s, s)


def step_scan(r: np.ndarray, X: np.ndarray, C: np.ndarray, splits: np.ndarray,
              weak: float = 1e-5) -> StepScan:
    """
    Score scan of a step in parameters ``C`` at candidate splits, with ``X`` common nuisance.

    The model ``r ≈ X a + 1[i ≥ k] C d`` (whitened residuals of a fit, its columns X, and the
    columns C of the parameters that step at pair k): at the fit (a at its optimum) the
    one-step gain of letting d differ from zero after k is ``½ g_kᵀ S_k⁻¹ g_k`` with
    ``g_k = Σ_{i≥k} Cᵢᵀrᵢ - U_kᵀ A⁺ b``, ``S_k = Σ_{i≥k} CᵢᵀCᵢ - U_kᵀ A⁺ U_k``,
    ``U_k = Σ_{i≥k} XᵢᵀCᵢ``, ``A = Σ XᵢᵀXᵢ``, ``b = Σ Xᵢᵀrᵢ`` (b need not vanish: C may share
    a column with X that the fit did not have). Sums over segments, so the cost is one pass.

    Parameters
    ----------
    r : ndarray, shape (n, m)
        Whitened residuals, in time order.
    X : ndarray, shape (n, m, p)
        Whitened columns common to the whole recording.
    C : ndarray, shape (n, m, q)
        Whitened columns of the parameters that step.
    splits : ndarray of int, shape (K,)
        Candidate first pairs after the step, increasing, in 1..n-1.
    weak : float
        Directions of A (unit diagonal) at or below this share of the largest are not used.

    Returns
    -------
    StepScan

    """
    q = C.shape[2]
    A = np.einsum('nmi,nmj->ij', X, X)
    b = np.einsum('nmi,nm->i', X, r)
    Ainv = _pinv_psd(A, weak)
    # sums over the segments [splits[j], splits[j+1]) (the last to the end), then from each
    # split to the end
    seg_cr = np.add.reduceat(np.einsum('nmi,nm->ni', C, r), splits, axis=0)
    seg_cc = np.add.reduceat(np.einsum('nmi,nmj->nij', C, C), splits, axis=0)
    seg_xc = np.add.reduceat(np.einsum('nmi,nmj->nij', X, C), splits, axis=0)
    cr = np.cumsum(seg_cr[::-1], axis=0)[::-1]
    cc = np.cumsum(seg_cc[::-1], axis=0)[::-1]
    xc = np.cumsum(seg_xc[::-1], axis=0)[::-1]
    g = cr - np.einsum('kpq,p->kq', xc, Ainv @ b)
    S = cc - np.einsum('kpq,pr,krs->kqs', xc, Ainv, xc)
    S = 0.5 * (S + np.transpose(S, (0, 2, 1)))
    gain = np.zeros(len(splits))
    steps = np.zeros((len(splits), q))
    for k in range(len(splits)):
        try:
            d = np.linalg.lstsq(S[k], g[k], rcond=1e-10)[0]
        except np.linalg.LinAlgError:
            continue
        steps[k] = d
        gain[k] = 0.5 * float(g[k] @ d)
    best = int(np.argmax(gain))
    return StepScan(index=int(splits[best]), gain=float(gain[best]), step=steps[best],
                    profile=gain)
