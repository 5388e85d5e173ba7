"""
Practical significance: each named effect re-tested beside the others, sized against the noise.

The selection adds effects one at a time; an effect accepted early may have stood in for one
found later (outliers taken for a noise level before the offset behind them was seen). So
every accepted effect is re-tested in the final model (``retest``): dropped from it, it must
lose held-out log-likelihood by the practical threshold, in (almost) every block where it
expects to gain (``selection.blocks_judged``), with the others present; the one that fails by
most goes, and the rest are tested again. Outliers must
also set aside pairs that lie beyond the stated noise (``OUTLIER_STATED_P``): pairs off only a
noise level the model shrank are not glitches.

An effect that passes is still only *found* when it matters at the stated noise
(``practical``):

- a structured effect must claim a channel (position, rotation) by moving some pair there by
  ``channels.SIZE_FLOOR`` of its stated noise, lower the held-out RMS of a channel it claims by
  ``channels.MIN_RMS_GAIN`` and raise that of no channel by as much (``channels``);
- a noise effect must change the noise's σ by at least ``NOISE_FLOOR`` (10 %) on at least
  ``NOISE_SHARE`` of the pairs;
- outliers must be at least ``OUTLIER_FLOOR`` of the pairs;
- a noise change at an instant (``noise_step``) must widen errors that are white: an excess
  smooth in time (``structure.SMOOTH_LAG1``) follows the sensor's path, a structured error
  there (metal brought near for a while), which the report names by what is left, not noise.

Below that it is listed as ``not_significant``, with its size, never as found. The named
effects are ordered by the share of the gap (the held-out excess at the stated noise) each
explains, dropped from the final model; noise effects, which explain none of it, after them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.channels import (
    channel_reasons,
    displacement,
    SIZE_FLOOR,
)
from coreg_ros.core.diagnosis.effects.registry import CANDIDATES
from coreg_ros.core.diagnosis.fit import Model
from coreg_ros.core.diagnosis.gap import position_rotation_rows
from coreg_ros.core.diagnosis.judged import (
    blocks_judged,
    expected_block_gains,
    own_gain_reasons,
)
from coreg_ros.core.diagnosis.record import optional, Record
from coreg_ros.core.diagnosis.residuals import base_errors
from coreg_ros.core.diagnosis.structure import SMOOTH_LAG1, smoothness
from coreg_ros.core.distributions import chi2_ppf
import numpy as np

#: A noise effect changes σ by at least this much (relative) ...
NOISE_FLOOR = 0.1
#: ... on at least this share of the pairs.
NOISE_SHARE = 0.1
#: Outliers count when at least this share of the pairs are (one glitch in a thousand).
OUTLIER_FLOOR = 0.001
#: ... and when the pairs they set aside lie, on average, beyond the χ²/dof the stated noise
#: gives one pair in a hundred (an outlier is off the stated noise, not off a shrunk one).
OUTLIER_STATED_P = 0.01
OUTLIERS = 'outliers'


@dataclass(frozen=True, kw_only=True)
class EffectTest(Record):
    """
    An accepted effect re-tested in the final model (the model without it against the model).

    Attributes
    ----------
    name : str
    held_out_gain : float
        Held-out log-likelihood lost without it, the others present, nats.
    blocks_improved, blocks : int
        Blocks where it gains, of all (time blocks, or workspace cells for spatial effects).
    share_of_gap : float
        The held-out excess at the stated noise (χ²/dof minus one) it takes off, as a share of
        the excess before any effect (0 for noise effects, which take none off).
    rms_gain_position, rms_gain_rotation : float, optional
        Relative fall of the held-out position (rotation) RMS at the stated noise, on the
        blocks it is judged on (workspace cells for a spatial effect).
    judged_gain_position, judged_gain_rotation : float, optional
        The same judged against the stated noise (``rms_gain``): what
        ``channels.channel_reasons`` holds to ``MIN_RMS_GAIN``; equal to the above while the
        errors are within the stated noise.
    passes : bool
        It keeps a practical held-out gain with the others present.
    reason : str

    """

    name: str
    held_out_gain: float
    blocks_improved: int
    blocks: int
    share_of_gap: float
    rms_gain_position: Optional[float] = optional()
    rms_gain_rotation: Optional[float] = optional()
    judged_gain_position: Optional[float] = optional()
    judged_gain_rotation: Optional[float] = optional()
    passes: bool
    reason: str


@dataclass(frozen=True, kw_only=True)
class NotSignificant(Record):
    """
    An effect the held-out data support but too small to matter at the stated noise.

    Attributes
    ----------
    name, kind : str
    estimate : Record
        Its size with uncertainty (an instance of the effect's class).
    practical_size : float
        Structured: the largest pair displacement over that pair's stated noise; noise: the
        relative change of σ on the pairs it changes most (``NOISE_SHARE``); outliers: the
        share of the pairs.
    floor : float
        What ``practical_size`` must reach.
    text : str

    """

    name: str
    kind: str
    estimate: Record
    practical_size: float
    floor: float
    text: str


def _ms(e: np.ndarray, rows: Optional[list], sel: np.ndarray) -> Optional[float]:
    if rows is None or not sel.any():
        return None
    return float(np.mean(e[sel][:, rows] ** 2))


def rms_gain(with_ms: Optional[float], without_ms: Optional[float],
             stated_ms: Optional[float]) -> Optional[float]:
    """
    Relative fall of a channel's held-out RMS an effect makes, judged at the stated noise.

    ``1 - sqrt(1 - (b² - a²) / min(b², s²))`` for the mean squares ``a²`` with the effect,
    ``b²`` without and the stated noise's ``s²``: the relative fall of the RMS ``1 - a/b``
    when the errors are within the stated noise; beyond it, the fall of the mean square is
    measured against the stated noise (an error left larger than stated by another effect, a
    jitter or a larger noise, does not dilute what this one explains). Negative: it raises
    the RMS. Without ``s²``: ``1 - a/b``.
    """
    if with_ms is None or not without_ms:
        return None
    if not stated_ms:
        return float(1.0 - np.sqrt(with_ms / without_ms))
    ref = min(without_ms, stated_ms)
    return float(1.0 - np.sqrt(max(1.0 - (without_ms - with_ms) / ref, 0.0)))


def _stated_sd(sel, state) -> np.ndarray:
    """Stated σ of each raw error of the selection pairs (n, m): B's and A's carried noise."""
    key = ('stated_sd', len(sel.idx), int(sel.idx[0]), int(sel.idx[-1]))
    got = sel.data.cache.get(key)
    if got is None:
        model = Model(sel.data, ())
        got = np.concatenate([model.evaluate(state, ch, jac=False).sd
                              for ch in model.chunks(sel.idx)])
        sel.data.cache[key] = got
    return got


def _fold_kind(sel, name: str, scored: tuple):
    """Return the held-out predictions and blocks an effect is judged on: cells if spatial."""
    fit, h, hs = scored
    if CANDIDATES[name].spatial:
        if hs is None:
            hs = sel.spatial_heldout(scored)
        return hs, sel.sf
    return h, sel.tf


def _drop_one(sel, names: tuple, name: str, full: tuple, base_excess: float) -> EffectTest:
    """Test ``name`` in the model ``names`` against the model without it."""
    rest = tuple(n for n in names if n != name)
    without = sel.score(rest, full[0].state)
    h, labels = _fold_kind(sel, name, full)
    h0, _ = _fold_kind(sel, name, without)
    fold_gains = h.fold_sums(h.ll) - h0.fold_sums(h0.ll)
    gain = float(fold_gains.sum())
    expected = expected_block_gains(sel, full[0], name, labels)
    judged = blocks_judged(sel, name, labels, expected=expected)
    blocks = int(judged.sum())
    improved = int(np.sum(fold_gains[judged] > 0))
    thr = sel.threshold(0)
    reasons = own_gain_reasons(expected, thr)
    if gain < thr:
        reasons.append(f'with the others present its held-out gain is {gain:.1f} nats, below '
                       f'the practical {thr:.1f}')
    if improved < max(blocks - 1, 1):
        reasons.append(f'with the others present it improves only {improved} of {blocks} '
                       f'blocks')
    # the stated-noise measures on the time blocks, over the pairs the full model counts
    ht, h0t = full[1], without[1]
    counted = ht.p_in > 0.5
    if not counted.any():
        counted = np.ones_like(counted)
    data = sel.data
    m = data.m
    pos, rot = position_rotation_rows(data)
    ex_full = float(np.mean(ht.quad_stated[counted]) / m) - 1.0
    # without an outlier model every pair is counted (the outliers are its gap)
    counted0 = counted if h0t.p_in.min() < 1.0 else np.ones_like(counted)
    ex_without = float(np.mean(h0t.quad_stated[counted0]) / m) - 1.0
    set_aside = ~(ht.p_in > 0.5)
    if name == OUTLIERS and set_aside.any():
        # an outlier is far off at the stated noise, not only off a noise the model shrank
        # (a recording inside its stated noise split into a tight half and the rest)
        stated = float(np.mean(ht.quad_stated[set_aside]) / m)
        floor = float(chi2_ppf(1.0 - OUTLIER_STATED_P, m) / m)
        if stated < floor:
            reasons.append(f'the pairs it sets aside lie at χ²/dof {stated:.2f} at the stated '
                           f'noise, inside it (an outlier lies beyond {floor:.2f})')
    share = 0.0
    if CANDIDATES[name].kind == 'structured' and base_excess > 1e-9:
        share = float(np.clip((ex_without - ex_full) / base_excess, 0.0, 1.0))
    # the channels' RMS on the blocks the effect is judged on: a field's fit is tried on
    # unseen cells of the workspace, not on a time block that may visit a region no other
    # block does (where any field model only extrapolates)
    kept = h.p_in > 0.5
    if not kept.any():
        kept = np.ones_like(kept)
    sd = _stated_sd(sel, full[0].state)
    gains, judged = {}, {}
    for key, rows in (('position', pos), ('rotation', rot)):
        a, b = _ms(h.e, rows, kept), _ms(h0.e, rows, kept)
        gains[key] = rms_gain(a, b, None)
        judged[key] = rms_gain(a, b, _ms(sd, rows, kept))
    return EffectTest(name=name, held_out_gain=gain, blocks_improved=improved, blocks=blocks,
                      share_of_gap=share, rms_gain_position=gains['position'],
                      rms_gain_rotation=gains['rotation'],
                      judged_gain_position=judged['position'],
                      judged_gain_rotation=judged['rotation'], passes=not reasons,
                      reason='; '.join(reasons) if reasons else 'passes')


def _simplest(sel, names: tuple, start) -> tuple:
    """
    Replace each effect by the simpler one it extends when that does as well beside the others.

    A clock step whose step is small, a field that is only a scale: the simpler model loses
    less than the nested margin of held-out log-likelihood (``Options.nested_share`` of the
    practical threshold), so the simpler is named.
    """
    margin = max(sel.opts.min_gain, sel.opts.nested_share * sel.threshold(0))
    for name in names:
        simpler = CANDIDATES[name].simpler
        if simpler is None or simpler in names:
            continue
        other = tuple(simpler if n == name else n for n in names)
        if any(CANDIDATES[a].acts_on == 'time' for a in other if a != simpler) and (
                CANDIDATES[simpler].acts_on == 'time'):
            continue
        full = sel.score(names, start)
        alt = sel.score(other, full[0].state)
        h, _ = _fold_kind(sel, name, full)
        h0, _ = _fold_kind(sel, name, alt)
        if float(h.ll.sum()) - float(h0.ll.sum()) < margin:
            names = other
    return names


def retest(sel, accepted: tuple, start, base_excess: float) -> tuple:
    """
    Re-test every accepted effect in the final model; drop those the others explain.

    Parameters
    ----------
    sel : selection.Selector
        The selection pairs, their blocks and the cache of fits.
    accepted : tuple of str
        The effects the selection accepted.
    start : fit.State
        A state of the accepted model (warm start of the models without one effect).
    base_excess : float
        The held-out excess (χ²/dof at the stated noise minus one) of the base model on the
        selection pairs.

    Returns
    -------
    kept : tuple of str
        The effects that keep a practical gain with the others present.
    tests : dict of str to EffectTest
        The last test of every accepted effect (the dropped ones' says why).

    """
    names = _simplest(sel, tuple(accepted), start)
    tests: dict = {}
    while names:
        full = sel.score(names, start)
        now = {n: _drop_one(sel, names, n, full, base_excess) for n in names}
        tests.update(now)
        failing = [t for t in now.values() if not t.passes]
        if not failing:
            break
        worst = min(failing, key=lambda t: t.held_out_gain)
        names = tuple(n for n in names if n != worst.name)
    return names, tests


def noise_change(fit, name: str) -> float:
    """
    Return the relative change of σ a noise effect makes, on the pairs it changes most.

    Per pair, σ's factor along the direction it changes most: the square roots of the
    generalized eigenvalues of the error's covariance with the effect's parameters against
    that without them (the others kept), the one farthest from one in log. A noise level
    changes every direction alike; a noise shape (one axis of B noisier) or a jitter (along the
    motion) changes one direction, which the total variance would dilute among the others.
    The ``1 - NOISE_SHARE`` quantile of ``|log factor|`` is returned as a relative change
    (``exp(q) - 1``).
    """
    var = fit.state.var
    params = CANDIDATES[name].var_params
    off = var.with_values(params, [getattr(vm.VarState(), p) for p in params])
    st = fit.stats
    q = float(np.quantile(_largest_log_factor(var, off, st), 1.0 - NOISE_SHARE))
    return float(np.expm1(q))


def _largest_log_factor(var, off, st, chunk: int = 8192) -> np.ndarray:
    """Per pair, the largest ``|log|`` of σ's factor along a direction, ``var`` over ``off``."""
    n = len(st.z)
    out = np.empty(n)
    for i in range(0, n, chunk):
        part = vm.PairStats(*(_rows(getattr(st, f), i, chunk) for f in (
            'z', 'lam', 'u', 'log_g', 'V')), markers=st.markers,
            step=_rows(st.step, i, chunk))
        c1 = vm.pair_covariances(var, part)
        c0 = vm.pair_covariances(off, part)
        L = np.linalg.cholesky(c0)
        x = np.linalg.solve(L, c1)
        w = np.linalg.eigvalsh(np.linalg.solve(L, np.swapaxes(x, 1, 2)))
        out[i:i + chunk] = np.max(np.abs(0.5 * np.log(np.maximum(w, 1e-300))), axis=1)
    return out


def _rows(a, i: int, chunk: int):
    return None if a is None else a[i:i + chunk]


def widened_smoothness(fit, name: str) -> Optional[float]:
    """
    Return the lag-one autocorrelation of the excess a noise change widens the noise for.

    For a noise effect that changes at an instant (``changes_at``): the errors of the final
    fit over their stated σ on the side the noise grew (after the instant for a factor above
    one, before it below), against the other side (``structure.smoothness``, the other side's
    own autocorrelation taken off). None for other effects or without pairs on both sides.
    """
    effect = CANDIDATES[name]
    data = fit.model.data
    found = data.cache.get(effect.changes_at) if effect.changes_at else None
    if effect.kind != 'noise' or found is None:
        return None
    e, sd = base_errors(data, fit)[:2]
    after = (data.t - data.t[0]) >= float(found.at_s)
    grew = after if getattr(fit.state.var, effect.var_params[0]) >= 0.0 else ~after
    if grew.sum() < 4 or (~grew).sum() < 4:
        return None
    z = e / sd
    return smoothness(z[grew], z[~grew], rest_lag=True)


def _noise_feature(reading, name: str) -> Optional[float]:
    """
    Return the relative size of what sets a noise effect apart from a noise level, or None.

    Distance noise: σ at the farthest pair over σ at the median distance, less one; a noise
    shape: its largest axis factor over its smallest, less one.
    """
    if name not in ('distance_noise', 'anisotropic_noise'):
        return None
    est = CANDIDATES[name].size(reading)
    ratio = est.edge_to_centre if name == 'distance_noise' else est.ratio
    return float(abs(ratio - 1.0))


def practical(reading, names: tuple, tests: dict) -> tuple:
    """
    Split the re-tested effects into those that matter at the stated noise and the others.

    Parameters
    ----------
    reading : effects.base.FitReading
        The final fit on all pairs, with every effect of ``names``.
    names : tuple of str
        The effects that passed ``retest``.
    tests : dict of str to EffectTest
        Their tests (the held-out RMS gains).

    Returns
    -------
    kept : tuple of str
        Ordered by the share of the gap explained (structured), then noise effects by gain.
    not_significant : list of NotSignificant

    """
    kept, small = [], []
    for name in names:
        effect = CANDIDATES[name]
        test = tests.get(name)
        reasons = []
        if effect.acts_on in ('time', 'mean'):
            moved = displacement(reading.fit, name)
            size, floor = max(moved.values()), SIZE_FLOOR
            reasons += channel_reasons(moved, test)
        elif name == OUTLIERS:
            size, floor = reading.var.eps, OUTLIER_FLOOR
            if size < floor:
                reasons.append(f'{size * 100:.3f} % of the pairs (floor {floor * 100:g} %)')
        else:
            size, floor = noise_change(reading.fit, name), NOISE_FLOOR
            feature = _noise_feature(reading, name)
            if size < floor:
                reasons.append(f'it changes the noise by {size * 100:.1f} % on '
                               f'{NOISE_SHARE * 100:.0f} % of the pairs (floor '
                               f'{floor * 100:g} %)')
            elif feature is not None and feature < floor:
                # a noise level, not the effect's own form: the level is noise_scale's
                size = feature
                reasons.append(f'what sets it apart from a noise level changes σ by only '
                               f'{feature * 100:.1f} % (floor {floor * 100:g} %)')
            smooth = widened_smoothness(reading.fit, name)
            if smooth is not None and smooth >= SMOOTH_LAG1:
                reasons.append(f'the errors it widens the noise for are smooth in time '
                               f'(lag-one {smooth:.2f}): a structured error, not noise')
        if reasons:
            estimate = effect.size(reading)
            small.append(NotSignificant(
                name=name, kind=effect.kind, estimate=estimate, practical_size=float(size),
                floor=float(floor), text=f'{estimate.text}: not significant, '
                                         + '; '.join(reasons)))
        else:
            kept.append(name)

    def order(n):
        t = tests.get(n)
        structured = CANDIDATES[n].kind == 'structured'
        return (0 if structured else 1, -(t.share_of_gap if t and structured else 0.0),
                -(t.held_out_gain if t else 0.0))

    return tuple(sorted(kept, key=order)), small
