"""
Candidate selection: score each candidate effect on held-out blocks, pick one per round.

Every candidate is fitted as an extension of the model (``fit.Model``) on the selection pairs
and scored by its gain in held-out log-likelihood on contiguous time blocks (and on cells of
the workspace for spatial effects), each block predicted by the fit on the others. A
candidate passes only if it gains in (almost) every block and by a practical size; the
simpler of nested candidates is preferred; a runner-up that explains the same thing is
reported as not separable; up to ``Options.max_effects`` effects are accepted in turn, each
on top of the previous ones. Candidates that cannot reach the practical size are screened
out from a one-step prediction (``screen``) without a refit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.data import DiagData, spatial_folds, time_folds
from coreg_ros.core.diagnosis.drift import drift_check
from coreg_ros.core.diagnosis.effects.registry import CANDIDATES, EFFECT_NAMES
from coreg_ros.core.diagnosis.fit import Fit, Heldout, Model
from coreg_ros.core.diagnosis.judged import (
    blocks_judged,
    expected_block_gains,
    own_gain_reasons,
    SCREEN_SHARE,
)
from coreg_ros.core.diagnosis.locate import STATIC_ANGULAR_SPEED, STATIC_SPEED
from coreg_ros.core.diagnosis.options import Options, Progress
from coreg_ros.core.diagnosis.record import optional, Record
import numpy as np


@dataclass(frozen=True, kw_only=True)
class CandidateScore(Record):
    """
    One candidate's line in the report's ranking.

    Attributes
    ----------
    name : str
    held_out_gain, held_out_gain_per_residual : float or None
        Over the accepted ones, nats (None when screened: not refitted).
    blocks_improved, blocks : int
    accepted_test : bool
        It passes the tests (gain, blocks).
    reason : str
    spatial_held_out_gain : float, optional
        On unseen cells of the workspace (spatial effects).
    predicted_in_sample_gain : float, optional
        A screened candidate's predicted in-sample gain, nats (written after ``screened``).

    """

    name: str
    held_out_gain: Optional[float]
    held_out_gain_per_residual: Optional[float]
    blocks_improved: int
    blocks: int
    accepted_test: bool
    reason: str
    spatial_held_out_gain: Optional[float] = optional()
    predicted_in_sample_gain: Optional[float] = optional()

    @property
    def screened(self) -> bool:
        """Whether it was screened out by its predicted gain (not refitted)."""
        return self.predicted_in_sample_gain is not None

    def as_dict(self) -> dict:
        """Return the line's JSON dict: a screened candidate's gains after its test."""
        doc = super().as_dict()
        if not self.screened:
            return doc
        # not refitted: the gain is the predicted in-sample one, not a held-out one
        doc.pop('predicted_in_sample_gain')
        doc['screened'] = True
        doc['predicted_in_sample_gain'] = self.predicted_in_sample_gain
        doc['held_out_gain'] = doc.pop('held_out_gain')
        return doc


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

    def score(self, n_res: int) -> CandidateScore:
        """Return the candidate's line in the ranking (``n_res``: residuals of the pairs)."""
        # a screened candidate was not refitted: its gain is the predicted in-sample one
        held_out = None if self.screened else float(self.gain)
        return CandidateScore(
            name=self.name, held_out_gain=held_out,
            held_out_gain_per_residual=None if self.screened else float(self.gain / max(n_res, 1)),
            blocks_improved=int(np.sum(self.fold_gains > 0)), blocks=int(len(self.fold_gains)),
            accepted_test=bool(self.passes), reason=self.reason,
            spatial_held_out_gain=None if self.spatial_gain is None else float(self.spatial_gain),
            predicted_in_sample_gain=float(self.gain) if self.screened else None)


def has_motion(data: DiagData) -> bool:
    """Whether the tool moves in more than a tenth of the pairs (motion effects can show)."""
    moving = (data.speed > STATIC_SPEED) | (data.angular_speed > STATIC_ANGULAR_SPEED)
    return bool(np.mean(moving) > 0.1)


class Selector:
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
            if any(CANDIDATES[n].spatial for n in names):
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


def score_candidate(sel: Selector, accepted: tuple, name: str, ref: tuple, round_no: int
                    ) -> Candidate:
    """Fit ``accepted + (name,)``, score its held-out gain over ``ref`` and test it."""
    names = accepted + (name,)
    fit, h, hs = sel.score(names, ref[0].state)
    ref_h = ref[1]
    fold_gains = h.fold_sums(h.ll) - ref_h.fold_sums(ref_h.ll)
    gain = float(fold_gains.sum())
    kind = 'time'
    if CANDIDATES[name].spatial:
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
    expected = expected_block_gains(sel, fit, name, labels)
    judged = blocks_judged(sel, name, labels, expected=expected)
    blocks = int(judged.sum())
    improved = int(np.sum(fold_gains[judged] > 0))
    if improved < max(blocks - 1, 1):
        reasons.append(f'improves only {improved} of {blocks} {kind} blocks')
    reasons += own_gain_reasons(expected, thr)
    cand.passes = not reasons
    cand.reason = '; '.join(reasons) if reasons else 'passes'
    return cand


#: A candidate is not refitted either (beside ``judged.SCREEN_SHARE`` of the practical
#: threshold) below this share of the best held-out gain found in the round (it could be neither
#: the pick nor a not-separable rival, which needs ``not_separable_ratio`` = 0.6 of it; the
#: margin is for the prediction's error). Such a candidate is looked at again in the next
#: round, on top of the pick.
BEHIND_SHARE = 0.3
#: The time effect whose linearisation screens every time effect (a time offset's parameter
#: is its first one).
SCREEN_TIME_EFFECT = 'clock_drift'
#: A structured rival that gains alike is preferred to a noise effect when it leaves at most
#: this share of the noise effect's held-out excess at the stated noise
#: (``_structure_before_noise``): a half, far from the small differences between two
#: descriptions of the same excess.
STRUCTURE_SHARE = 0.5


def screen(sel: Selector, accepted: tuple, ref: tuple, todo: Sequence[str]) -> dict:
    """
    Predicted in-sample gain (nats) of each candidate from the reference fit, no refit.

    Mean and time effects share one linearisation: a single pass of the reference model
    extended by every compatible mean effect and a clock drift (whose first column is the
    time offset's), all new θ at zero. At the reference optimum the gradient is the score,
    and the one-step gain of adding a candidate's columns is ``½ gₛᵀ Hₛₛ⁻¹ gₛ`` over the
    reference's parameters and the candidate's. A time effect whose shift is not the drift's
    (a clock step) has a pass of its own. Variance effects are fitted on the
    reference's pair statistics (the mean held). A candidate missing from the result is
    refitted whatever its score.
    """
    out: dict = {}
    fit0 = ref[0]
    state0 = fit0.state
    time_new = [n for n in todo if CANDIDATES[n].acts_on == 'time']
    mean_new = [n for n in todo if CANDIDATES[n].acts_on == 'mean']
    if time_new or mean_new:
        names = accepted + ((SCREEN_TIME_EFFECT,) if time_new else ()) + tuple(mean_new)
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
                effect = CANDIDATES[name]
                sl = model.slices[SCREEN_TIME_EFFECT if effect.acts_on == 'time' else name]
                cols = list(range(sl.start, sl.stop))
                if effect.acts_on == 'time':
                    cols = cols[:effect.term.n]
                gain = _one_step_gain(ps, base_cols, cols)
                if gain is not None:
                    out[name] = gain
    for name in time_new:
        if _shares_screen(name):
            continue
        # a time effect whose shift is not the drift's (a clock step: the offset after an
        # instant) is linearised on its own: a ramp stands for a step only in part
        try:
            model = Model(sel.data, accepted + (name,))
            ps = model.normal(model.initial_state(state0), sel.idx)
        except (ValueError, np.linalg.LinAlgError):
            out.pop(name, None)
            continue
        base_cols = list(range(model.P))
        for a in accepted:
            if a in model.slices:
                base_cols += list(range(model.slices[a].start, model.slices[a].stop))
        sl = model.slices[name]
        out[name] = _one_step_gain(ps, base_cols, list(range(sl.start, sl.stop)))
    stats = fit0.stats
    ll0 = float(np.sum(vm.loglik(state0.var, stats)))
    for name in todo:
        if CANDIDATES[name].acts_on != 'variance':
            continue
        model = Model(sel.data, accepted + (name,))
        if any(CANDIDATES[n].acts_on in ('time', 'mean') for n in model.names
               if n not in fit0.model.names):
            continue
        var0 = model.initial_state(state0).var
        try:
            var = vm.fit_variance(stats, var0, model.var_names)
        except (ValueError, FloatingPointError):
            continue
        out[name] = max(float(np.sum(vm.loglik(var, stats))) - ll0, 0.0)
    return out


def _shares_screen(name: str) -> bool:
    """Whether a time effect's shift is the first columns of ``SCREEN_TIME_EFFECT``'s."""
    return name == SCREEN_TIME_EFFECT or CANDIDATES[SCREEN_TIME_EFFECT].simpler == name


def _one_step_gain(ps, base_cols: list, cols: list) -> Optional[float]:
    """
    One-step gain ``½ gₛᵀ Hₛₛ⁻¹ gₛ`` of adding ``cols`` to ``base_cols``, nats (``screen``).

    The reference's own gradient is ~0 at its optimum: what is left is the candidate's
    score; the reference's share is taken off all the same.
    """
    c = np.array(base_cols + cols)
    H = ps.H[np.ix_(c, c)]
    g = ps.g[c]
    try:
        step = np.linalg.lstsq(H, g, rcond=1e-12)[0]
        hb = H[:len(base_cols), :len(base_cols)]
        gb = g[:len(base_cols)]
        own = float(gb @ np.linalg.lstsq(hb, gb, rcond=1e-12)[0])
    except np.linalg.LinAlgError:
        return None
    return 0.5 * max(float(g @ step) - own, 0.0)


def compatible(accepted: tuple, name: str) -> bool:
    """Whether ``name`` can be fitted on top of ``accepted`` (one time effect, one noise level)."""
    if name in accepted:
        return False
    effects = [CANDIDATES[n] for n in (name, *accepted)]
    if effects[0].acts_on == 'time' and any(e.acts_on == 'time' for e in effects[1:]):
        return False
    return sum(e.sets_noise_level for e in effects) < 2


def _stated_excess(sel: Selector, cand: Candidate) -> float:
    """Held-out χ²/dof at the stated noise minus one, left by a candidate's model."""
    return float(np.mean(cand.heldout.quad_stated)) / sel.data.m - 1.0


def _structure_before_noise(sel: Selector, best: Candidate, passing: list) -> Candidate:
    """
    Prefer a structured rival that does as well to a noise effect that explains by widening.

    A noise effect (jitter, a larger noise) fits any error of the mean in likelihood by making
    the noise as large as the error; a structured effect that predicts the error leaves the
    held-out errors at the stated noise. When both gain alike (within the not-separable
    ratio), the one that leaves at most ``STRUCTURE_SHARE`` of the noise effect's held-out
    excess at the stated noise is the explanation (a clock set back: its step beside the
    few samples whose order it broke, rather than 65 ms of jitter). True jitter or noise is
    not reduced at the stated noise by any structure, so it keeps its place.
    """
    if CANDIDATES[best.name].kind != 'noise':
        return best
    excess = _stated_excess(sel, best)
    if not excess > 0.0:
        return best
    rivals = [c for c in passing if CANDIDATES[c.name].kind == 'structured'
              and CANDIDATES[c.name].acts_on in ('time', 'mean')
              and c.gain >= sel.opts.not_separable_ratio * best.gain
              and _stated_excess(sel, c) <= STRUCTURE_SHARE * excess]
    return max(rivals, key=lambda c: c.gain) if rivals else best


def nested(a: str, b: str) -> bool:
    """Whether one of the two effects is a special case of the other (``simpler``)."""
    return CANDIDATES[a].simpler == b or CANDIDATES[b].simpler == a


def select_round(sel: Selector, accepted: tuple, ref: tuple, names: Sequence[str],
                 round_no: int, progress_span: tuple) -> tuple:
    """One round: score the candidates, pick one, test separability. Returns (pick, ...)."""
    cands = []
    lo, hi = progress_span
    todo = [n for n in names if compatible(accepted, n)]
    thr = sel.threshold(round_no)
    predicted = screen(sel, accepted, ref, todo)
    # the most promising first: a candidate far behind the best one found so far can be
    # neither the pick nor its not-separable rival, and is not refitted
    todo = sorted(todo, key=lambda n: -predicted.get(n, np.inf))
    best_gain = 0.0
    # the best-predicted candidate of each way of acting is refitted whenever it could matter:
    # a reference whose outlier model sets aside what the candidate would explain (an offset
    # under glitches) weighs its one-step prediction down, the refit finds it
    leaders = set()
    for how in ('time', 'mean', 'variance'):
        ranked = [n for n in todo if CANDIDATES[n].acts_on == how
                  and predicted.get(n, np.inf) >= SCREEN_SHARE * thr]
        # with the simpler one it extends (a drift the per-block check refuses leaves the
        # constant offset)
        leaders.update(ranked[:1] + [CANDIDATES[n].simpler for n in ranked[:1]
                                     if CANDIDATES[n].simpler in ranked])
    for i, name in enumerate(todo):
        sel.progress(lo + (hi - lo) * i / max(len(todo), 1), f'round {round_no + 1}: {name}')
        pred = predicted.get(name)
        reason = ''
        if name in leaders:
            pass
        elif pred is not None and pred < SCREEN_SHARE * thr:
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
        cand = score_candidate(sel, accepted, name, ref, round_no)
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
    simpler = CANDIDATES[best.name].simpler
    alt = next((c for c in passing if c.name == simpler), None)
    if alt is not None and best.gain - alt.gain < margin:
        best = alt
    best = _structure_before_noise(sel, best, passing)
    not_sep = []
    for other in passing:
        if other is best or nested(other.name, best.name):
            continue
        if other.gain < sel.opts.not_separable_ratio * best.gain:
            continue
        if not compatible(accepted + (best.name,), other.name):
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


@dataclass
class Selection:
    """
    What the selection rounds accepted.

    Attributes
    ----------
    accepted : tuple of str
        The accepted effects, in the order they were accepted.
    chosen : list of (Candidate, list of str)
        Each accepted candidate and the rivals it is not separable from.
    not_separable : list of [str, str]
        The accepted effect and each such rival.
    rounds : list of list of Candidate
        The candidates scored in each round.
    drift_checks : list of DriftCheck
        ``drift.drift_check`` of each round that picked a clock drift.
    ref : tuple
        ``Selector.score`` of the accepted model (fit, time held-out, spatial held-out).

    """

    accepted: tuple
    chosen: list
    not_separable: list
    rounds: list
    drift_checks: list
    ref: tuple


def select_effects(sel: Selector, start) -> Selection:
    """
    Accept up to ``Options.max_effects`` effects in turn, each on top of the previous ones.

    Parameters
    ----------
    sel : Selector
        The selection pairs, their blocks, the options and the cache of fits.
    start : fit.State
        The base model's state.

    Returns
    -------
    Selection

    """
    opts, data = sel.opts, sel.data
    names = [c for c in opts.candidates if c in EFFECT_NAMES]
    if not has_motion(data):
        names = [c for c in names if not CANDIDATES[c].needs_motion]
    ref = sel.score((), start)
    accepted: tuple = ()
    not_separable = []
    rounds = []
    chosen = []
    drift_checks = []
    for r in range(opts.max_effects):
        span = (0.1 + 0.25 * r, 0.1 + 0.25 * (r + 1))
        best, cands, not_sep = select_round(sel, accepted, ref, names, r, span)
        rounds.append(cands)
        if best is not None and CANDIDATES[best.name].trend_checked:
            check = drift_check(data, sel, best, cands)
            drift_checks.append(check)
            if not check.accepted:
                best.passes = False
                best.reason = check.reason
                alt = [c for c in cands if c.passes and c.name != best.name]
                best = max(alt, key=lambda c: c.gain) if alt else None
                not_sep = []
        if best is None:
            break
        accepted = accepted + (best.name,)
        chosen.append((best, not_sep))
        for other in not_sep:
            not_separable.append([best.name, other])
        ref = sel.score(accepted, best.fit.state)
    return Selection(accepted, chosen, not_separable, rounds, drift_checks, ref)
