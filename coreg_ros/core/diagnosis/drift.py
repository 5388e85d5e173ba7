"""
The check a clock drift must pass beyond its held-out gain: per-block offsets that trend.

A drift and a constant offset differ only by a slow trend, which other errors (a field
crossed at different times, non-stationary noise) can mimic; the offset fitted on each time
block alone must show it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis.data import DiagData
from coreg_ros.core.diagnosis.fit import Model
from coreg_ros.core.diagnosis.record import optional, Record
import numpy as np


@dataclass(frozen=True, kw_only=True)
class DriftCheck(Record):
    """
    The offsets fitted per time block, and whether they trend with the drift.

    Attributes
    ----------
    block_offsets_s, block_sigma_s, block_mid_s : list of float
        Per block: the offset and its standard uncertainty, and the block's middle, s.
    accepted : bool
    reason : str
    trend_ppm, trend_sigma_ppm : float, optional
        The offsets' linear trend and its standard uncertainty, ppm (three blocks or more).
    drift_ppm : float, optional
        The drift fitted, ppm.

    """

    block_offsets_s: list
    block_sigma_s: list
    block_mid_s: list
    accepted: bool
    reason: str
    trend_ppm: Optional[float] = optional()
    trend_sigma_ppm: Optional[float] = optional()
    drift_ppm: Optional[float] = optional()


def drift_check(data: DiagData, sel, best, cands: list) -> DriftCheck:
    """
    Accept a clock drift only if it beats a constant offset and per-block offsets trend.

    The offset is fitted on each time block alone (``time_offset`` beside the effects already
    accepted); a drift must show as a significant linear trend of those offsets (slope beyond
    3σ, agreeing in sign with the drift and within a factor of three of it), and the drift's
    held-out gain must exceed the constant offset's by the practical threshold.

    Parameters
    ----------
    data : DiagData
        All pairs.
    sel : selection.Selector
        The selection pairs, their time blocks and the practical threshold.
    best : selection.Candidate
        The clock drift candidate.
    cands : list of selection.Candidate
        The round's candidates (the constant offset among them).

    Returns
    -------
    DriftCheck

    """
    K = sel.K
    idx = sel.idx
    taus, sds, mids = [], [], []
    # the offset per block beside the effects already accepted (outliers set aside, a noise
    # level in the weights): without them a block's offset is pulled by what they explain
    others = tuple(n for n in best.names if n != best.name)
    for k in range(K):
        block = idx[sel.tf == k]
        if len(block) < 30:
            continue
        try:
            fit = Model(data, others + ('time_offset',)).fit(best.fit.state, block)
        except (ValueError, np.linalg.LinAlgError):
            continue
        cov = fit.mean_cov()
        sl = fit.model.slices['time_offset']
        if cov is None:
            continue
        taus.append(float(fit.state.theta['time_offset'][0]))
        sds.append(float(np.sqrt(max(cov[sl, sl][0, 0], 1e-30))))
        mids.append(float(np.mean(data.t[block])))
    if len(taus) < 3:
        return DriftCheck(block_offsets_s=taus, block_sigma_s=sds, block_mid_s=mids,
                          accepted=False, reason='too few blocks to see a trend of the offset')
    t = np.array(mids)
    y = np.array(taus)
    w = 1.0 / np.maximum(np.array(sds), 1e-9) ** 2
    # the per-block σ ignores any non-stationary error: widen by the scatter about the line
    A = np.stack([np.ones_like(t), t - np.average(t, weights=w)], axis=1)
    H = A.T @ (A * w[:, None])
    coef = np.linalg.solve(H, A.T @ (w * y))
    res = y - A @ coef
    dof = max(len(y) - 2, 1)
    infl = max(1.0, float(np.sum(w * res ** 2) / dof))
    slope_sd = float(np.sqrt(np.linalg.inv(H)[1, 1] * infl))
    slope = float(coef[1])
    est = best.fit.state.theta['clock_drift']
    kappa = float(est[1]) / max(best.fit.model.duration, 1e-9)
    const = next((c for c in cands if c.name == 'time_offset'), None)
    margin = sel.threshold(0)
    reasons = []
    if abs(slope) < 3.0 * slope_sd:
        reasons.append(f'the per-block offsets show no trend ({slope * 1e6:.1f} ± '
                       f'{slope_sd * 1e6:.1f} ppm)')
    elif not (1.0 / 3.0 <= (slope / kappa if kappa != 0 else np.inf) <= 3.0):
        reasons.append(f'the per-block offsets trend by {slope * 1e6:.1f} ppm, not the '
                       f'{kappa * 1e6:.1f} ppm of the drift fit')
    if const is not None and const.passes and best.gain - const.gain < margin:
        reasons.append('no better than a constant offset on held-out blocks')
    return DriftCheck(block_offsets_s=taus, block_sigma_s=sds, block_mid_s=mids,
                      accepted=not reasons,
                      reason='; '.join(reasons) if reasons else 'per-block offsets trend',
                      trend_ppm=slope * 1e6, trend_sigma_ppm=slope_sd * 1e6,
                      drift_ppm=kappa * 1e6)
