"""
The sim-to-real gap diagnosis: detect, locate, explain, quantify (docs/design.md §5).

``diagnose(pairs, settings)`` calibrates, fits the base model with the stated noise, measures
the gap (chi-square, whiteness, tails) and where it lies (``residuals.py``), then explains it
with the ten candidate effects of ``candidates.py``:

1. every candidate is fitted as an extension of the model (joint Gauss-Newton with the
   calibration, or maximum likelihood for the noise effects, ``fit.py``) and scored by its
   gain in held-out log-likelihood on contiguous time blocks (and on cells of the workspace
   for spatial effects), each block predicted by the fit on the others (``selection.py``);
2. a candidate is accepted only if it gains in (almost) every block, by a practical size (a
   share of a nat per residual, not merely a tiny p-value) and, for spatial effects, also on
   unseen parts of the workspace; the simpler of nested candidates is preferred;
3. when another candidate gains nearly as much and the two explain the same thing (neither
   adds to the other), the pair is reported as not separable with the recorded motion;
4. up to three effects are accepted in turn, each on top of the previous ones;
5. the gap before and after is measured on held-out blocks of all pairs, and each accepted
   effect's size is reported with its uncertainty (``summary.py``, ``findings.py``).

``streams.diagnose_streams`` is the entry from the recorded streams.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.diagnosis import gap as gp
from coreg_ros.core.diagnosis.data import DiagData, prepare, spatial_folds, time_folds
from coreg_ros.core.diagnosis.effects.base import FitReading
from coreg_ros.core.diagnosis.effects.finding import COARSE_SEARCH, Finding
from coreg_ros.core.diagnosis.effects.registry import CANDIDATES
from coreg_ros.core.diagnosis.findings import (
    noise_excess,
    structure_checks,
    verdict,
    with_stamps,
)
from coreg_ros.core.diagnosis.fit import Fit, Heldout, Model, start_state
from coreg_ros.core.diagnosis.options import Options, Progress
from coreg_ros.core.diagnosis.residuals import base_errors, detect_locate
from coreg_ros.core.diagnosis.selection import select_effects, Selector
from coreg_ros.core.diagnosis.summary import gap_measures, transforms
from coreg_ros.core.models import Parameters
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import Pairs, PoseStream
import numpy as np


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


def diagnose(pairs: Pairs, settings: Settings, stream_a: Optional[PoseStream] = None,
             options: Optional[Options] = None, progress: Optional[Progress] = None,
             cov_a: Optional[np.ndarray] = None, cov_b: Optional[np.ndarray] = None,
             context: Optional[dict] = None) -> Diagnosis:
    """
    Diagnose the gap between a recording and the model with its stated noise.

    Parameters
    ----------
    pairs : Pairs
        Paired samples (``pairing.pair_for``).
    settings : Settings
        Model, method and stated noise (``sigma_a``, ``sigma_b``).
    stream_a : PoseStream, optional
        Device A's whole stream (better velocities and time shifts than the pairs alone).
    options : Options, optional
        Tuning; the defaults when None.
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
    errors = base_errors(data, base)
    detection, location = detect_locate(data, base, errors)
    # the base residuals guide data-dependent bases (the field source's position)
    data.cache['base_errors'] = errors[0]

    n = data.n
    stride = int(np.ceil(n / opts.max_select_pairs))
    idx = np.arange(0, n, stride)
    sel = Selector(data, idx, opts, progress)
    found = select_effects(sel, base.state)
    accepted, chosen, ref = found.accepted, found.chosen, found.ref
    rounds, not_separable, drift_checks = found.rounds, found.not_separable, found.drift_checks
    shift = float(context.get('coarse_shift_s', 0.0))

    progress(0.85, 'final fit on all pairs')
    forced_offset = shift != 0.0 and not any(CANDIDATES[a].acts_on == 'time' for a in accepted)
    if forced_offset:
        # the coarse search moved the pairing: that offset is an effect found, refined here
        accepted = ('time_offset',) + accepted
        final = Model(data, accepted).fit(ref[0].state, None, folds, K)
    elif stride == 1:
        final = ref[0]
    else:
        final = Model(data, accepted).fit(ref[0].state, None, folds, K)
    gap_folds, blocks_kind = folds, 'time blocks'
    if any(CANDIDATES[a].spatial and CANDIDATES[a].acts_on == 'mean' for a in accepted):
        # a field is tested where it can be: on unseen cells of the workspace, between seen
        # ones (a time block may hold a region nothing else visits)
        gap_folds = spatial_folds(data.b_points[:, 0, :], K, seed=opts.seed)
        blocks_kind = 'workspace cells'
    before = base.heldout(gap_folds, K)
    after = final.heldout(gap_folds, K) if accepted else before
    held_after = gap_measures(data, final, after)
    sd = errors[1]
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
        held_before = gap_measures(b_data, b_fit, b_held)
        stated_before = gp.stated_measures(b_data, b_held.quad_stated, b_held.e,
                                           base_errors(b_data, b_fit)[1],
                                           np.ones(b_data.n, dtype=bool))
    else:
        held_before = gap_measures(data, base, before)
        stated_before = gp.stated_measures(data, before.quad_stated, before.e, sd, everyone)
    stated_after = gp.stated_measures(data, after.quad_stated, after.e, sd, counted)
    gap_before = gp.GapBefore(held_out=held_before, stated=stated_before,
                              held_out_on=blocks_kind)
    gap_after = gp.GapAfter(
        held_out=held_after, stated=stated_after,
        share_of_excess_explained=gp.share_explained(stated_before.counted, stated_after.counted,
                                                     stated_after.excluded_pairs.share),
        held_out_on=blocks_kind, rms_moved=gp.rms_moved(stated_before.counted,
                                                        stated_after.counted))
    n_res = len(idx) * data.m
    reading = FitReading.of(final)

    def sized(name):
        est = CANDIDATES[name].size(reading)
        return est.shifted(shift) if shift else est

    findings = []
    if forced_offset:
        findings.append(Finding.of(replace(sized('time_offset'), coarse_s=shift),
                                   source=COARSE_SEARCH))
    for cand, not_sep in chosen:
        trend = drift_checks[-1] if drift_checks and CANDIDATES[cand.name].trend_checked else None
        findings.append(Finding.of(
            sized(cand.name), held_out_gain=float(cand.gain),
            held_out_gain_per_residual=float(cand.gain / n_res),
            blocks_improved=int(np.sum(cand.fold_gains > 0)), blocks=int(len(cand.fold_gains)),
            spatial_held_out_gain=(None if cand.spatial_gain is None
                                   else float(cand.spatial_gain)),
            not_separable_with=list(not_sep) if not_sep else None, per_block_offsets=trend))
    stamps = context.get('stamps')
    if stamps is not None:
        findings = with_stamps(stamps, findings)
    structure, findings = structure_checks(data, final, after, counted, findings, gap_after)
    excess = noise_excess(data, after, counted, findings, gap_after)
    gap_detected = bool(detection.gap or findings)
    if stamps is not None and stamps['issues']:
        gap_detected = True
    report = {
        'gap_detected': gap_detected,
        'effects': [f.as_dict() for f in findings],
        'not_separable': not_separable,
        'gap_before': gap_before.as_dict(),
        'gap_after': gap_after.as_dict(),
        'noise_excess': None if excess is None else excess.as_dict(),
        'excess_left': structure.as_dict(),
        'location': location.as_dict(),
        'verdict': verdict(gap_detected, findings, not_separable, gap_before, gap_after,
                           detection, location, excess),
        'detection': detection.as_dict(),
        'candidates': [[c.row(n_res) for c in sorted(cs, key=lambda c: -c.gain)]
                       for cs in rounds],
        'calibration': {'before': transforms(base), 'after': transforms(final)},
        'model': spec.name, 'n_pairs': int(n), 'n_pairs_selection': int(len(idx)),
        'duration_s': float(data.t[-1] - data.t[0]) if n > 1 else 0.0,
        'stated_noise': {'sigma_a': list(data.sigma_a), 'sigma_b': list(data.sigma_b)},
    }
    if stamps is not None:
        report['stamps'] = stamps
        if stamps['issues'] and not findings:
            report['verdict'] = ('timing issues in the stamps, residuals fit the model: '
                                 + '; '.join(f'{d["device"]}: {d["text"]}'
                                             for d in stamps['devices']))
    if shift:
        report['coarse_offset_s'] = shift
    progress(1.0, 'done')
    return Diagnosis(report=report, data=data, base=base, final=final, before=before,
                     after=after, rounds=rounds)
