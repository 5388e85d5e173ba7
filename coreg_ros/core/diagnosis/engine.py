"""
The sim-to-real gap diagnosis: detect, locate, explain, quantify (DESIGN.md §5).

``diagnose(pairs, settings)`` calibrates, fits the base model with the stated noise, measures
the gap (chi-square, whiteness, tails) and where it lies, then explains it with the ten
candidate effects of ``effects.py``:

1. every candidate is fitted as an extension of the model (joint Gauss-Newton with the
   calibration, or maximum likelihood for the noise effects) and scored by its gain in
   held-out log-likelihood on contiguous time blocks (and on cells of the workspace for
   spatial effects), each block predicted by the fit on the others;
2. a candidate is accepted only if it gains in (almost) every block, by a practical size (a
   share of a nat per residual, not merely a tiny p-value) and, for spatial effects, also on
   unseen parts of the workspace; the simpler of nested candidates is preferred;
3. when another candidate gains nearly as much and the two explain the same thing (neither
   adds to the other), the pair is reported as not separable with the recorded motion;
4. up to three effects are accepted in turn, each on top of the previous ones;
5. the gap before and after is measured on held-out blocks of all pairs, and each accepted
   effect's size is reported with its uncertainty.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Optional, Union

import numpy as np

from coreg_ros.core.calibrate import calibrate
from coreg_ros.core.diagnosis import detect as dt
from coreg_ros.core.diagnosis import effects as fx
from coreg_ros.core.diagnosis import gap as gp
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.data import DiagData, prepare, spatial_folds, time_folds
from coreg_ros.core.diagnosis.fit import Fit, Heldout, Model, start_state
from coreg_ros.core.diagnosis.summary import effect_estimate, gap_measures, transforms
from coreg_ros.core.diagnosis.threads import single_blas_thread
from coreg_ros.core.models import Parameters
from coreg_ros.core.pipeline import pair_for
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import Pairs, PoseStream

Progress = Callable[[float, str], None]


@dataclass(frozen=True)
class Options:
    """
    Tuning of the diagnosis.

    Attributes
    ----------
    n_folds : int
        Blocks of the held-out validation.
    max_effects : int
        Effects accepted at most.
    max_select_pairs : int
        Pairs used to select effects (an even subsample beyond); the final fit uses all.
    practical : float
        Smallest held-out gain that counts, in nats per residual (0.005 ≈ a change of 0.01 in
        chi-square per degree of freedom, or a noise factor off by 7 %).
    practical_next : float
        The same for the second and third effect.
    min_gain : float
        Smallest held-out gain in nats, whatever the size of the recording.
    not_separable_ratio : float
        A runner-up gaining at least this share of the best candidate's gain is tested for
        separability.
    nested_share : float
        The richer of two nested candidates is preferred when it gains at least this share of
        the practical threshold more than the simpler one.
    candidates : tuple of str
    seed : int
        Seed of the spatial blocks.

    """

    n_folds: int = 5
    max_effects: int = 3
    max_select_pairs: int = 15000
    practical: float = 0.005
    practical_next: float = 0.02
    min_gain: float = 10.0
    not_separable_ratio: float = 0.6
    nested_share: float = 0.25
    candidates: tuple = fx.EFFECT_NAMES
    seed: int = 0


@dataclass
class Candidate:
    """One candidate effect scored on top of the accepted ones."""

    name: str
    names: tuple
    fit: Fit
    heldout: Heldout
    gain: float
    fold_gains: np.ndarray
    spatial_gain: Optional[float] = None
    passes: bool = False
    reason: str = ''

    def row(self, n_res: int) -> dict:
        """JSON row of the candidate ranking."""
        row = {'name': self.name, 'held_out_gain': float(self.gain),
               'held_out_gain_per_residual': float(self.gain / max(n_res, 1)),
               'blocks_improved': int(np.sum(self.fold_gains > 0)),
               'blocks': int(len(self.fold_gains)), 'accepted_test': bool(self.passes),
               'reason': self.reason}
        if self.spatial_gain is not None:
            row['spatial_held_out_gain'] = float(self.spatial_gain)
        return row


@dataclass
class Diagnosis:
    """
    The outcome of ``diagnose``.

    Attributes
    ----------
    report : dict
        The JSON document (keys ``gap_detected``, ``effects``, ``not_separable``,
        ``gap_before``, ``gap_after``, ``location``, ``verdict``, and more).
    data : DiagData
    base : Fit
        The model with the stated noise and no effect, on all pairs.
    final : Fit
        The model with the accepted effects, on all pairs.
    before, after : Heldout
        Held-out predictions of every pair by the base and the final model.
    rounds : list of list of Candidate
        The candidates scored in each round of the selection.

    """

    report: dict
    data: DiagData
    base: Fit
    final: Fit
    before: Heldout
    after: Heldout
    rounds: list = field(default_factory=list)


def _params_of(result, spec) -> Parameters:
    return Parameters.from_transforms(spec, result.base_to_base.position,
                                      result.base_to_base.quat_wxyz, result.markers,
                                      result.tool_to_marker.quat_wxyz)


def _has_motion(data: DiagData) -> bool:
    moving = (data.speed > dt.STATIC_SPEED) | (data.angular_speed > dt.STATIC_ANGULAR_SPEED)
    return bool(np.mean(moving) > 0.1)


class _Selector:
    """Scoring of candidate models on the selection pairs."""

    def __init__(self, data: DiagData, idx: np.ndarray, opts: Options, progress: Progress):
        self.data = data
        self.idx = idx
        self.opts = opts
        self.progress = progress
        self.K = opts.n_folds
        self.tf = time_folds(data.t[idx], self.K)
        self.sf = spatial_folds(data.b_points[idx, 0, :], self.K, seed=opts.seed)
        self.n_res = len(idx) * data.m
        self.cache = {}

    def score(self, names: tuple, start) -> tuple:
        """Fit the model ``names`` on the selection pairs; its time and spatial held-out."""
        key = tuple(sorted(names))
        if key not in self.cache:
            fit = Model(self.data, names).fit(start, self.idx, self.tf, self.K)
            h = fit.heldout(self.tf, self.K)
            hs = None
            if any(n in fx.SPATIAL_EFFECTS for n in names):
                hs = fit.heldout(self.sf, self.K)
            self.cache[key] = (fit, h, hs)
        return self.cache[key]

    def spatial_ll(self, ref: tuple) -> float:
        """Held-out log-likelihood of the reference model on the spatial blocks."""
        fit, _, hs = ref
        if hs is None:
            hs = fit.heldout(self.sf, self.K)
            self.cache[tuple(sorted(fit.model.names))] = (fit, ref[1], hs)
        return float(hs.ll.sum())

    def threshold(self, round_no: int) -> float:
        """Smallest held-out gain that counts in this round, nats."""
        per = self.opts.practical if round_no == 0 else self.opts.practical_next
        return max(self.opts.min_gain, per * self.n_res)


def _candidate(sel: _Selector, accepted: tuple, name: str, ref: tuple, round_no: int
               ) -> Candidate:
    names = accepted + (name,)
    fit, h, hs = sel.score(names, ref[0].state)
    ref_h = ref[1]
    fold_gains = h.fold_sums(h.ll) - ref_h.fold_sums(ref_h.ll)
    gain = float(fold_gains.sum())
    cand = Candidate(name, names, fit, h, gain, fold_gains)
    thr = sel.threshold(round_no)
    if hs is not None:
        cand.spatial_gain = float(hs.ll.sum()) - sel.spatial_ll(ref)
    reasons = []
    if gain < thr:
        reasons.append(f'held-out gain {gain:.1f} below the practical {thr:.1f} nats')
    blocks = int(np.sum(np.bincount(sel.tf, minlength=sel.K) > 0))
    if np.sum(fold_gains > 0) < blocks - 1:
        reasons.append(f'improves only {int(np.sum(fold_gains > 0))} of {blocks} time blocks')
    if cand.spatial_gain is not None and cand.spatial_gain < 0.5 * thr:
        reasons.append(f'spatial held-out gain {cand.spatial_gain:.1f} too small')
    cand.passes = not reasons
    cand.reason = '; '.join(reasons) if reasons else 'passes'
    return cand


def _compatible(accepted: tuple, name: str) -> bool:
    if name in accepted:
        return False
    if name in fx.TIME_EFFECTS and any(a in fx.TIME_EFFECTS for a in accepted):
        return False
    if {name, *accepted} >= {'noise_scale', 'distance_noise'}:
        return False
    return True


def _nested(a: str, b: str) -> bool:
    return (a, b) in fx.NESTED or (b, a) in fx.NESTED


def _select_round(sel: _Selector, accepted: tuple, ref: tuple, names: Sequence[str],
                  round_no: int, progress_span: tuple) -> tuple:
    """One round: score the candidates, pick one, test separability. Returns (pick, ...)."""
    cands = []
    lo, hi = progress_span
    todo = [n for n in names if _compatible(accepted, n)]
    for i, name in enumerate(todo):
        sel.progress(lo + (hi - lo) * i / max(len(todo), 1), f'round {round_no + 1}: {name}')
        cands.append(_candidate(sel, accepted, name, ref, round_no))
    passing = sorted([c for c in cands if c.passes], key=lambda c: -c.gain)
    if not passing:
        return None, cands, []
    best = passing[0]
    thr = sel.threshold(round_no)
    # nested: prefer the simpler unless the richer gains clearly more (its few extra
    # parameters are already paid for on the held-out blocks)
    margin = max(sel.opts.min_gain, sel.opts.nested_share * thr)
    for simple, rich in fx.NESTED:
        if best.name == rich:
            alt = next((c for c in passing if c.name == simple), None)
            if alt is not None and best.gain - alt.gain < margin:
                best = alt
    not_sep = []
    for other in passing:
        if other is best or _nested(other.name, best.name):
            continue
        if other.gain < sel.opts.not_separable_ratio * best.gain:
            continue
        if not _compatible(accepted + (best.name,), other.name):
            # two time effects, or two noise levels, cannot be fitted together: compare as is
            if other.gain > best.gain - thr:
                not_sep.append(other.name)
            continue
        both, h_both, _ = sel.score(accepted + (best.name, other.name), best.fit.state)
        ll_both = float(h_both.ll.sum())
        gain_best_over_other = ll_both - float(other.heldout.ll.sum())
        gain_other_over_best = ll_both - float(best.heldout.ll.sum())
        if gain_best_over_other < thr and gain_other_over_best < thr:
            not_sep.append(other.name)
    return best, cands, not_sep


def diagnose(pairs: Pairs, settings: Settings, stream_a: Optional[PoseStream] = None,
             options: Optional[Options] = None, progress: Optional[Progress] = None,
             cov_a: Optional[np.ndarray] = None, cov_b: Optional[np.ndarray] = None
             ) -> Diagnosis:
    """
    Diagnose the gap between a recording and the model with its stated noise.

    Parameters
    ----------
    pairs : Pairs
        Paired samples (``pipeline.pair_for``).
    settings : Settings
        Model, method and stated noise (``sigma_a``, ``sigma_b``).
    stream_a : PoseStream, optional
        Device A's whole stream (better velocities and time shifts than the pairs alone).
    options : Options, optional
    progress : callable, optional
        ``progress(fraction, text)`` called as the work advances.
    cov_a, cov_b : ndarray, shape (6, 6), optional
        Full noise covariances (ROS layout) overriding the sigmas.

    Returns
    -------
    Diagnosis

    Raises
    ------
    TooFewPairsError, InputError, UnobservableError
        As ``calibrate`` does.

    """
    with single_blas_thread():
        return _diagnose(pairs, settings, stream_a, options or Options(),
                         progress or (lambda f, s: None), cov_a, cov_b)


def _diagnose(pairs, settings, stream_a, opts, progress, cov_a, cov_b) -> Diagnosis:
    progress(0.0, 'calibrating')
    # the diagnosis models outliers itself: its base fit keeps every pair
    result = calibrate(pairs, settings.updated(robust=False), cov_a=cov_a, cov_b=cov_b)
    data = prepare(pairs, settings, stream_a, cov_a, cov_b)
    spec = data.spec
    K = opts.n_folds
    folds = time_folds(data.t, K)
    base_model = Model(data, ())
    base = base_model.fit(start_state(_params_of(result, spec)), None, folds, K)
    progress(0.05, 'detecting')
    detection, location = _detect_locate(data, base)

    n = data.n
    stride = int(np.ceil(n / opts.max_select_pairs))
    idx = np.arange(0, n, stride)
    sel = _Selector(data, idx, opts, progress)
    names = [c for c in opts.candidates if c in fx.EFFECT_NAMES]
    if not _has_motion(data):
        names = [c for c in names if c not in fx.MOTION_EFFECTS]
    ref = sel.score((), base.state)
    accepted: tuple = ()
    not_separable = []
    rounds = []
    chosen = []
    for r in range(opts.max_effects):
        span = (0.1 + 0.25 * r, 0.1 + 0.25 * (r + 1))
        best, cands, not_sep = _select_round(sel, accepted, ref, names, r, span)
        rounds.append(cands)
        if best is None:
            break
        if r == 0:
            # later rounds only revisit what improved on the base model on its own: an
            # effect that helps nothing alone is not looked for behind another one
            names = [c.name for c in cands if c.passes]
        accepted = accepted + (best.name,)
        chosen.append((best, not_sep))
        for other in not_sep:
            not_separable.append([best.name, other])
        ref = sel.score(accepted, best.fit.state)

    progress(0.85, 'final fit on all pairs')
    if stride == 1:
        final = ref[0]
    else:
        final = Model(data, accepted).fit(ref[0].state, None, folds, K)
    before = base.heldout(folds, K)
    after = final.heldout(folds, K) if accepted else before
    gap_before = gap_measures(data, base, before)
    gap_after = gap_measures(data, final, after)
    sd = _stated_sd(data, base)
    everyone = np.ones(n, dtype=bool)
    counted = after.p_in > 0.5 if final.state.var.eps > 0 else everyone
    gap_before.update(gp.stated_measures(data, before.quad_stated, before.e, sd, everyone))
    gap_after.update(gp.stated_measures(data, after.quad_stated, after.e, sd, counted))
    gap_after['share_of_excess_explained'] = gp.share_explained(gap_before, gap_after)
    gap_after['rms_moved'] = gp.rms_moved(gap_before, gap_after)
    gap_before['share_of_excess_explained'] = 0.0
    n_res = len(idx) * data.m
    effect_rows = []
    final_cov = final.mean_cov()
    var_cov = final.var_cov() if final.model.var_names else None
    for cand, not_sep in chosen:
        est = effect_estimate(cand.name, final, final_cov, var_cov)
        row = {'name': cand.name, 'kind': fx.effect_kind(cand.name), 'estimate': est,
               'held_out_gain': float(cand.gain),
               'held_out_gain_per_residual': float(cand.gain / n_res),
               'blocks_improved': int(np.sum(cand.fold_gains > 0)),
               'blocks': int(len(cand.fold_gains))}
        if cand.spatial_gain is not None:
            row['spatial_held_out_gain'] = float(cand.spatial_gain)
        if not_sep:
            row['not_separable_with'] = list(not_sep)
        effect_rows.append(row)
    structure = _structure_checks(data, final, after, counted, effect_rows, gap_after)
    noise_excess = _noise_excess(data, final, after, counted, effect_rows, gap_after)
    gap_detected = bool(detection['gap'] or effect_rows)
    report = {
        'gap_detected': gap_detected,
        'effects': effect_rows,
        'not_separable': not_separable,
        'gap_before': gap_before,
        'gap_after': gap_after,
        'noise_excess': noise_excess,
        'excess_left': structure,
        'location': location,
        'verdict': _verdict(gap_detected, effect_rows, not_separable, gap_before, gap_after,
                            detection, location, noise_excess),
        'detection': detection,
        'candidates': [[c.row(n_res) for c in sorted(cs, key=lambda c: -c.gain)]
                       for cs in rounds],
        'calibration': {'before': transforms(base), 'after': transforms(final)},
        'model': spec.name, 'n_pairs': int(n), 'n_pairs_selection': int(len(idx)),
        'duration_s': float(data.t[-1] - data.t[0]) if n > 1 else 0.0,
        'stated_noise': {'sigma_a': list(data.sigma_a), 'sigma_b': list(data.sigma_b)},
    }
    progress(1.0, 'done')
    return Diagnosis(report=report, data=data, base=base, final=final, before=before,
                     after=after, rounds=rounds)


def diagnose_streams(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                     settings: Settings, options: Optional[Options] = None,
                     progress: Optional[Progress] = None) -> Diagnosis:
    """Pair the streams as ``coreg calibrate`` does, then ``diagnose``."""
    pairs, report = pair_for(stream_a, streams_b, settings)
    diag = diagnose(pairs, settings, stream_a, options, progress)
    diag.report['pairing'] = {'n_a': report.n_a, 'n_b': report.n_b,
                              'n_paired': report.n_paired, 'unpaired': dict(report.unpaired)}
    return diag


def base_errors(data: DiagData, fit: Fit):
    """Raw errors, standardized errors, quad, decorrelated standardized errors, rates."""
    model = fit.model
    idx = np.arange(data.n)
    parts = [model.evaluate(fit.state, ch, jac=False) for ch in model.chunks(idx)]
    e = np.concatenate([p.e for p in parts])
    sd = np.concatenate([p.sd for p in parts])
    z = np.concatenate([p.st.z for p in parts])
    lam = np.concatenate([p.st.lam for p in parts])
    fdot = np.concatenate([p.fdot for p in parts])
    return e, sd, z, lam, fdot


def _detect_locate(data: DiagData, base: Fit):
    e, sd, z, lam, fdot = base_errors(data, base)
    zstd = z / np.sqrt(1.0 + lam)
    quad = np.sum(zstd ** 2, axis=1)
    detection = dt.detect(quad, zstd, data.m, data.spec.n_params)
    # split ḟ into the parts of linear and angular velocity
    model = base.model
    idx = np.arange(data.n)
    fv, fw = [], []
    for ch in model.chunks(idx):
        from coreg_ros.core.models import linearize
        _, _, jx = linearize(base.state.params, data.pos_a[ch], data.quat_a[ch],
                             data.pos_b[ch], None if data.quat_b is None else data.quat_b[ch],
                             with_input=True)
        fv.append(np.einsum('nij,nj->ni', jx[:, :, 0:3], data.vel[ch]))
        fw.append(np.einsum('nij,nj->ni', jx[:, :, 3:6], data.omega[ch]))
    fv = np.concatenate(fv) / sd
    fw = np.concatenate(fw) / sd
    step = float(np.median(np.diff(data.t))) if data.n > 1 else 0.0
    location = dt.locate(t=data.t, quad=quad, e_std=e / sd, m=data.m,
                         has_rotation=data.spec.has_q1, points=data.b_points[:, 0, :],
                         speed=data.speed, angular_speed=data.angular_speed, fdot_v=fv,
                         fdot_w=fw, dt=step)
    return detection, location


def _stated_sd(data: DiagData, fit: Fit) -> np.ndarray:
    """Return the standard deviation (N, m) of each raw error under the stated noise."""
    model = fit.model
    return np.concatenate([model.evaluate(fit.state, ch, jac=False).sd
                           for ch in model.chunks(np.arange(data.n))])


def _structure_checks(data, final, after, counted, rows: list, gap_after: dict) -> dict:
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
    # under the fitted noise model: a noise that grows with range is stationary, not local
    emap = gp.excess_map(data, after.quad, counted)
    out['map'] = emap
    ex_after = float(np.mean(after.quad[counted]) / data.m) - 1.0
    if (emap['concentrated'] and ex_after > 0.05
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
    return out


def _noise_excess(data, final, after, counted, rows: list, gap_after: dict) -> Optional[dict]:
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


def _verdict(gap: bool, effects: list, not_sep: list, before: dict, after: dict,
             detection: dict, location: dict, noise_excess: Optional[dict] = None) -> str:
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
    if share < 0.05:
        verb = 'effects found but the gap did not shrink:'
    return f'{verb} {"; ".join(parts)} ({share * 100:.0f} % of the excess): {numbers}'
