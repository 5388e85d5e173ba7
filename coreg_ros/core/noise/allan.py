"""
The Allan deviation of a still device's pose: white noise, random walk, drift; how long to average.

The overlapping Allan variance of a signal ``x`` sampled every ``τ0`` (each axis of the
position, m, or of the rotation vector, rad), averaged over ``m`` samples (``τ = m τ0``):

    σ²(τ) = 1 / (2 (N - 2m + 1)) Σ_j (x̄_{j+m} - x̄_j)²

with ``x̄_j`` the mean of ``x[j:j+m]``, pooled over the still segments. Three processes are
fitted to it by non-negative least squares (IEEE Std 952 for gyroscopes, read with the pose
as the signal): white noise of σ per sample (``σ² τ0 / τ``), a random walk of ``q`` m²/s
(``q τ / 3``) and a linear drift of ``R`` m/s (``R² τ² / 2``). ``white`` is the per-sample σ
of the white noise (what a calibration's pairs see); ``tau_limit`` the averaging time beyond
which the random walk or the drift make averaging worse (infinite when neither is seen within
the still time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Averaging factors m: octaves while at least ``MIN_DIFFERENCES`` differences remain.
MIN_DIFFERENCES = 8
#: Improvement of the fit's χ² that a random walk and drift must bring to be claimed (χ² of
#: two degrees of freedom at 99.9 %; the overlapping estimates are correlated across τ, so
#: this is a rough yardstick, kept strict).
DRIFT_CHI2 = 13.8


@dataclass(frozen=True)
class AllanCurve:
    """
    The Allan deviation of one channel (three axes) and the processes fitted to it.

    Attributes
    ----------
    tau : ndarray, shape (K,)
        Averaging times, s.
    adev : ndarray, shape (K, 3)
        Allan deviation per axis (m or rad).
    count : ndarray, shape (K,)
        Differences pooled at each τ.
    tau0 : float
        The sample interval, s.
    white : ndarray, shape (3,)
        White noise σ per sample, per axis.
    random_walk : ndarray, shape (3,)
        Random walk intensity per axis, unit/√s (the σ of the walk after 1 s).
    drift : ndarray, shape (3,)
        Linear drift per axis, unit/s.
    tau_limit : float
        Longest useful averaging time, s (the minimum of the fitted deviation over the axes);
        ``inf`` when no random walk or drift shows within the still time.

    """

    tau: np.ndarray
    adev: np.ndarray
    count: np.ndarray
    tau0: float
    white: np.ndarray
    random_walk: np.ndarray
    drift: np.ndarray
    tau_limit: float

    def as_dict(self) -> dict:
        """JSON form: lists, ``tau_limit_s`` null when infinite."""
        return {'tau_s': self.tau.tolist(), 'adev': self.adev.tolist(),
                'white_sigma': self.white.tolist(),
                'random_walk_per_sqrt_s': self.random_walk.tolist(),
                'drift_per_s': self.drift.tolist(),
                'tau_limit_s': None if not np.isfinite(self.tau_limit) else self.tau_limit}


def allan_sums(x: np.ndarray, max_m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Sum the squared differences of m-sample means of one segment, for m = 1, 2, 4 ... max_m.

    Parameters
    ----------
    x : ndarray, shape (N, 3)
        The segment's samples of one channel.
    max_m : int
        The largest averaging factor.

    Returns
    -------
    m : ndarray of int, shape (K,)
    sums : ndarray, shape (K, 3)
        ``Σ_j (x̄_{j+m} - x̄_j)²`` per axis.
    count : ndarray of int, shape (K,)
        Differences in each sum.

    """
    x = np.asarray(x, dtype=float)
    x = x - x.mean(axis=0)
    c = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    ms, sums, counts = [], [], []
    m = 1
    while m <= max_m and len(x) - 2 * m + 1 >= MIN_DIFFERENCES:
        means = (c[m:] - c[:-m]) / m          # x̄_j, j = 0 .. N - m
        d = means[m:] - means[:-m]            # x̄_{j+m} - x̄_j
        ms.append(m)
        sums.append(np.sum(d * d, axis=0))
        counts.append(len(d))
        m *= 2
    return (np.array(ms, dtype=int), np.array(sums).reshape(-1, x.shape[1]),
            np.array(counts, dtype=int))


def allan_curve(segments: list, tau0: float) -> AllanCurve:
    """
    Return the pooled Allan deviation of still segments and the processes fitted to it.

    Parameters
    ----------
    segments : list of ndarray, each shape (N_k, 3)
        One channel's samples (position m, or rotation vector rad) in each still segment.
    tau0 : float
        The sample interval, s.

    Returns
    -------
    AllanCurve

    """
    longest = max(len(s) for s in segments)
    max_m = max(1, longest // 4)
    # each segment's Allan variance, averaged with the same weight (its length) at every τ:
    # segments of different noise (at different distances) then mix into a white curve
    total = {}
    for x in segments:
        ms, sums, counts = allan_sums(x, max_m)
        for m, s, k in zip(ms, sums, counts, strict=True):
            acc = total.setdefault(int(m), [np.zeros(3), 0.0, 0])
            acc[0] += len(x) * s / (2.0 * k)
            acc[1] += len(x)
            acc[2] += int(k)
    ms = np.array(sorted(total), dtype=int)
    count = np.array([total[m][2] for m in ms], dtype=int)
    avar = np.array([total[m][0] / total[m][1] for m in ms]).reshape(-1, 3)
    tau = ms * tau0
    coef = np.array([_fit(tau, avar[:, k], ms, count) for k in range(3)])  # (3, 3): a, b, c
    white = np.sqrt(coef[:, 0] / tau0)
    random_walk = np.sqrt(3.0 * coef[:, 1])
    drift = np.sqrt(2.0 * coef[:, 2])
    span = sum(len(s) for s in segments) * tau0
    return AllanCurve(tau, np.sqrt(avar), count, float(tau0), white, random_walk, drift,
                      _tau_limit(coef, tau0, span))


def _fit(tau: np.ndarray, avar: np.ndarray, m: np.ndarray, count: np.ndarray) -> np.ndarray:
    """
    Fit (a, b, c) >= 0 of ``a/τ + b τ + c τ²`` to the Allan variance.

    Each point weighed by its relative precision (the overlapping estimator's ~3·count/(4m)
    degrees of freedom), first at the measured value, then at the fitted one (a measured
    value that came out low would otherwise pull the fit down). The random walk and the drift
    are kept only when they improve the fit beyond chance (``DRIFT_CHI2``): white noise alone
    scatters at long τ, where few differences remain.
    """
    rows = np.stack([1.0 / tau, tau, tau ** 2], axis=1)
    precision = np.sqrt(3.0 * count / (4.0 * m))
    full, chi_full = _weighted_nnls(rows, avar, precision)
    white, chi_white = _weighted_nnls(rows[:, :1], avar, precision)
    if chi_white - chi_full < DRIFT_CHI2:
        return np.array([white[0], 0.0, 0.0])
    return full


def _weighted_nnls(rows: np.ndarray, avar: np.ndarray, precision: np.ndarray) -> tuple:
    """Return the reweighted non-negative fit of ``rows @ coef`` to ``avar`` and its χ²."""
    # imported on first use: scipy.optimize adds 0.15 s of CPU to every command's start
    from scipy.optimize import nnls

    scale = np.maximum(avar, 1e-300)
    coef = np.zeros(rows.shape[1])
    for _ in range(3):
        w = precision / scale
        # columns scaled to unit size: nnls is not scale-invariant in practice
        norm = np.maximum(np.linalg.norm(rows * w[:, None], axis=0), 1e-300)
        sol, _ = nnls(rows * w[:, None] / norm, avar * w)
        coef = sol / norm
        scale = np.maximum(rows @ coef, 1e-300)
    return coef, float(np.sum(((rows @ coef - avar) * precision / scale) ** 2))


def _tau_limit(coef: np.ndarray, tau0: float, span: float) -> float:
    """Return the averaging time of the fitted deviation's minimum (inf beyond ``span``)."""
    grid = tau0 * np.logspace(0, 9, 400)
    model = (coef[:, 0:1] / grid + coef[:, 1:2] * grid + coef[:, 2:3] * grid ** 2)
    best = grid[np.argmin(model, axis=1)]
    limit = float(np.min(best))
    return limit if limit < span else float('inf')
