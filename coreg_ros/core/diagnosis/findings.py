"""
What the report says beyond the accepted effects: stamps, structure left, noise, verdict.

These read the final fit's held-out errors and the findings of the accepted effects, add or
rename findings (jitter named from the stamps, clustered outliers called non-stationary, an
excess left in some blocks only) and write the one-sentence verdict.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from coreg_ros.core.diagnosis import excess as ex
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.causes import Cause
from coreg_ros.core.diagnosis.detect import Detection
from coreg_ros.core.diagnosis.effects.finding import Finding
from coreg_ros.core.diagnosis.effects.local import (
    ClusteredOutliers,
    LocalExcess,
    NonStationaryCandidate,
)
from coreg_ros.core.diagnosis.effects.noise import OutliersCandidate
from coreg_ros.core.diagnosis.effects.registry import CANDIDATES
from coreg_ros.core.diagnosis.gap import GapAfter, GapBefore
from coreg_ros.core.diagnosis.locate import Location
from coreg_ros.core.diagnosis.record import keyed, optional, Record
from coreg_ros.core.diagnosis.residuals import base_errors
from coreg_ros.core.diagnosis.stamps import jitter_finding, StampReport
from coreg_ros.core.diagnosis.structure import leftover, TimeWindow, Unexplained
import numpy as np


@dataclass(frozen=True, kw_only=True)
class ExcessLeft(Record):
    """
    The excess left after the accepted effects, and whether the flagged pairs cluster.

    Attributes
    ----------
    excess_map : excess.ExcessMap
        Where it lies, under the final model's noise (key ``map``).
    flagged_pairs : excess.FlaggedPairs, optional
        Whether the pairs the outlier model set aside cluster (with an outlier model).
    window : structure.TimeWindow, optional
        The window in time whose held-out errors stand out (``structure.time_window``).

    """

    excess_map: ex.ExcessMap = keyed('map')
    flagged_pairs: Optional[ex.FlaggedPairs] = optional()
    window: Optional[TimeWindow] = optional()


@dataclass(frozen=True, kw_only=True)
class NoiseExcess(Record):
    """
    The noise left larger (or smaller) than stated: a description, not a gap closed.

    Attributes
    ----------
    factor : float
        √(χ²/dof) at the stated noise: the residual noise over the stated.
    effects : list of str
        The noise effects found.
    largest_in_time_s : list of float
        The time block where the excess is largest: from, to, s.
    largest_in_workspace_m : list of float
        The centre of the cell where it is largest (B's base frame), m.
    concentrated : bool
        Some blocks or cells carry most of it.
    where : str
    text : str

    """

    factor: float
    effects: list
    largest_in_time_s: list
    largest_in_workspace_m: list
    concentrated: bool
    where: str
    text: str


def _replaced(findings: list, old: Finding, new: Finding) -> list:
    """Return the findings with ``old`` replaced by ``new`` in its place."""
    return [new if f is old else f for f in findings]


def with_stamps(stamps: StampReport, findings: list) -> list:
    """
    Name jitter from the stamps when the residuals did not; add drops and gaps to any finding.

    The stamp jitter goes first when the residuals named nothing structured (their first
    answer then was a noise description the stamps explain).

    Parameters
    ----------
    stamps : StampReport
        ``stamps.stamps_report`` of the recording.
    findings : list of Finding
        The effects found so far.

    Returns
    -------
    list of Finding

    """
    found = jitter_finding(stamps)
    if found is None:
        return findings
    have = next((f for f in findings if f.name == found.name), None)
    if have is not None:
        return _replaced(findings, have,
                         replace(have, estimate=have.estimate.with_stamps(found.estimate)))
    if findings and findings[0].kind == 'structured':
        return findings + [found]
    # a noise answer ahead of it was the jitter seen through the residuals
    return [found] + findings


def structure_checks(data, final, after, counted, findings: list, gap_after: GapAfter,
                     sd: np.ndarray, look_local: bool = True) -> tuple:
    """
    Outliers versus structure, and an excess left in some blocks or cells only.

    Flagged pairs that cluster in time or in the workspace are a structured or
    non-stationary error there, not glitches: the ``outliers`` finding is renamed
    ``non_stationary`` (kind structured) and says where. An outlier share at the model's cap
    is said, never hidden. A structured error left in one window of time that comes and goes
    (``structure.leftover``) adds a ``non_stationary`` finding: no stationary effect explains
    it. What else is left is the ``Unexplained`` structure, by its signature.

    Returns
    -------
    excess_left : ExcessLeft
    findings : list of Finding
    unexplained : structure.Unexplained or None

    """
    flagged = ~counted
    # under the fitted noise model: a noise that grows with range is stationary, not local
    emap = ex.excess_map(data, after.quad, counted)

    def sized(estimate, hot: np.ndarray):
        # how large the local error is where it acts (held-out errors, noise taken off)
        size = ex.local_error_size(data, after.e, hot)
        return estimate if size is None else estimate.sized(size)

    stated_excess = gap_after.stated.counted.chi2_per_dof_at_stated_noise - 1.0
    local = NonStationaryCandidate.name
    window, unexplained = None, None
    if look_local:
        e_in = base_errors(data, final)[0]
        quad_in = vm.loglik(final.state.var, final.stats, with_parts=True)[2]
        window, unexplained = leftover(data, e_in, quad_in, sd, counted, stated_excess, emap)
    comes_and_goes = (window is not None and window.structured and window.kind == 'window'
                      and stated_excess > 0.02)
    inside = np.zeros(data.n, dtype=bool)
    if comes_and_goes:
        inside = (data.t >= window.from_s) & (data.t <= window.to_s)
    found = next((f for f in findings if f.name == OutliersCandidate.name), None)
    cl = None
    if found is not None:
        cl = ex.flagged_clustering(data, flagged)
        at_cap = final.state.var.eps >= vm.MAX_OUTLIER_SHARE * 0.98
        # flagged pairs mostly inside a window that comes and goes are where it acts
        in_window = comes_and_goes and float(np.mean(inside[flagged])) >= 0.5
        if cl.clustered or in_window:
            where = cl.where if cl.clustered else (f'time {window.from_s:.0f}-'
                                                   f'{window.to_s:.0f} s')
            # the flagged pairs are where it acts (the excess map counts them out)
            estimate = sized(ClusteredOutliers.of(cl.count, cl.share, where, at_cap),
                             flagged | inside)
            named = replace(found, name=estimate.name, kind=estimate.kind, estimate=estimate,
                            renamed_from=found.name)
        else:
            named = replace(found, estimate=found.estimate.capped(at_cap).in_runs(cl.runs))
        findings = _replaced(findings, found, named)
    if comes_and_goes and not any(f.name == local for f in findings):
        # a structured error that comes and goes: the library's non-stationary error
        estimate = LocalExcess.of(f'time {window.from_s:.0f}-{window.to_s:.0f} s',
                                  emap.share_in_time_blocks, emap.share_in_cells,
                                  float(np.mean(quad_in[inside & counted]) / data.m) - 1.0)
        findings = findings + [Finding.of(sized(estimate, inside))]
    if comes_and_goes and unexplained is not None:
        # what is left beside the window, at the stated noise
        rest = counted & ~inside
        rest_excess = float(np.mean(after.quad_stated[rest]) / data.m) - 1.0
        unexplained = leftover(data, e_in, quad_in, sd, rest, rest_excess, emap)[1]
    ns = next((f for f in findings if f.name == local), None)
    if ns is not None and CANDIDATES[findings[0].name].sets_noise_level:
        # a local structured error goes before noise descriptions of it (a noise effect
        # never explains the gap)
        findings = [ns] + [f for f in findings if f is not ns]
    return ExcessLeft(excess_map=emap, flagged_pairs=cl, window=window), findings, unexplained


def noise_excess(data, after, counted, findings: list, gap_after: GapAfter
                 ) -> Optional[NoiseExcess]:
    """
    Describe the noise left larger (or smaller) than stated: a description, not a gap closed.

    Returns None when the held-out χ²/dof at the stated noise is within 5 % of one and no
    noise effect was accepted.
    """
    chi = gap_after.stated.counted.chi2_per_dof_at_stated_noise
    noisy = [f.name for f in findings if f.kind == 'noise']
    if abs(chi - 1.0) < 0.05 and not noisy:
        return None
    emap = ex.excess_map(data, after.quad_stated, counted)
    worst_t = max(emap.time_blocks, key=lambda b: b.excess)
    worst_c = max(emap.cells, key=lambda c: c.excess)
    factor = float(np.sqrt(max(chi, 0.0)))
    return NoiseExcess(factor=factor, effects=noisy,
                       largest_in_time_s=[worst_t.from_s, worst_t.to_s],
                       largest_in_workspace_m=worst_c.centre_m,
                       concentrated=emap.concentrated, where=emap.text,
                       text=(f'the residual noise is x {factor:.2f} the stated'
                             + (f' ({", ".join(noisy)})' if noisy else '')))


def verdict(gap: bool, effects: list, not_sep: list, before: GapBefore, after: GapAfter,
            detection: Detection, location: Location,
            noise_excess: Optional[NoiseExcess] = None,
            stamps: Optional[StampReport] = None, cause: Optional[Cause] = None,
            unexplained: Optional[Unexplained] = None) -> str:
    """
    One sentence: no gap, timing issues, a gap nothing explains, noise, or the gap explained.

    Parameters
    ----------
    gap : bool
        Whether a gap was detected.
    effects : list of Finding
        The effects found.
    not_sep : list
        Pairs of effects not separable.
    before, after : GapBefore, GapAfter
        The gap before and after the accepted effects.
    detection, location : Detection, Location
        ``detect.detect`` and ``locate.locate`` of the base fit.
    noise_excess : NoiseExcess, optional
        ``noise_excess`` of the final fit.
    stamps : StampReport, optional
        What the stamps say (from the streams).
    cause : causes.Cause, optional
        A mistake a cheap check names: the answer.
    unexplained : structure.Unexplained, optional
        What no effect of the library explains, by its signature.

    Returns
    -------
    str

    """
    if cause is not None:
        return (f'the recording as given cannot be diagnosed ({cause.check.replace("_", " ")})'
                f': {cause.text}; no effect is looked for until it is fixed')
    if not gap:
        return (f'no gap: the recording fits the model with the stated noise '
                f'(chi2/dof {detection.chi2_per_dof:.3f}, p = {detection.p_value:.2g})')
    if not effects and stamps is not None and stamps.issues:
        return ('timing issues in the stamps, residuals fit the model: '
                + '; '.join(f'{d.device}: {d.text}' for d in stamps.devices))
    if not effects:
        if unexplained is not None:
            return (f'gap detected (chi2/dof {detection.chi2_per_dof:.2f}): no effect of the '
                    f'library explains it; {unexplained.text}')
        return (f'gap detected (chi2/dof {detection.chi2_per_dof:.2f}) but none of the '
                f'candidate effects explains it; largest in {location.largest}')
    parts = []
    for found in effects:
        text = found.name
        if found.estimate.text:
            text += f' {found.estimate.text}'
        if found.not_separable_with:
            text += f' (not separable from {", ".join(found.not_separable_with)})'
        parts.append(text)
    structured = [f for f in effects if f.kind == 'structured']
    share = after.share_of_excess_explained
    b, a = before.stated.counted, after.stated.counted
    numbers = (f'held-out chi2/dof at the stated noise '
               f'{b.chi2_per_dof_at_stated_noise:.2f} -> '
               f'{a.chi2_per_dof_at_stated_noise:.2f}, position RMS '
               f'{b.rms_position_mm:.3f} -> {a.rms_position_mm:.3f} mm '
               f'(stated floor {a.stated_floor_position_mm:.3f} mm)')
    if a.rms_rotation_deg is not None:
        numbers += (f', rotation RMS {b.rms_rotation_deg:.3f} -> '
                    f'{a.rms_rotation_deg:.3f} deg (stated floor '
                    f'{a.stated_floor_rotation_deg:.3f} deg)')
    excluded = after.stated.excluded_pairs.count
    if excluded:
        numbers += f'; {excluded} pairs set aside, counted as unexplained'
    if not structured:
        larger = noise_excess is None or noise_excess.factor >= 1
        return (f'no structured effect: the residuals are noise '
                f'{"larger" if larger else "smaller"} '
                f'than stated ({"; ".join(parts)}); nothing is explained, the noise is '
                f'described: {numbers}')
    verb = 'gap explained by' if share >= 0.5 else 'gap partly explained by'
    if b.chi2_per_dof_at_stated_noise < 1.05:
        # nothing in excess of the stated noise: an effect can be real without a gap
        return (f'found {"; ".join(parts)}; the recording is within the stated noise, so '
                f'there is no excess to explain: {numbers}')
    if share < 0.05:
        verb = 'effects found but the gap did not shrink:'
    left = f'; {unexplained.text}' if unexplained is not None else ''
    return f'{verb} {"; ".join(parts)} ({share * 100:.0f} % of the excess): {numbers}{left}'
