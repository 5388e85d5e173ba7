"""
What the report says beyond the accepted effects: stamps, structure left, noise, verdict.

These read the final fit's held-out errors and the rows of the accepted effects, add or
rename rows (jitter named from the stamps, clustered outliers called non-stationary, an
excess left in some blocks only) and write the one-sentence verdict.
"""

from __future__ import annotations

from typing import Optional

from coreg_ros.core.diagnosis import gap as gp
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.stamps import jitter_row
import numpy as np


def stamp_rows(stamps: dict, rows: list) -> None:
    """
    Name jitter from the stamps when the residuals did not; add drops and gaps to any row.

    The stamp jitter goes first when the residuals named nothing structured (their first
    answer then was a noise description the stamps explain).
    """
    row = jitter_row(stamps)
    if row is None:
        return
    have = next((r for r in rows if r['name'] == 'timestamp_jitter'), None)
    if have is not None:
        have['estimate']['sigma_s_from_stamps'] = row['estimate']['sigma_s']
        have['estimate']['dropped'] = row['estimate']['dropped']
        have['estimate']['gaps'] = row['estimate']['gaps']
        have['estimate']['text'] += f' (stamps: {row["estimate"]["text"]})'
        return
    if rows and rows[0]['kind'] == 'structured':
        rows.append(row)
    else:
        # a noise answer ahead of it was the jitter seen through the residuals
        rows[:] = [row] + rows


def structure_checks(data, final, after, counted, rows: list, gap_after: dict) -> dict:
    """
    Outliers versus structure, and an excess left in some blocks or cells only.

    Flagged pairs that cluster in time or in the workspace are a structured or
    non-stationary error there, not glitches: the ``outliers`` row is renamed
    ``non_stationary`` (kind structured) and says where. An outlier share at the model's cap
    is said, never hidden. An excess left after the accepted effects that is concentrated in
    some time blocks or workspace cells adds a ``non_stationary`` row: no stationary effect
    explains it.
    """
    out = {}
    flagged = ~counted
    # under the fitted noise model: a noise that grows with range is stationary, not local
    emap = gp.excess_map(data, after.quad, counted)
    out['map'] = emap

    def sized(estimate: dict, hot: np.ndarray) -> dict:
        # how large the local error is where it acts (held-out errors, noise taken off)
        size = gp.local_error_size(data, after.e, hot)
        if size:
            estimate.update(max_mm=size['max_mm'], rms_mm=size['rms_mm'],
                            window_s=[size['from_s'], size['to_s']])
            estimate['text'] += (f'; up to {size["max_mm"]:.2f} mm (RMS {size["rms_mm"]:.2f}'
                                 f' mm) in {size["from_s"]:.0f}-{size["to_s"]:.0f} s')
        return estimate

    hot_t = gp.hot_time_mask(data, emap)
    row = next((r for r in rows if r['name'] == 'outliers'), None)
    if row is not None:
        cl = gp.flagged_clustering(data, flagged)
        out['flagged_pairs'] = cl
        at_cap = final.state.var.eps >= vm.MAX_OUTLIER_SHARE * 0.98
        row['estimate']['at_cap'] = bool(at_cap)
        if at_cap:
            row['estimate']['text'] += (f' (at the cap of {vm.MAX_OUTLIER_SHARE * 100:.0f} %: '
                                        'more pairs lie outside the stated noise; these are '
                                        'not glitches)')
        if cl['clustered'] or at_cap:
            row['name'] = 'non_stationary'
            row['kind'] = 'structured'
            row['from'] = 'outliers'
            where = cl['where'] or 'throughout'
            row['estimate'] = {
                'flagged_pairs': cl['count'], 'flagged_share': cl['share'],
                'where': cl['where'], 'at_cap': bool(at_cap),
                'text': (f'structured/non-stationary error here: {where} '
                         f'({cl["count"]} pairs, {cl["share"] * 100:.1f} %, flagged in '
                         'clusters, not at random)')}
            # the flagged pairs are where it acts (the excess map counts them out)
            row['estimate'] = sized(row['estimate'], flagged)
    ex_after = float(np.mean(after.quad[counted]) / data.m) - 1.0
    stated_excess = gap_after['chi2_per_dof_at_stated_noise'] - 1.0
    if (emap['concentrated_in_time'] and ex_after > 0.02 and stated_excess > 0.02
            and not any(r['name'] == 'non_stationary' for r in rows)):
        rows.append({'name': 'non_stationary', 'kind': 'structured',
                     'estimate': {'where': emap['text'],
                                  'share_in_time_blocks': emap['share_in_time_blocks'],
                                  'share_in_cells': emap['share_in_cells'],
                                  'excess_after': ex_after,
                                  'text': (f'excess left in {emap["text"]} only: no '
                                           'stationary effect explains it')},
                     'held_out_gain': 0.0, 'held_out_gain_per_residual': 0.0,
                     'blocks_improved': 0, 'blocks': 0})
        rows[-1]['estimate'] = sized(rows[-1]['estimate'], hot_t)
    ns = next((r for r in rows if r['name'] == 'non_stationary'), None)
    if ns is not None and rows[0]['name'] in ('distance_noise', 'noise_scale'):
        # a local structured error goes before noise descriptions of it (a noise effect
        # never explains the gap)
        rows.remove(ns)
        rows.insert(0, ns)
    return out


def noise_excess(data, final, after, counted, rows: list, gap_after: dict) -> Optional[dict]:
    """
    Describe the noise left larger (or smaller) than stated: a description, not a gap closed.

    Returns None when the held-out χ²/dof at the stated noise is within 5 % of one and no
    noise effect was accepted.
    """
    chi = gap_after['chi2_per_dof_at_stated_noise']
    noise_rows = [r for r in rows if r['kind'] == 'noise']
    if abs(chi - 1.0) < 0.05 and not noise_rows:
        return None
    emap = gp.excess_map(data, after.quad_stated, counted)
    worst_t = max(emap['time_blocks'], key=lambda b: b['excess'])
    worst_c = max(emap['cells'], key=lambda c: c['excess'])
    out = {'factor': float(np.sqrt(max(chi, 0.0))),
           'effects': [r['name'] for r in noise_rows],
           'largest_in_time_s': [worst_t['from_s'], worst_t['to_s']],
           'largest_in_workspace_m': worst_c['centre_m'],
           'concentrated': emap['concentrated'], 'where': emap['text']}
    var = final.state.var
    if 'distance_noise' in final.model.var_names:
        out['distance_exponent'] = float(var.k)
    if 'noise_scale' in final.model.var_names:
        out['noise_scale'] = float(np.exp(0.5 * var.log_s2))
    out['text'] = (f'the residual noise is x {out["factor"]:.2f} the stated'
                   + (f' ({", ".join(out["effects"])})' if out['effects'] else ''))
    return out


def verdict(gap: bool, effects: list, not_sep: list, before: dict, after: dict,
            detection: dict, location: dict, noise_excess: Optional[dict] = None) -> str:
    """
    One sentence: no gap, a gap nothing explains, noise described, or the gap explained.

    Parameters
    ----------
    gap : bool
        Whether a gap was detected.
    effects : list of dict
        The report's effect rows.
    not_sep : list
        Pairs of effects not separable.
    before, after : dict
        The gap measures before and after the accepted effects.
    detection, location : dict
        ``detect.detect`` and ``detect.locate`` of the base fit.
    noise_excess : dict, optional
        ``noise_excess`` of the final fit.

    Returns
    -------
    str

    """
    if not gap:
        return (f'no gap: the recording fits the model with the stated noise '
                f'(chi2/dof {detection["chi2_per_dof"]:.3f}, p = {detection["p_value"]:.2g})')
    if not effects:
        return (f'gap detected (chi2/dof {detection["chi2_per_dof"]:.2f}) but none of the '
                f'candidate effects explains it; largest in {location["largest"]}')
    parts = []
    for row in effects:
        text = row['name']
        if row['estimate'].get('text'):
            text += f' {row["estimate"]["text"]}'
        if row.get('not_separable_with'):
            text += f' (not separable from {", ".join(row["not_separable_with"])})'
        parts.append(text)
    structured = [r for r in effects if r['kind'] == 'structured']
    share = after['share_of_excess_explained']
    numbers = (f'held-out chi2/dof at the stated noise '
               f'{before["chi2_per_dof_at_stated_noise"]:.2f} -> '
               f'{after["chi2_per_dof_at_stated_noise"]:.2f}, position RMS '
               f'{before["rms_position_mm"]:.3f} -> {after["rms_position_mm"]:.3f} mm '
               f'(stated floor {after["stated_floor_position_mm"]:.3f} mm)')
    if 'rms_rotation_deg' in after:
        numbers += (f', rotation RMS {before["rms_rotation_deg"]:.3f} -> '
                    f'{after["rms_rotation_deg"]:.3f} deg (stated floor '
                    f'{after["stated_floor_rotation_deg"]:.3f} deg)')
    excl = after['excluded_pairs']
    if excl['count']:
        numbers += f'; {excl["count"]} pairs set aside, counted as unexplained'
    if not structured:
        return (f'no structured effect: the residuals are noise '
                f'{"larger" if (noise_excess or {}).get("factor", 1) >= 1 else "smaller"} '
                f'than stated ({"; ".join(parts)}); nothing is explained, the noise is '
                f'described: {numbers}')
    verb = 'gap explained by' if share >= 0.5 else 'gap partly explained by'
    if before['chi2_per_dof_at_stated_noise'] < 1.05:
        # nothing in excess of the stated noise: an effect can be real without a gap
        return (f'found {"; ".join(parts)}; the recording is within the stated noise, so '
                f'there is no excess to explain: {numbers}')
    if share < 0.05:
        verb = 'effects found but the gap did not shrink:'
    return f'{verb} {"; ".join(parts)} ({share * 100:.0f} % of the excess): {numbers}'
