"""
Detect and locate a gap between a recording and the fitted model (docs/design.md §5 steps 1-2).

Inputs are the base fit's output errors of every pair: the raw error e (n, m), its standard
deviation under the stated noise (n, m), the squared normalized error per pair (chi-square
with m degrees of freedom if the model holds), and the velocities.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

#: Lags of the Ljung-Box whiteness test.
LJUNG_BOX_LAGS = 20
#: Lags (in pairs) of the residual-velocity cross-correlation.
XCORR_LAGS = 25
#: Below these speeds a pair counts as static (m/s, rad/s).
STATIC_SPEED = 0.002
STATIC_ANGULAR_SPEED = 0.01
#: A deviation must be at least this large to count as practically relevant.
PRACTICAL_CHI2 = 0.05
PRACTICAL_AUTOCORR = 0.05
#: Significance level of the detection tests (several tests: strict).
ALPHA = 1e-3


def ljung_box(x: np.ndarray, lags: int = LJUNG_BOX_LAGS):
    """
    Ljung-Box statistic of a series, its p-value and the autocorrelations at lags 1..h.

    Parameters
    ----------
    x : ndarray, shape (n,)
        The series, in time order.
    lags : int
        Largest lag h.

    Returns
    -------
    q : float
    p_value : float
    rho : ndarray, shape (h,)

    """
    x = np.asarray(x, dtype=float)
    n = len(x)
    h = int(min(lags, max(n // 4, 1)))
    x = x - x.mean()
    den = float(np.dot(x, x))
    if n < 8 or den <= 0:
        return 0.0, 1.0, np.zeros(h)
    rho = np.array([np.dot(x[:-k], x[k:]) / den for k in range(1, h + 1)])
    q = float(n * (n + 2) * np.sum(rho ** 2 / (n - np.arange(1, h + 1))))
    return q, float(stats.chi2.sf(q, h)), rho


def detect(quad: np.ndarray, zstd: np.ndarray, m: int, n_params: int) -> dict:
    """
    Chi-square goodness of fit, whiteness and tails of the base fit.

    Parameters
    ----------
    quad : ndarray, shape (n,)
        Squared normalized output error per pair (stated noise).
    zstd : ndarray, shape (n, m)
        Decorrelated errors scaled to unit variance (white N(0, 1) if the model holds).
    m : int
        Residuals per pair.
    n_params : int
        Parameters fitted (φ).

    Returns
    -------
    dict
        ``chi2``, ``dof``, ``chi2_per_dof``, ``p_value`` (upper tail), ``p_value_low`` (lower
        tail: noise smaller than stated), ``ljung_box`` (statistic, dof, p-value, largest
        autocorrelation), ``tails`` (excess kurtosis, share beyond 4σ and expected, count of
        pairs beyond the 1e-6 quantile and expected), ``flags`` (which tests found a
        practically relevant gap), ``gap``.

    """
    n = len(quad)
    chi2 = float(np.sum(quad))
    dof = max(n * m - n_params, 1)
    ratio = chi2 / dof
    p_hi = float(stats.chi2.sf(chi2, dof))
    p_lo = float(stats.chi2.cdf(chi2, dof))
    qs, rhos = [], []
    for j in range(zstd.shape[1]):
        q, _, rho = ljung_box(zstd[:, j])
        qs.append(q)
        rhos.append(rho)
    h = len(rhos[0]) if rhos else 1
    q_total = float(np.sum(qs))
    lb_dof = h * zstd.shape[1]
    p_lb = float(stats.chi2.sf(q_total, lb_dof))
    rho_max = float(np.max(np.abs(np.concatenate(rhos)))) if rhos else 0.0
    rho1 = float(np.mean([r[0] for r in rhos])) if rhos else 0.0
    flat = zstd.reshape(-1)
    kurt = float(stats.kurtosis(flat)) if flat.size > 3 else 0.0
    beyond4 = float(np.mean(np.abs(flat) > 4.0))
    expected4 = float(2.0 * stats.norm.sf(4.0))
    limit = stats.chi2.isf(1e-6, m)
    gross = int(np.sum(quad > limit))
    expected_gross = 1e-6 * n
    p_tail = float(stats.poisson.sf(gross - 1, max(expected_gross, 1e-12)))
    flags = {
        'chi2_high': bool(p_hi < ALPHA and ratio > 1.0 + PRACTICAL_CHI2),
        'chi2_low': bool(p_lo < ALPHA and ratio < 1.0 - PRACTICAL_CHI2),
        'not_white': bool(p_lb < ALPHA and rho_max > PRACTICAL_AUTOCORR),
        'heavy_tails': bool(p_tail < ALPHA and gross >= max(3, 0.001 * n)),
    }
    return {
        'chi2': chi2, 'dof': int(dof), 'chi2_per_dof': ratio, 'p_value': p_hi,
        'p_value_low': p_lo,
        'ljung_box': {'statistic': q_total, 'dof': int(lb_dof), 'p_value': p_lb,
                      'max_autocorrelation': rho_max, 'lag1_autocorrelation': rho1},
        'tails': {'excess_kurtosis': kurt, 'share_beyond_4sigma': beyond4,
                  'expected_share_beyond_4sigma': expected4, 'gross_pairs': gross,
                  'expected_gross_pairs': expected_gross, 'p_value': p_tail},
        'flags': flags,
        'gap': bool(any(flags.values())),
    }


def _binned(values: np.ndarray, excess: np.ndarray, edges: np.ndarray, unit: str) -> list:
    out = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (values >= lo) & (values <= hi)
        if sel.any():
            out.append({'from': float(lo), 'to': float(hi), 'unit': unit, 'n': int(sel.sum()),
                        'excess': float(excess[sel].mean())})
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
           fdot_v: np.ndarray, fdot_w: np.ndarray, dt: float, n_time_blocks: int = 10) -> dict:
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
    dict
        ``by_channel``, ``by_region``, ``by_speed``, ``by_time``, ``static_vs_moving``,
        ``velocity_xcorr`` (lags in s, correlations with linear and angular velocity, peaks)
        and ``largest`` (a short description of where the excess is largest).

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
            regions.append({'octant': ''.join('+' if o & b else '-' for b in (1, 2, 4)),
                            'centre_m': points[sel].mean(axis=0).tolist(), 'n': int(sel.sum()),
                            'excess': float(excess[sel].mean())})
    speed_edges = np.unique(np.quantile(speed, np.linspace(0, 1, 6)))
    by_speed = _binned(speed, excess, speed_edges, 'm/s') if len(speed_edges) > 1 else []
    edges_t = np.linspace(t[0], t[-1], n_time_blocks + 1)
    by_time = _binned(t, excess, edges_t, 's')
    static = (speed < STATIC_SPEED) & (angular_speed < STATIC_ANGULAR_SPEED)
    svm = {'static': {'n': int(static.sum()),
                      'excess': float(excess[static].mean()) if static.any() else None},
           'moving': {'n': int((~static).sum()),
                      'excess': float(excess[~static].mean()) if (~static).any() else None}}
    lags, cv = _xcorr(e_std, fdot_v, XCORR_LAGS)
    _, cw = _xcorr(e_std, fdot_w, XCORR_LAGS)
    xcorr = {'lag_s': (lags * dt).tolist(), 'linear': cv.tolist(), 'angular': cw.tolist(),
             'linear_at_zero': float(cv[len(cv) // 2]) if len(cv) else 0.0,
             'angular_at_zero': float(cw[len(cw) // 2]) if len(cw) else 0.0,
             'linear_peak': float(cv[np.argmax(np.abs(cv))]) if len(cv) else 0.0,
             'linear_peak_lag_s': float(lags[np.argmax(np.abs(cv))] * dt) if len(cv) else 0.0}
    corr_speed = _spearman(speed, excess)
    corr_range = _spearman(np.linalg.norm(points, axis=1), excess)
    largest = max(channels, key=lambda k: channels[k])
    parts = [f'channel {largest} (excess {channels[largest]:+.2f})']
    if regions:
        r = max(regions, key=lambda r: r['excess'])
        parts.append(f'octant {r["octant"]} (excess {r["excess"]:+.2f})')
    if by_time:
        b = max(by_time, key=lambda b: b['excess'])
        parts.append(f'time {b["from"]:.0f}-{b["to"]:.0f} s (excess {b["excess"]:+.2f})')
    return {
        'mean_excess': float(excess.mean()),
        'by_channel': channels, 'by_region': regions, 'by_speed': by_speed,
        'by_time': by_time, 'static_vs_moving': svm, 'velocity_xcorr': xcorr,
        'excess_vs_speed_rank_correlation': corr_speed,
        'excess_vs_range_rank_correlation': corr_range,
        'largest': '; '.join(parts),
    }


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    return float(stats.spearmanr(a, b)[0])
