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
    screened: bool = False
    behind: bool = False

    def row(self, n_res: int) -> dict:
        """JSON row of the candidate ranking."""
        row = {'name': self.name, 'held_out_gain': float(self.gain),
               'held_out_gain_per_residual': float(self.gain / max(n_res, 1)),
               'blocks_improved': int(np.sum(self.fold_gains > 0)),
               'blocks': int(len(self.fold_gains)), 'accepted_test': bool(self.passes),
               'reason': self.reason}
        if self.spatial_gain is not None:
            row['spatial_held_out_gain'] = float(self.spatial_gain)
        if self.screened:
            # not refitted: the gain is the predicted in-sample one, not a held-out one
            row['screened'] = True
            row['predicted_in_sample_gain'] = row.pop('held_out_gain')
            row['held_out_gain'] = None
            row['held_out_gain_per_residual'] = None
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

    def spatial_heldout(self, ref: tuple):
        """Held-out predictions of the reference model on the spatial blocks."""
        key = tuple(sorted(ref[0].model.names))
        fit, h, hs = self.cache.get(key, ref)
        if hs is None:
            hs = fit.heldout(self.sf, self.K)
            self.cache[key] = (fit, h, hs)
        return hs

    def spatial_ll(self, ref: tuple) -> float:
        """Held-out log-likelihood of the reference model on the spatial blocks."""
        return float(self.spatial_heldout(ref).ll.sum())

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
    kind = 'time'
    if name in fx.SPATIAL_EFFECTS:
        # a spatial effect is judged on unseen cells of the workspace (interpolation): a
        # time block may cover a region the rest of the motion never visits, where any
        # field model can only extrapolate
        ref_s = sel.spatial_heldout(ref)
        fold_gains = hs.fold_sums(hs.ll) - ref_s.fold_sums(ref_s.ll)
        gain = float(fold_gains.sum())
        kind = 'workspace'
    cand = Candidate(name, names, fit, h, gain, fold_gains)
    thr = sel.threshold(round_no)
    if hs is not None:
        cand.spatial_gain = float(hs.ll.sum()) - sel.spatial_ll(ref)
    reasons = []
    if gain < thr:
        reasons.append(f'held-out gain {gain:.1f} below the practical {thr:.1f} nats')
    labels = sel.sf if kind == 'workspace' else sel.tf
    blocks = int(np.sum(np.bincount(labels, minlength=sel.K) > 0))
    if np.sum(fold_gains > 0) < blocks - 1:
        reasons.append(f'improves only {int(np.sum(fold_gains > 0))} of {blocks} {kind} '
                       f'blocks')
    cand.passes = not reasons
    cand.reason = '; '.join(reasons) if reasons else 'passes'
    return cand


#: A candidate whose predicted in-sample gain is below this share of the practical threshold
#: is not refitted (its held-out gain cannot reach the threshold; the share leaves room for
#: the linearisation's error).
SCREEN_SHARE = 0.3
#: ... or below this share of the best held-out gain found in the round (it could be neither
#: the pick nor a not-separable rival, which needs ``not_separable_ratio`` = 0.6 of it; the
#: margin is for the prediction's error). Such a candidate is looked at again in the next
#: round, on top of the pick.
BEHIND_SHARE = 0.3


def screen(sel: _Selector, accepted: tuple, ref: tuple, todo: Sequence[str]) -> dict:
    """
    Predicted in-sample gain (nats) of each candidate from the reference fit, no refit.

    Mean and time effects share one linearisation: a single pass of the reference model
    extended by every compatible mean effect and a clock drift (whose first column is the
    time offset's), all new θ at zero. At the reference optimum the gradient is the score,
    and the one-step gain of adding a candidate's columns is ``½ gₛᵀ Hₛₛ⁻¹ gₛ`` over the
    reference's parameters and the candidate's. Variance effects are fitted on the
    reference's pair statistics (the mean held). A candidate missing from the result is
    refitted whatever its score.
    """
    out: dict = {}
    fit0 = ref[0]
    state0 = fit0.state
    time_new = [n for n in todo if n in fx.TIME_EFFECTS]
    mean_new = [n for n in todo if n in fx.MEAN_EFFECTS]
    if time_new or mean_new:
        names = accepted + (('clock_drift',) if time_new else ()) + tuple(mean_new)
        try:
            model = Model(sel.data, names)
            ps = model.normal(model.initial_state(state0), sel.idx)
        except (ValueError, np.linalg.LinAlgError):
            ps = None
        if ps is not None:
            base_cols = list(range(model.P))
            for a in accepted:
                if a in model.slices:
                    base_cols += list(range(model.slices[a].start, model.slices[a].stop))
            for name in time_new + mean_new:
                sl = model.slices['clock_drift' if name in fx.TIME_EFFECTS else name]
                cols = list(range(sl.start, sl.stop))
                if name == 'time_offset':
                    cols = cols[:1]
                c = np.array(base_cols + cols)
                H = ps.H[np.ix_(c, c)]
                g = ps.g[c]
                try:
                    step = np.linalg.lstsq(H, g, rcond=1e-12)[0]
                except np.linalg.LinAlgError:
                    continue
                # the reference's own gradient is ~0 at its optimum: what is left is the
                # candidate's score; take the reference's share off all the same
                hb = H[:len(base_cols), :len(base_cols)]
                gb = g[:len(base_cols)]
                own = float(gb @ np.linalg.lstsq(hb, gb, rcond=1e-12)[0])
                out[name] = 0.5 * max(float(g @ step) - own, 0.0)
    stats = fit0.stats
    ll0 = float(np.sum(vm.loglik(state0.var, stats)))
    for name in todo:
        if name not in fx.VARIANCE_EFFECTS:
            continue
        model = Model(sel.data, accepted + (name,))
        if any(n in fx.TIME_EFFECTS or n in fx.MEAN_EFFECTS for n in model.names
               if n not in fit0.model.names):
            continue
        var0 = model.initial_state(state0).var
        try:
            var = vm.fit_variance(stats, var0, model.var_names)
        except (ValueError, FloatingPointError):
            continue
        out[name] = max(float(np.sum(vm.loglik(var, stats))) - ll0, 0.0)
    return out


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
    thr = sel.threshold(round_no)
    predicted = screen(sel, accepted, ref, todo)
    # the most promising first: a candidate far behind the best one found so far can be
    # neither the pick nor its not-separable rival, and is not refitted
    todo = sorted(todo, key=lambda n: -predicted.get(n, np.inf))
    best_gain = 0.0
    for i, name in enumerate(todo):
        sel.progress(lo + (hi - lo) * i / max(len(todo), 1), f'round {round_no + 1}: {name}')
        pred = predicted.get(name)
        reason = ''
        if pred is not None and pred < SCREEN_SHARE * thr:
            # the refit cannot gain the practical size: its in-sample gain bounds the
            # held-out one, and the one-step prediction from the reference is that gain
            reason = (f'screened: predicted in-sample gain {pred:.1f} nats, below '
                      f'{SCREEN_SHARE:.2f} of the practical {thr:.1f}')
        elif pred is not None and pred < BEHIND_SHARE * best_gain:
            reason = (f'screened: predicted in-sample gain {pred:.1f} nats, below '
                      f'{BEHIND_SHARE:.2f} of the best held-out gain {best_gain:.1f}')
        if reason:
            # looked at again behind the pick only if it could have passed on its own (the
            # next round revisits only what passed alone)
            cands.append(Candidate(name, accepted + (name,), None, None, pred,
                                   np.zeros(sel.K), reason=reason, screened=True,
                                   behind=pred >= thr))
            continue
        cand = _candidate(sel, accepted, name, ref, round_no)
        cands.append(cand)
        if cand.passes:
            best_gain = max(best_gain, cand.gain)
    passing = sorted([c for c in cands if c.passes], key=lambda c: -c.gain)
    if not passing:
        return None, cands, []
    best = passing[0]
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
             cov_a: Optional[np.ndarray] = None, cov_b: Optional[np.ndarray] = None,
             context: Optional[dict] = None) -> Diagnosis:
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
    context : dict, optional
        What ``diagnose_streams`` read before pairing: ``stamps`` (``stamps.stamps_report``),
        ``coarse_shift_s`` (the pairs were made that far from the given offset, found by the
        coarse search) and ``before`` (the pairs at the given offset, for the gap before).

    Returns
    -------
    Diagnosis

    Raises
    ------
    TooFewPairsError, InputError, UnobservableError
        As ``calibrate`` does.

    """
    return _diagnose(pairs, settings, stream_a, options or Options(),
                     progress or (lambda f, s: None), cov_a, cov_b, context or {})


def _diagnose(pairs, settings, stream_a, opts, progress, cov_a, cov_b, context) -> Diagnosis:
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
    # the base residuals guide data-dependent bases (the field source's position)
    data.cache['base_errors'] = base_errors(data, base)[0]

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
    shift = float(context.get('coarse_shift_s', 0.0))
    drift_checks = []
    for r in range(opts.max_effects):
        span = (0.1 + 0.25 * r, 0.1 + 0.25 * (r + 1))
        best, cands, not_sep = _select_round(sel, accepted, ref, names, r, span)
        rounds.append(cands)
        if best is not None and best.name == 'clock_drift':
            check = _drift_check(data, sel, best, cands)
            drift_checks.append(check)
            if not check['accepted']:
                best.passes = False
                best.reason = check['reason']
                alt = [c for c in cands if c.passes and c.name != 'clock_drift']
                best = max(alt, key=lambda c: c.gain) if alt else None
                not_sep = []
        if best is None:
            break
        if r == 0:
            # later rounds only revisit what improved on the base model on its own: an
            # effect that helps nothing alone is not looked for behind another one
            names = [c.name for c in cands if c.passes or c.behind]
        accepted = accepted + (best.name,)
        chosen.append((best, not_sep))
        for other in not_sep:
            not_separable.append([best.name, other])
        ref = sel.score(accepted, best.fit.state)

    progress(0.85, 'final fit on all pairs')
    forced_offset = shift != 0.0 and not any(a in fx.TIME_EFFECTS for a in accepted)
    if forced_offset:
        # the coarse search moved the pairing: that offset is an effect found, refined here
        accepted = ('time_offset',) + accepted
        final = Model(data, accepted).fit(ref[0].state, None, folds, K)
    elif stride == 1:
        final = ref[0]
    else:
        final = Model(data, accepted).fit(ref[0].state, None, folds, K)
    gap_folds, blocks_kind = folds, 'time blocks'
    if any(a in fx.SPATIAL_EFFECTS and a in fx.MEAN_EFFECTS for a in accepted):
        # a field is tested where it can be: on unseen cells of the workspace, between seen
        # ones (a time block may hold a region nothing else visits)
        gap_folds = spatial_folds(data.b_points[:, 0, :], K, seed=opts.seed)
        blocks_kind = 'workspace cells'
    before = base.heldout(gap_folds, K)
    after = final.heldout(gap_folds, K) if accepted else before
    gap_after = gap_measures(data, final, after)
    sd = _stated_sd(data, base)
    everyone = np.ones(n, dtype=bool)
    counted = after.p_in > 0.5 if final.state.var.eps > 0 else everyone
    if 'before' in context:
        # the gap before is the recording paired at the offset the user gave
        b_pairs, b_settings = context['before']
        b_data = prepare(b_pairs, b_settings, stream_a, cov_a, cov_b)
        b_folds = (time_folds(b_data.t, K) if blocks_kind == 'time blocks'
                   else spatial_folds(b_data.b_points[:, 0, :], K, seed=opts.seed))
        b_res = calibrate(b_pairs, b_settings.updated(robust=False), cov_a=cov_a, cov_b=cov_b)
        b_fit = Model(b_data, ()).fit(start_state(_params_of(b_res, spec)), None, b_folds, K)
        b_held = b_fit.heldout(b_folds, K)
        gap_before = gap_measures(b_data, b_fit, b_held)
        gap_before.update(gp.stated_measures(b_data, b_held.quad_stated, b_held.e,
                                             _stated_sd(b_data, b_fit),
                                             np.ones(b_data.n, dtype=bool)))
    else:
        gap_before = gap_measures(data, base, before)
        gap_before.update(gp.stated_measures(data, before.quad_stated, before.e, sd, everyone))
    gap_after.update(gp.stated_measures(data, after.quad_stated, after.e, sd, counted))
    gap_after['share_of_excess_explained'] = gp.share_explained(gap_before, gap_after)
    gap_before['held_out_on'] = gap_after['held_out_on'] = blocks_kind
    gap_after['rms_moved'] = gp.rms_moved(gap_before, gap_after)
    gap_before['share_of_excess_explained'] = 0.0
    n_res = len(idx) * data.m
    effect_rows = []
    final_cov = final.mean_cov()
    var_cov = final.var_cov() if final.model.var_names else None
    if forced_offset:
        est = effect_estimate('time_offset', final, final_cov, var_cov)
        est['coarse_s'] = shift
        effect_rows.append({'name': 'time_offset', 'kind': 'structured', 'estimate': est,
                            'source': 'coarse search', 'held_out_gain': 0.0,
                            'held_out_gain_per_residual': 0.0, 'blocks_improved': 0,
                            'blocks': 0})
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
    for row in effect_rows:
        est = row['estimate']
        if shift and 'tau_s' in est:
            est['tau_s'] += shift
            est['text'] = f'{est["tau_s"] * 1e3:.2f} ± {est["sigma_s"] * 1e3:.2f} ms'
        if shift and 'offset_at_start_s' in est:
            est['offset_at_start_s'] += shift
            est['offset_at_end_s'] += shift
    if drift_checks:
        row = next((r for r in effect_rows if r['name'] == 'clock_drift'), None)
        if row is not None:
            row['per_block_offsets'] = drift_checks[-1]
    stamps = context.get('stamps')
    if stamps is not None:
        _stamp_rows(stamps, effect_rows)
    structure = _structure_checks(data, final, after, counted, effect_rows, gap_after)
    noise_excess = _noise_excess(data, final, after, counted, effect_rows, gap_after)
    gap_detected = bool(detection['gap'] or effect_rows)
    if stamps is not None and stamps['issues']:
        gap_detected = True
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
    if stamps is not None:
        report['stamps'] = stamps
        if stamps['issues'] and not effect_rows:
            report['verdict'] = ('timing issues in the stamps, residuals fit the model: '
                                 + '; '.join(f'{d["device"]}: {d["text"]}'
                                             for d in stamps['devices']))
    if shift:
        report['coarse_offset_s'] = shift
    progress(1.0, 'done')
    return Diagnosis(report=report, data=data, base=base, final=final, before=before,
                     after=after, rounds=rounds)


def diagnose_streams(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                     settings: Settings, options: Optional[Options] = None,
                     progress: Optional[Progress] = None) -> Diagnosis:
    """
    Read the stamps, search the clock offset coarsely, pair as ``coreg calibrate``, diagnose.

    The coarse search (``timing.coarse_offsets``, the devices' speeds cross-correlated) finds
    offsets of any size even when another error dominates the residuals; when its best
    candidate is more than ``COARSE_MIN_S`` from the given offset and pairing there fits
    clearly better, the diagnosis pairs there, names the offset and measures the gap before
    at the given offset.
    """
    from coreg_ros.core.diagnosis.stamps import stamps_report

    bs = list(streams_b) if isinstance(streams_b, (list, tuple)) else [streams_b]
    context = {'stamps': stamps_report(stream_a, bs)}
    pairs, report = pair_for(stream_a, bs, settings)
    use_settings = settings
    shift = _coarse_shift(stream_a, bs, settings, pairs, options)
    if shift:
        moved = settings.updated(time_offset=settings.time_offset + shift)
        context['before'] = (pairs, settings)
        context['coarse_shift_s'] = shift
        pairs, report = pair_for(stream_a, bs, moved)
        use_settings = moved
    diag = diagnose(pairs, use_settings, stream_a, options, progress, context=context)
    diag.report['pairing'] = {'n_a': report.n_a, 'n_b': report.n_b,
                              'n_paired': report.n_paired, 'unpaired': dict(report.unpaired)}
    return diag


#: A coarse offset this far from the given one (s) is tried as the pairing offset.
COARSE_MIN_S = 0.05
#: ... and kept when the fit there has at most this share of the χ² at the given offset.
COARSE_GAIN = 0.5


def _coarse_shift(stream_a, streams_b, settings, pairs, options) -> float:
    """Shift (s) of the pairing offset found by the coarse search, or 0."""
    from coreg_ros.core.timing import coarse_offsets

    angular = settings.model == 'full_pose' or len(streams_b) == 3
    try:
        cands = coarse_offsets(stream_a, streams_b, angular=angular)
    except (ValueError, np.linalg.LinAlgError):
        return 0.0
    if not cands or abs(cands[0][0] - settings.time_offset) <= COARSE_MIN_S or len(pairs) < 50:
        # the speeds correlate best near the given offset: the fine fit takes it from there
        return 0.0
    far = [tau for tau, _ in cands[:2] if abs(tau - settings.time_offset) > COARSE_MIN_S]

    def thin(p):
        # the comparison needs a few thousand pairs, not all
        step = max(1, len(p) // 4000)
        if step == 1:
            return p
        return Pairs(stamps=p.stamps[::step], pos_a=p.pos_a[::step], quat_a=p.quat_a[::step],
                     pos_b=p.pos_b[::step],
                     quat_b=None if p.quat_b is None else p.quat_b[::step],
                     a_var_scale=None if p.a_var_scale is None else p.a_var_scale[::step])

    try:
        here = calibrate(thin(pairs), settings.updated(robust=False))
    except Exception:  # noqa: BLE001 - a refusal at the given offset: try the other
        here = None
    best, best_chi = 0.0, here.chi2 / max(here.dof, 1) if here is not None else np.inf
    for tau in far:
        moved = settings.updated(time_offset=tau)
        p2, _ = pair_for(stream_a, streams_b, moved)
        if len(p2) < max(50, 0.5 * len(pairs)):
            continue
        try:
            res = calibrate(thin(p2), moved.updated(robust=False))
        except Exception:  # noqa: BLE001 - unobservable or too few: not this one
            continue
        chi = res.chi2 / max(res.dof, 1)
        if chi < COARSE_GAIN * best_chi:
            best, best_chi = tau - settings.time_offset, chi
    return float(best)


def _drift_check(data: DiagData, sel: _Selector, best: Candidate, cands: list) -> dict:
    """
    Accept a clock drift only if it beats a constant offset and per-block offsets trend.

    The offset is fitted on each time block alone (``time_offset`` model); a drift must show
    as a significant linear trend of those offsets (slope beyond 3σ, agreeing in sign with
    the drift and within a factor of three of it), and the drift's held-out gain must exceed
    the constant offset's by the practical threshold.
    """
    K = sel.K
    idx = sel.idx
    taus, sds, mids = [], [], []
    for k in range(K):
        block = idx[sel.tf == k]
        if len(block) < 30:
            continue
        try:
            fit = Model(data, ('time_offset',)).fit(best.fit.state, block)
        except (ValueError, np.linalg.LinAlgError):
            continue
        cov = fit.mean_cov()
        sl = fit.model.slices['time_offset']
        if cov is None:
            continue
        taus.append(float(fit.state.theta['time_offset'][0]))
        sds.append(float(np.sqrt(max(cov[sl, sl][0, 0], 1e-30))))
        mids.append(float(np.mean(data.t[block])))
    out = {'block_offsets_s': taus, 'block_sigma_s': sds, 'block_mid_s': mids,
           'accepted': False, 'reason': ''}
    if len(taus) < 3:
        out['reason'] = 'too few blocks to see a trend of the offset'
        return out
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
    out.update(trend_ppm=slope * 1e6, trend_sigma_ppm=slope_sd * 1e6, drift_ppm=kappa * 1e6)
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
    out['accepted'] = not reasons
    out['reason'] = '; '.join(reasons) if reasons else 'per-block offsets trend'
    return out


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


def _stamp_rows(stamps: dict, rows: list) -> None:
    """
    Name jitter from the stamps when the residuals did not; add drops and gaps to any row.

    The stamp jitter goes first when the residuals named nothing structured (their first
    answer then was a noise description the stamps explain).
    """
    from coreg_ros.core.diagnosis.stamps import jitter_row

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
    if before['chi2_per_dof_at_stated_noise'] < 1.05:
        # nothing in excess of the stated noise: an effect can be real without a gap
        return (f'found {"; ".join(parts)}; the recording is within the stated noise, so '
                f'there is no excess to explain: {numbers}')
    if share < 0.05:
        verb = 'effects found but the gap did not shrink:'
    return f'{verb} {"; ".join(parts)} ({share * 100:.0f} % of the excess): {numbers}'
