"""
What the best model still leaves: a window in time, or structure no effect of the library fits.

After the effects found, the held-out errors under the final noise model are searched for
what remains:

- **when** (``time_window``): the time window whose errors are most in excess of the rest (a
  likelihood-ratio scan over windows of the recording, at least ``timeline.CHANGE_S`` long);
  one that stands out and is not explained by the places visited then is a change in time.
  If its errors are smooth in time (they follow the sensor's path: lag-one autocorrelation
  ``SMOOTH_LAG1`` or more) it is a structured error; otherwise the noise changed. A
  structured error that comes and goes is the library's ``non_stationary``; one that stays to
  the end (or was there from the start) is a step.
- **where**: cells of the workspace that hold most of the excess (``excess.excess_map``);
- **tied to** speed, angular speed, the tool's orientation, the distance from B's base (rank
  correlation with the excess);
- **not white**: the held-out errors correlate from pair to pair;
- **which channel**: the position axis or the rotation with the largest excess.

When the excess left at the stated noise is practical (``LEFT_EXCESS``) and one of these
shows, the report says "unexplained structure" with this signature (``Unexplained``) rather
than forcing the nearest name of the library.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core import quaternion as quat
from coreg_ros.core.diagnosis.detect import ljung_box
from coreg_ros.core.diagnosis.excess import explained_by_place
from coreg_ros.core.diagnosis.record import optional, Record
from coreg_ros.core.diagnosis.timeline import CHANGE_S, CHANGE_SAMPLES
from coreg_ros.core.distributions import chi2_sf, scipy_stats
import numpy as np

#: Segments of the recording whose windows are scanned (equal numbers of pairs).
SEGMENTS = 100
#: A window stands out when its likelihood ratio (nats) against the rest is at least this:
#: on clean recordings the largest over all windows stays under about 15.
WINDOW_LR = 30.0
#: ... and its noise variance is at least this share above the rest's.
WINDOW_EXCESS = 0.2
#: A window whose excess is smoother than this (lag-one autocorrelation of the excess over the
#: rest's noise: one for an error that follows the sensor's path, zero for noise that grew)
#: is structure.
SMOOTH_LAG1 = 0.5
#: The held-out excess at the stated noise (χ²/dof minus one) left after the effects from
#: which leftover structure is reported.
LEFT_EXCESS = 0.05
#: A rank correlation of the excess with speed, orientation or distance counts from this size
#: (and p below ``TIED_P``).
TIED_RHO = 0.1
TIED_P = 1e-6
#: The held-out errors are not white when some channel's autocorrelation reaches this (and
#: the Ljung-Box p is below 1e-3).
NOT_WHITE = 0.1


@dataclass(frozen=True, kw_only=True)
class TimeWindow(Record):
    """
    The time window whose held-out errors stand out most from the rest.

    Attributes
    ----------
    from_s, to_s : float
        The window, s from the first pair.
    kind : str
        ``'window'`` (it comes and goes), ``'from'`` (it starts and stays to the end) or
        ``'until'`` (it was there from the start and stops).
    noise_factor : float
        √ of the window's variance over the rest's.
    lag1 : float
        Lag-one autocorrelation of its errors' excess over the rest (``smoothness``).
    structured : bool
        Smooth in time: a structured error, not a change of the noise.
    likelihood_ratio : float
        Against the rest, nats.
    by_place : float
        Its excess predicted from the same places at other times, as a share of its own.

    """

    from_s: float
    to_s: float
    kind: str
    noise_factor: float
    lag1: float
    structured: bool
    likelihood_ratio: float
    by_place: float

    @property
    def text(self) -> str:
        """Return the window in words."""
        what = 'a structured error' if self.structured else f'noise × {self.noise_factor:.2f}'
        if self.kind == 'from':
            return f'{what} from {self.from_s:.1f} s on (a change that stays)'
        if self.kind == 'until':
            return f'{what} until {self.to_s:.1f} s (a change at that instant)'
        return f'{what} in {self.from_s:.1f}-{self.to_s:.1f} s, then back'


@dataclass(frozen=True, kw_only=True)
class Unexplained(Record):
    """
    Held-out structure no effect of the library explains, by its signature.

    Attributes
    ----------
    excess : float
        Held-out χ²/dof at the stated noise minus one, after the effects found.
    channel : str
        The channel with the largest excess (``x``, ``y``, ``z`` of B's base, ``rotation``).
    when : TimeWindow, optional
        A time window or step that stands out.
    where : str, optional
        Workspace cells that hold most of the excess.
    tied_to : dict, optional
        Rank correlations of the excess with ``speed``, ``angular_speed``, ``orientation``
        (the tool's angle from its mean orientation), ``distance`` (from B's base) that count.
    not_white : float, optional
        The largest autocorrelation of the held-out errors, when they are not white.
    text : str

    """

    excess: float
    channel: str
    when: Optional[TimeWindow] = optional()
    where: Optional[str] = optional()
    tied_to: Optional[dict] = optional()
    not_white: Optional[float] = optional()
    text: str


def smoothness(e: np.ndarray, rest: np.ndarray, rest_lag: bool = False) -> float:
    """
    Lag-one autocorrelation of the excess of e (n, m) over the variance of ``rest`` (k, m).

    White noise has no lag-one autocovariance: what e has is its excess's, which over the
    excess variance (e's variance less the rest's, per channel) is one for an error that is
    smooth in time and zero for noise that only grew. With ``rest_lag`` the rest's own lag-one
    autocovariance is taken off too (a smooth error left everywhere is not the excess's).
    """
    if len(e) < 4 or len(rest) < 4:
        return 0.0

    def lag_one(v):
        x = v - v.mean(axis=0)
        return float(np.sum(np.mean(x[1:] * x[:-1], axis=0)))

    cov1 = lag_one(e) - (lag_one(rest) if rest_lag else 0.0)
    excess = float(np.sum(np.clip(np.var(e, axis=0) - np.var(rest, axis=0), 0.0, None)))
    return float(np.clip(cov1 / excess, -1.0, 1.0)) if excess > 0 else 0.0


def time_window(data, quad: np.ndarray, e_std: np.ndarray, counted: np.ndarray,
                excess: np.ndarray) -> Optional[TimeWindow]:
    """
    Scan the windows of the recording for the one whose held-out errors stand out most.

    Parameters
    ----------
    data : DiagData
        The pairs.
    quad : ndarray, shape (N,)
        Held-out squared normalised error per pair under the final noise model.
    e_std : ndarray, shape (N, m)
        Held-out errors over their stated σ (for smoothness).
    counted : ndarray of bool, shape (N,)
        Pairs not set aside.
    excess : ndarray, shape (N,)
        Per-pair excess for the place test.

    Returns
    -------
    TimeWindow or None
        None when no window stands out (``WINDOW_LR``, ``WINDOW_EXCESS``) for at least
        ``CHANGE_S`` and ``CHANGE_SAMPLES``.

    """
    idx = np.flatnonzero(counted)
    n, m = len(idx), data.m
    if n < 4 * CHANGE_SAMPLES:
        return None
    t = data.t[idx]
    q = quad[idx]
    G = int(min(SEGMENTS, n // CHANGE_SAMPLES))
    edges = np.linspace(0, n, G + 1).astype(int)
    cq = np.concatenate([[0.0], np.cumsum(np.add.reduceat(q, edges[:-1]))])
    cn = edges.astype(float)
    a, b = np.triu_indices(G + 1, 1)
    nw = cn[b] - cn[a]
    sw = cq[b] - cq[a]
    no = n - nw
    so = cq[-1] - sw
    span = t[np.minimum(edges[b], n) - 1] - t[edges[a]]
    ok = (nw >= CHANGE_SAMPLES) & (span >= CHANGE_S) & (no >= CHANGE_SAMPLES)
    if not ok.any():
        return None
    with np.errstate(divide='ignore', invalid='ignore'):
        s_all = cq[-1] / (n * m)
        s_w = sw / (nw * m)
        s_o = so / np.maximum(no * m, 1e-300)
        lr = 0.5 * m * (n * np.log(s_all) - nw * np.log(s_w) - no * np.log(s_o))
    lr = np.where(ok & (s_w > s_o) & np.isfinite(lr), lr, -np.inf)
    best = int(np.argmax(lr))
    ratio = float(s_w[best] / max(s_o[best], 1e-300))
    if not (lr[best] >= WINDOW_LR and ratio - 1.0 >= WINDOW_EXCESS):
        return None
    lo, hi = edges[a[best]], edges[b[best]]
    inside = np.zeros(data.n, dtype=bool)
    inside[idx[lo:hi]] = True
    kind = 'window'
    if hi == n:
        kind = 'from'
    elif lo == 0:
        kind = 'until'
    lag1 = smoothness(e_std[idx[lo:hi]], e_std[np.concatenate([idx[:lo], idx[hi:]])])
    by_place = explained_by_place(excess[counted], data.b_points[counted, 0, :], inside[counted])
    return TimeWindow(from_s=float(t[lo]), to_s=float(t[hi - 1]), kind=kind,
                      noise_factor=float(np.sqrt(ratio)), lag1=lag1,
                      structured=bool(lag1 >= SMOOTH_LAG1), likelihood_ratio=float(lr[best]),
                      by_place=by_place)


def _tied(data, excess: np.ndarray, counted: np.ndarray) -> dict:
    """Rank correlations of the excess with what the motion does, those that count."""
    q = np.asarray(data.quat_a)[counted]
    ref = quat.chordal_mean(q)
    angle = np.linalg.norm(quat.log(quat.multiply(q, quat.conjugate(ref))), axis=1)
    out = {}
    for name, x in (('speed', data.speed[counted]), ('angular_speed',
                                                     data.angular_speed[counted]),
                    ('orientation', angle),
                    ('distance', np.linalg.norm(data.b_points[counted, 0, :], axis=1))):
        if len(x) < 10 or np.ptp(x) <= 0:
            continue
        rho, p = scipy_stats().spearmanr(x, excess[counted])
        if np.isfinite(rho) and abs(rho) >= TIED_RHO and p < TIED_P:
            out[name] = float(rho)
    return out


def _not_white(e_std: np.ndarray) -> Optional[float]:
    """Return the largest autocorrelation of e_std's columns, when they are not white."""
    qs, rhos = [], []
    for j in range(e_std.shape[1]):
        q, _, rho = ljung_box(e_std[:, j])
        qs.append(q)
        rhos.append(rho)
    if not rhos or not len(rhos[0]):
        return None
    h = len(rhos[0])
    p = float(chi2_sf(float(np.sum(qs)), h * e_std.shape[1]))
    top = float(np.max(np.abs(np.concatenate(rhos))))
    return top if p < 1e-3 and top >= NOT_WHITE else None


def leftover(data, e: np.ndarray, quad: np.ndarray, sd: np.ndarray, counted: np.ndarray,
             stated_excess: float, emap) -> tuple:
    """
    Find what the final model leaves: a window in time, and structure by its signature.

    Parameters
    ----------
    data : DiagData
        The pairs.
    e : ndarray, shape (N, m)
        The final model's raw errors (in sample: a held-out block of a change in time is
        predicted from a short stretch on one side, which would make a window of its own).
    quad : ndarray, shape (N,)
        Their squared normalised size under the final noise model.
    sd : ndarray, shape (N, m)
        Each raw error's stated σ.
    counted : ndarray of bool, shape (N,)
        Pairs not set aside.
    stated_excess : float
        Held-out χ²/dof at the stated noise minus one, after the effects (the gate).
    emap : excess.ExcessMap
        Where the excess lies under the final noise model.

    Returns
    -------
    window : TimeWindow or None
        A window or step in time (structured or noise).
    unexplained : Unexplained or None
        The signature of what is left, when it is practical and shows some structure.

    """
    m = data.m
    e_std = e / sd
    ex = quad / m - 1.0
    window = time_window(data, quad, e_std, counted, ex)
    if window is not None and window.by_place >= 0.5:
        window = None  # the places visited then, not the time
    if stated_excess < LEFT_EXCESS:
        return window, None
    tied = _tied(data, ex, counted)
    white = _not_white(e_std[counted])
    where = None
    if emap.concentrated_in_workspace:
        hot = [c for c in emap.cells if c.stands_out][:4]
        where = 'workspace cells at ' + '; '.join(
            '[' + ', '.join(f'{v:.2f}' for v in c.centre_m) + '] m' for c in hot)
    if window is None and not tied and white is None and where is None:
        return None, None
    rows = {'x': [r for r in range(m) if r % 3 == 0 and not (data.spec.has_q1 and r >= 3)],
            'y': [r for r in range(m) if r % 3 == 1 and not (data.spec.has_q1 and r >= 3)],
            'z': [r for r in range(m) if r % 3 == 2 and not (data.spec.has_q1 and r >= 3)]}
    if data.spec.has_q1:
        rows['rotation'] = [3, 4, 5]
    by_channel = {k: float(np.mean(e_std[counted][:, v] ** 2)) for k, v in rows.items()}
    channel = max(by_channel, key=by_channel.get)
    parts = [f'excess {stated_excess:.2f} left, largest in channel {channel}']
    if window is not None:
        parts.append('when: ' + window.text)
    if where:
        parts.append('where: ' + where)
    if tied:
        parts.append('tied to ' + ', '.join(f'{k} (ρ {v:+.2f})' for k, v in tied.items()))
    if white is not None:
        parts.append(f'not white (autocorrelation up to {white:.2f})')
    return window, Unexplained(excess=float(stated_excess), channel=channel, when=window,
                               where=where, tied_to=tied or None, not_white=white,
                               text='unexplained structure: ' + '; '.join(parts))
