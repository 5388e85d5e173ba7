"""
Locate a gap: where the excess of the base fit's residuals lies (docs/design.md §5 step 2).

By channel, by octant of the workspace, by speed, by time, static against moving, and the
residual-velocity cross-correlation (an error that follows the motion: a clock effect).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis.record import keyed, Record
from coreg_ros.core.distributions import scipy_stats
import numpy as np

#: Lags (in pairs) of the residual-velocity cross-correlation.
XCORR_LAGS = 25
#: Below these speeds a pair counts as static (m/s, rad/s).
STATIC_SPEED = 0.002
STATIC_ANGULAR_SPEED = 0.01


@dataclass(frozen=True)
class BinExcess(Record):
    """
    The excess of the pairs whose value (speed, time) lies in one bin.

    Attributes
    ----------
    from_, to : float
        The bin (keys ``from``, ``to``), in ``unit``.
    unit : str
    n : int
    excess : float
        Mean excess per residual.

    """

    from_: float = keyed('from')
    to: float
    unit: str
    n: int
    excess: float


@dataclass(frozen=True)
class RegionExcess(Record):
    """
    The excess in one octant around the median of B's positions.

    Attributes
    ----------
    octant : str
        ``'+-+'``: above or below the median along x, y, z.
    centre_m : list of float
        The mean position of its pairs, m.
    n : int
    excess : float

    """

    octant: str
    centre_m: list
    n: int
    excess: float


@dataclass(frozen=True)
class PairGroup(Record):
    """The excess of a group of pairs (None without pairs)."""

    n: int
    excess: Optional[float]


@dataclass(frozen=True)
class StaticMoving(Record):
    """The excess of the static pairs against the moving ones."""

    static: PairGroup
    moving: PairGroup


@dataclass(frozen=True, kw_only=True)
class VelocityXcorr(Record):
    """
    The residuals' cross-correlation with the output rate due to A's velocity.

    Attributes
    ----------
    lag_s : list of float
        The lags, s.
    linear, angular : list of float
        The correlation at each lag with the rate due to linear (angular) velocity.
    linear_at_zero, angular_at_zero : float
    linear_peak, linear_peak_lag_s : float
        The largest |correlation| with the linear rate (signed) and its lag, s.

    """

    lag_s: list
    linear: list
    angular: list
    linear_at_zero: float
    angular_at_zero: float
    linear_peak: float
    linear_peak_lag_s: float


@dataclass(frozen=True, kw_only=True)
class Location(Record):
    """
    Where the excess of the normalized squared residuals lies.

    Attributes
    ----------
    mean_excess : float
    by_channel : dict
        Excess per channel (``x``, ``y``, ``z``, and ``rotation`` for full pose).
    by_region : list of RegionExcess
    by_speed, by_time : list of BinExcess
    static_vs_moving : StaticMoving
    velocity_xcorr : VelocityXcorr
    excess_vs_speed_rank_correlation, excess_vs_range_rank_correlation : float
    largest : str
        Where the excess is largest, in words.

    """

    mean_excess: float
    by_channel: dict
    by_region: list
    by_speed: list
    by_time: list
    static_vs_moving: StaticMoving
    velocity_xcorr: VelocityXcorr
    excess_vs_speed_rank_correlation: float
    excess_vs_range_rank_correlation: float
    largest: str


def _binned(values: np.ndarray, excess: np.ndarray, edges: np.ndarray, unit: str) -> list:
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (values >= lo) & (values <= hi)
        if sel.any():
            out.append(BinExcess(float(lo), float(hi), unit, int(sel.sum()),
                                 float(excess[sel].mean())))
    return out


def _xcorr(a: np.ndarray, b: np.ndarray, lags: int) -> tuple[np.ndarray, np.ndarray]:
    """Normalised cross-correlation Σ a(i)·b(i+ℓ) of two (n, d) series for ℓ in ±lags."""
    n = len(a)
    lags = int(min(lags, max(n // 4, 0)))
    den = np.sqrt(np.sum(a * a) * np.sum(b * b))
    out = np.zeros(2 * lags + 1)
    ell = np.arange(-lags, lags + 1)
    if den <= 0:
        return ell, out
    for i, k in enumerate(ell):
        if k >= 0:
            out[i] = np.sum(a[:n - k] * b[k:]) / den
        else:
            out[i] = np.sum(a[-k:] * b[:n + k]) / den
    return ell, out


def locate(*, t: np.ndarray, quad: np.ndarray, e_std: np.ndarray, m: int, has_rotation: bool,
           points: np.ndarray, speed: np.ndarray, angular_speed: np.ndarray,
           fdot_v: np.ndarray, fdot_w: np.ndarray, dt: float, n_time_blocks: int = 10
           ) -> Location:
    """
    Where the excess of the normalized squared residuals lies.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Time of each pair, s.
    quad : ndarray, shape (n,)
        Squared normalized error per pair (stated noise); its mean over m is 1 if the model
        holds, so ``quad / m - 1`` is the excess.
    e_std : ndarray, shape (n, m)
        Raw errors each divided by its standard deviation.
    m : int
        Residuals per pair.
    has_rotation : bool
        Rows 3:6 are rotation (full pose).
    points : ndarray, shape (n, 3)
        B's marker position (B's base frame), m.
    speed, angular_speed : ndarray, shape (n,)
        A's tool speed (m/s) and angular speed (rad/s).
    fdot_v, fdot_w : ndarray, shape (n, m)
        Output rate due to A's linear and angular velocity (normalized like e_std).
    dt : float
        Median time between pairs, s (for the lags).
    n_time_blocks : int
        Blocks of equal duration for ``by_time``.

    Returns
    -------
    Location

    """
    excess = quad / m - 1.0
    channels = {}
    pos_rows = [r for r in range(m) if not (has_rotation and r >= 3)]
    for a, name in enumerate('xyz'):
        rows = [r for r in pos_rows if r % 3 == a]
        channels[name] = float(np.mean(e_std[:, rows] ** 2) - 1.0)
    if has_rotation:
        channels['rotation'] = float(np.mean(e_std[:, 3:6] ** 2) - 1.0)
    # regions: octants around the median of B's positions
    med = np.median(points, axis=0)
    octant = ((points > med) * np.array([1, 2, 4])).sum(axis=1)
    regions = []
    for o in range(8):
        sel = octant == o
        if sel.any():
            regions.append(RegionExcess(''.join('+' if o & b else '-' for b in (1, 2, 4)),
                                        points[sel].mean(axis=0).tolist(), int(sel.sum()),
                                        float(excess[sel].mean())))
    speed_edges = np.unique(np.quantile(speed, np.linspace(0, 1, 6)))
    by_speed = _binned(speed, excess, speed_edges, 'm/s') if len(speed_edges) > 1 else []
    edges_t = np.linspace(t[0], t[-1], n_time_blocks + 1)
    by_time = _binned(t, excess, edges_t, 's')
    static = (speed < STATIC_SPEED) & (angular_speed < STATIC_ANGULAR_SPEED)
    svm = StaticMoving(
        PairGroup(int(static.sum()), float(excess[static].mean()) if static.any() else None),
        PairGroup(int((~static).sum()),
                  float(excess[~static].mean()) if (~static).any() else None))
    lags, cv = _xcorr(e_std, fdot_v, XCORR_LAGS)
    _, cw = _xcorr(e_std, fdot_w, XCORR_LAGS)
    xcorr = VelocityXcorr(
        lag_s=(lags * dt).tolist(), linear=cv.tolist(), angular=cw.tolist(),
        linear_at_zero=float(cv[len(cv) // 2]) if len(cv) else 0.0,
        angular_at_zero=float(cw[len(cw) // 2]) if len(cw) else 0.0,
        linear_peak=float(cv[np.argmax(np.abs(cv))]) if len(cv) else 0.0,
        linear_peak_lag_s=float(lags[np.argmax(np.abs(cv))] * dt) if len(cv) else 0.0)
    corr_speed = _spearman(speed, excess)
    corr_range = _spearman(np.linalg.norm(points, axis=1), excess)
    largest = max(channels, key=lambda k: channels[k])
    parts = [f'channel {largest} (excess {channels[largest]:+.2f})']
    if regions:
        r = max(regions, key=lambda r: r.excess)
        parts.append(f'octant {r.octant} (excess {r.excess:+.2f})')
    if by_time:
        b = max(by_time, key=lambda b: b.excess)
        parts.append(f'time {b.from_:.0f}-{b.to:.0f} s (excess {b.excess:+.2f})')
    return Location(mean_excess=float(excess.mean()), by_channel=channels, by_region=regions,
                    by_speed=by_speed, by_time=by_time, static_vs_moving=svm,
                    velocity_xcorr=xcorr, excess_vs_speed_rank_correlation=corr_speed,
                    excess_vs_range_rank_correlation=corr_range, largest='; '.join(parts))


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    return float(scipy_stats().spearmanr(a, b)[0])
