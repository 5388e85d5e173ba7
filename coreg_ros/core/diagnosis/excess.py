"""
Where the excess that is left lies, and how large an error is where it acts.

- ``excess_map``: the excess left per time block and workspace cell, and whether it is
  concentrated (a non-stationary or local error that no stationary effect explains).
- ``flagged_clustering``: whether the pairs an outlier model flags cluster in time or in the
  workspace (then they are structure, not glitches).
- ``local_error_size``: the size of an error that acts at some times only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis.data import grid_cells, time_folds
from coreg_ros.core.diagnosis.record import Record
from coreg_ros.core.diagnosis.timeline import flagged_runs, FlaggedRuns, run_bounds
from coreg_ros.core.distributions import chi2_sf
import numpy as np

#: Time blocks and cells per workspace axis of the excess map.
TIME_BLOCKS = 10
CELLS = 3
#: A block or cell is "where the excess lies" when its mean excess per residual is at least
#: this and this many times the median block's.
LOCAL_EXCESS = 0.2
LOCAL_RATIO = 3.0


@dataclass(frozen=True)
class TimeBlock(Record):
    """
    The excess in one time block.

    Attributes
    ----------
    from_s, to_s : float
        The block, s from the first pair.
    n : int
        Pairs in it.
    excess : float
        Mean excess per residual (χ²/dof minus one).
    stands_out : bool
        Its excess is local: practically and significantly above the other blocks'.

    """

    from_s: float
    to_s: float
    n: int
    excess: float
    stands_out: bool


@dataclass(frozen=True)
class CellExcess(Record):
    """
    The excess in one cell of the workspace.

    Attributes
    ----------
    centre_m : list of float
        The mean position of its pairs (B's first marker, B's base frame), m.
    n : int
    excess : float
    stands_out : bool

    """

    centre_m: list
    n: int
    excess: float
    stands_out: bool


@dataclass(frozen=True, kw_only=True)
class ExcessMap(Record):
    """
    Where the held-out excess lies: time blocks and workspace cells.

    Attributes
    ----------
    time_blocks : list of TimeBlock
    cells : list of CellExcess
    concentrated_in_time, concentrated_in_workspace : bool
        The blocks (cells) that stand out hold most of the excess while being a minority of
        the pairs (in time: not explained by the places visited then).
    explained_by_place : float
        The hot time blocks' excess predicted from the same places at other times, as a share
        of theirs (0 when nothing is concentrated in time).
    share_in_time_blocks, share_in_cells : float
        The share of the excess in the blocks (cells) that stand out.
    concentrated : bool
        In time or in the workspace.
    text : str

    """

    time_blocks: list
    cells: list
    concentrated_in_time: bool
    concentrated_in_workspace: bool
    explained_by_place: float
    share_in_time_blocks: float
    share_in_cells: float
    concentrated: bool
    text: str


@dataclass(frozen=True, kw_only=True)
class FlaggedPairs(Record):
    """
    Whether the pairs an outlier model flags cluster in time or in the workspace.

    Attributes
    ----------
    clustered : bool
        In time or in the workspace.
    in_time, in_workspace : bool
    count : int
        Pairs flagged.
    share : float
        Their share of all pairs.
    p_time, p_workspace : float
        p-values of the homogeneity of the flagged runs over time blocks and cells.
    where : str
    runs : timeline.FlaggedRuns
        The flagged pairs grouped in time: changes, bursts.

    """

    clustered: bool
    in_time: bool
    in_workspace: bool
    count: int
    share: float
    p_time: float
    p_workspace: float
    where: str
    runs: FlaggedRuns


@dataclass(frozen=True)
class LocalSize(Record):
    """
    Size of an error that acts at some times only (held-out errors, noise taken off).

    Attributes
    ----------
    max_mm, rms_mm : float
        The largest and the RMS smoothed position error of the hot pairs, mm.
    noise_mm : float
        What was taken off: the noise's level at the same count, mm.
    from_s, to_s : float
        The hot pairs' span, s.

    """

    max_mm: float
    rms_mm: float
    noise_mm: float
    from_s: float
    to_s: float


def _concentration(excess: np.ndarray, labels: np.ndarray, quad: np.ndarray, m: int) -> dict:
    """Mean excess per label, and which labels stand out (practically and significantly)."""
    out = []
    ids = np.unique(labels)
    means = np.array([excess[labels == i].mean() for i in ids])
    counts = np.array([np.sum(labels == i) for i in ids])
    med = float(np.median(means))
    for i, mu, c in zip(ids, means, counts, strict=True):
        sel = labels == i
        # chi-square of the block's sum against the others' level (scaled by their mean)
        level = max(1.0 + med, 1.0)
        stat = float(np.sum(quad[sel]) / level)
        p = float(chi2_sf(stat, m * int(c)))
        out.append({'label': int(i), 'n': int(c), 'excess': float(mu),
                    'stands_out': bool(mu >= LOCAL_EXCESS and mu >= LOCAL_RATIO * max(med, 0.05)
                                       and p < 1e-6 and c >= 10)})
    return {'median_excess': med, 'blocks': out}


def excess_map(data, quad_stated: np.ndarray, counted: np.ndarray,
               n_blocks: int = TIME_BLOCKS) -> ExcessMap:
    """
    Where the held-out excess (stated noise) lies: time blocks and workspace cells.

    Parameters
    ----------
    data : DiagData
        The pairs.
    quad_stated : ndarray, shape (N,)
        Held-out squared normalised error per pair at the stated noise.
    counted : ndarray of bool, shape (N,)
        Pairs not set aside (the excluded ones are shown apart, not hidden).
    n_blocks : int
        Time blocks of equal duration.

    Returns
    -------
    ExcessMap

    """
    m = data.m
    excess = quad_stated / m - 1.0
    t = data.t
    span = max(float(t[-1] - t[0]), 1e-12)
    tb = time_folds(t, n_blocks)
    pts = data.b_points[:, 0, :]
    cl = grid_cells(pts, CELLS)
    sel = counted if counted.sum() >= 20 else np.ones_like(counted)
    ct = _concentration(excess[sel], tb[sel], quad_stated[sel], m)
    cc = _concentration(excess[sel], cl[sel], quad_stated[sel], m)
    edges = t[0] + span * np.arange(n_blocks + 1) / n_blocks
    time_blocks = [TimeBlock(float(edges[b['label']]), float(edges[b['label'] + 1]), b['n'],
                             b['excess'], b['stands_out']) for b in ct['blocks']]
    cells = [CellExcess(pts[sel][cl[sel] == b['label']].mean(axis=0).tolist(), b['n'],
                        b['excess'], b['stands_out']) for b in cc['blocks']]
    hot_t = [b for b in time_blocks if b.stands_out]
    hot_c = [c for c in cells if c.stands_out]

    def share(blocks):
        # block sums, not pair sums: a pair's own excess is mostly its noise
        pos = [max(b['excess'], 0.0) * b['n'] for b in blocks]
        hot = [max(b['excess'], 0.0) * b['n'] for b in blocks if b['stands_out']]
        return float(sum(hot) / sum(pos)) if sum(pos) > 0 else 0.0

    hot_t_mask = np.isin(tb[sel], [b['label'] for b in ct['blocks'] if b['stands_out']])
    hot_c_mask = np.isin(cl[sel], [b['label'] for b in cc['blocks'] if b['stands_out']])
    # concentrated: the standing-out blocks (or cells) hold most of the excess while being
    # a minority of the pairs
    conc_t = bool(hot_t and share(ct['blocks']) >= 0.5 and hot_t_mask.mean() <= 0.5)
    by_place = 0.0
    if conc_t:
        by_place = explained_by_place(excess[sel], pts[sel], hot_t_mask)
        conc_t = by_place < 0.5
    conc_c = bool(hot_c and share(cc['blocks']) >= 0.5 and hot_c_mask.mean() <= 0.5)
    parts = []
    if conc_t:
        parts.append('time ' + ', '.join(f'{b.from_s:.0f}-{b.to_s:.0f} s' for b in hot_t))
    if conc_c:
        parts.append('workspace cells at ' + '; '.join(
            '[' + ', '.join(f'{v:.2f}' for v in c.centre_m) + '] m' for c in hot_c[:4]))
    return ExcessMap(time_blocks=time_blocks, cells=cells, concentrated_in_time=conc_t,
                     concentrated_in_workspace=conc_c, explained_by_place=by_place,
                     share_in_time_blocks=share(ct['blocks']),
                     share_in_cells=share(cc['blocks']), concentrated=conc_t or conc_c,
                     text='; '.join(parts))


def explained_by_place(ex: np.ndarray, pts: np.ndarray, hot: np.ndarray) -> float:
    """
    How much of the excess at some times the same places show at other times (a share).

    A stationary local error shows in time too when the motion visits its place at some times
    only: the hot pairs' excess is predicted from the ten nearest pairs recorded at other
    times within a tenth of the workspace (same place, other time).

    Parameters
    ----------
    ex : ndarray, shape (N,)
        Excess per pair.
    pts : ndarray, shape (N, 3)
        Where each pair is, m.
    hot : ndarray of bool, shape (N,)
        The pairs at the times in question.

    Returns
    -------
    float
        The predicted excess over the hot pairs' own (inf when the motion never came back to
        those places: time and place cannot be told apart).

    """
    from scipy.spatial import cKDTree

    cold = ~hot
    pred = np.zeros(int(hot.sum()))
    seen = np.zeros(int(hot.sum()), dtype=bool)
    if cold.sum() >= 20:
        radius = 0.1 * float(np.max(np.ptp(pts, axis=0)))
        tree = cKDTree(pts[cold])
        dist, nn = tree.query(pts[hot], k=10, distance_upper_bound=radius)
        ok = np.isfinite(dist)
        seen = ok.sum(axis=1) >= 5
        vals = np.where(ok, ex[cold][np.minimum(nn, cold.sum() - 1)], 0.0)
        pred = np.where(seen, vals.sum(axis=1) / np.maximum(ok.sum(axis=1), 1), 0.0)
    if not seen.any() or seen.mean() < 0.5:
        return float('inf')
    e_hot = float(ex[hot][seen].mean())
    return float(min(pred[seen].mean() / e_hot, 1e3)) if e_hot > 0 else 1.0


def flagged_clustering(data, flagged: np.ndarray, n_blocks: int = TIME_BLOCKS) -> FlaggedPairs:
    """
    Whether flagged pairs cluster in time or in the workspace (then: structure, not glitches).

    The flagged pairs are grouped into runs in time first (``timeline.flagged_runs``): a run
    that lasts seconds is a change; shorter runs are glitch episodes, each counted once.
    Glitches strike at random: the runs per time block and per workspace cell are then
    binomial with the overall rate. A chi-square test of that homogeneity (and a practical
    size: some block holds at least three times the runs it would) says the flagged pairs
    are not outliers but a structured or non-stationary error there.

    Parameters
    ----------
    data : DiagData
        The pairs.
    flagged : ndarray of bool, shape (N,)
        Pairs the outlier model set aside.
    n_blocks : int
        Time blocks of equal duration.

    Returns
    -------
    FlaggedPairs

    """
    n = len(flagged)
    k = int(flagged.sum())
    p_value = {'time': 1.0, 'workspace': 1.0}
    found = {'time': False, 'workspace': False}
    where = []
    runs = flagged_runs(data.t, flagged)
    if runs.changes:
        found['time'] = True
        where.append('time ' + ', '.join(f'{a:.0f}-{b:.0f} s' for a, b in runs.changes[:4])
                     + ' (lasting, not a burst)')
    elif runs.runs >= 8:
        first, _ = run_bounds(flagged, runs.merge_gap)
        episodes = np.zeros(n, dtype=bool)
        episodes[first] = True
        p_value, found, where = _clusters(data, episodes, n_blocks)
    return FlaggedPairs(clustered=found['time'] or found['workspace'], in_time=found['time'],
                        in_workspace=found['workspace'], count=k, share=float(k / max(n, 1)),
                        p_time=p_value['time'], p_workspace=p_value['workspace'],
                        where='; '.join(where), runs=runs)


def _clusters(data, flagged: np.ndarray, n_blocks: int) -> tuple:
    """
    Test the flagged share's homogeneity over time blocks and over cells of the workspace.

    Returns
    -------
    p_value, clustered : dict
        Per ``'time'`` and ``'workspace'``: the p-value, and whether they cluster.
    where : list of str
        Where they cluster.

    """
    n = len(flagged)
    k = int(flagged.sum())
    p_value, found = {}, {}
    t = data.t
    span = max(float(t[-1] - t[0]), 1e-12)
    tb = time_folds(t, n_blocks)
    # A's tool positions: a flagged pair's own B position may be the glitch itself
    pts = data.pos_a
    cl = grid_cells(pts, CELLS)
    share = k / n
    where = []
    for key, labels in (('time', tb), ('workspace', cl)):
        ids, inv = np.unique(labels, return_inverse=True)
        tot = np.bincount(inv)
        hit = np.bincount(inv, weights=flagged.astype(float))
        exp = tot * share
        ok = exp > 0
        stat = float(np.sum((hit[ok] - exp[ok]) ** 2 / (exp[ok] * (1 - share) + 1e-12)))
        p = float(chi2_sf(stat, max(int(ok.sum()) - 1, 1)))
        ratio = hit / np.maximum(exp, 1e-12)
        big = (ratio >= 3.0) & (hit >= 5)
        clustered = bool(p < 1e-6 and big.any())
        p_value[key] = p
        found[key] = clustered
        if clustered and key == 'time':
            edges = t[0] + span * np.arange(n_blocks + 1) / n_blocks
            where.append('time ' + ', '.join(f'{edges[i]:.0f}-{edges[i + 1]:.0f} s'
                                             for i in ids[big]))
        elif clustered:
            cen = [pts[labels == i].mean(axis=0) for i in ids[big]][:4]
            where.append('workspace (A tool) near ' + '; '.join(
                '[' + ', '.join(f'{v:.2f}' for v in c) + '] m' for c in cen))
    return p_value, found, where


def local_error_size(data, e: np.ndarray, hot: np.ndarray, window: int = 5
                     ) -> Optional[LocalSize]:
    """
    Size of an error that acts at some times only: the largest held-out position error there.

    The held-out position errors of B's first marker are smoothed over ``window`` samples
    (the disturbance follows the sensor's path, the noise does not) and their largest norm
    among the ``hot`` pairs is taken; the same statistic of the noise alone, read from the
    other pairs at the same count, is taken off in quadrature.

    Returns
    -------
    LocalSize or None
        None when there are fewer than ``window`` hot or other pairs.

    """
    hot = np.asarray(hot, dtype=bool)
    if hot.sum() < window or (~hot).sum() < window:
        return None
    p = e[:, 0:3]
    kernel = np.ones(window) / window
    s = np.stack([np.convolve(p[:, i], kernel, mode='same') for i in range(3)], axis=1)
    norm = np.linalg.norm(s, axis=1) * 1e3
    # the cold pairs' smoothed error: its level at the count of independent hot samples
    cold = norm[~hot]
    n_eff = max(hot.sum() / window, 1.0)
    noise_max = float(np.quantile(cold, max(0.0, 1.0 - 1.0 / n_eff)))
    noise_rms = float(np.sqrt(np.mean(cold ** 2)))
    peak = float(norm[hot].max())
    rms = float(np.sqrt(np.mean(norm[hot] ** 2)))
    t = np.quantile(data.t[hot], [0.02, 0.98])
    return LocalSize(max_mm=float(np.sqrt(max(peak ** 2 - noise_max ** 2, 0.0))),
                     rms_mm=float(np.sqrt(max(rms ** 2 - noise_rms ** 2, 0.0))),
                     noise_mm=noise_max, from_s=float(t[0]), to_s=float(t[1]))


def hot_time_mask(data, emap: ExcessMap) -> np.ndarray:
    """Pairs in the time blocks of an excess map that stand out."""
    hot = np.zeros(data.n, dtype=bool)
    for b in emap.time_blocks:
        if b.stands_out:
            hot |= (data.t >= b.from_s) & (data.t <= b.to_s)
    return hot
