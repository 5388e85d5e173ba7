"""
The sim-to-real gap diagnosis: detect, locate, explain, quantify (docs/design.md §5).

``diagnose(pairs, settings)`` calibrates, fits the base model with the stated noise, measures
the gap (chi-square, whiteness, tails) and where it lies (``residuals.py``), then explains it
with the ten candidate effects (``effects/``, one class each):

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
5. the gap before and after is measured on held-out blocks of all pairs (``gap.py``), and
   each accepted effect's size is reported with its uncertainty (its class's ``size``,
   ``effects/``); what no stationary effect explains is said (``findings.py``).

The report is a ``report.DiagnosisReport``; ``as_dict()`` is its JSON document.
``streams.diagnose_streams`` is the entry from the recorded streams.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial
from typing import Optional

from coreg_ros.core.calibration.auto_noise import noise_floor
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.noise_verdict import estimate_dict
from coreg_ros.core.diagnosis import gap as gp
from coreg_ros.core.diagnosis.data import DiagData, prepare, spatial_folds, time_folds
from coreg_ros.core.diagnosis.effects.base import FitReading
from coreg_ros.core.diagnosis.effects.clock import TimeOffsetCandidate
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
from coreg_ros.core.diagnosis.report import CalibrationChange, DiagnosisReport, StatedNoise
from coreg_ros.core.diagnosis.residuals import base_errors, detect_locate
from coreg_ros.core.diagnosis.selection import select_effects, Selection, Selector
from coreg_ros.core.diagnosis.summary import gap_measures, transforms
from coreg_ros.core.diagnosis.text import floor_named
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
    report : DiagnosisReport
        The report; ``report.as_dict()`` is the JSON document (keys ``gap_detected``,
        ``effects``, ``not_separable``, ``gap_before``, ``gap_after``, ``location``,
        ``verdict``, and more).
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

    report: DiagnosisReport
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
        Full noise covariances (ROS layout) overriding the settings'. Without them and with
        ``settings.noise == 'auto'`` the noise estimated with the calibration is the floor
        (``auto_noise.noise_floor``), the report's ``noise`` beside the stated one.
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
    estimate = None
    if settings.noise == 'auto' and cov_a is None and cov_b is None:
        # the noise estimated with the calibration is the floor; the stated one is reported
        estimate, cov_a, cov_b = noise_floor(pairs, settings)
    cov_a = settings.cov_a if cov_a is None else cov_a  # the full noise, if the settings have it
    cov_b = settings.cov_b if cov_b is None else cov_b
    diag = _diagnose(pairs, settings, stream_a, options or Options(),
                     progress or (lambda f, s: None), cov_a, cov_b, context or {})
    if estimate is not None:
        diag.report = replace(diag.report, noise=estimate_dict(estimate),
                              verdict=floor_named(diag.report.verdict, True))
    return diag


def _base_fit(pairs: Pairs, settings: Settings, stream_a, cov_a, cov_b, n_folds: int) -> tuple:
    """Calibrate, prepare the data and fit the base model; (data, its time blocks, the fit)."""
    # the diagnosis models outliers itself: its base fit keeps every pair
    result = calibrate(pairs, settings.updated(robust=False), cov_a=cov_a, cov_b=cov_b)
    data = prepare(pairs, settings, stream_a, cov_a, cov_b)
    folds = time_folds(data.t, n_folds)
    base = Model(data, ()).fit(start_state(_params_of(result, data.spec)), None, folds, n_folds)
    return data, folds, base


def _diagnose(pairs, settings, stream_a, opts, progress, cov_a, cov_b, context) -> Diagnosis:
    progress(0.0, 'calibrating')
    K = opts.n_folds
    data, folds, base = _base_fit(pairs, settings, stream_a, cov_a, cov_b, K)
    progress(0.05, 'detecting')
    errors = base_errors(data, base)
    detection, location = detect_locate(data, base, errors)
    # the base residuals guide data-dependent bases (the field source's position)
    data.cache['base_errors'] = errors[0]
    stride = int(np.ceil(data.n / opts.max_select_pairs))
    sel = Selector(data, np.arange(0, data.n, stride), opts, progress)
    found = select_effects(sel, base.state)
    shift = float(context.get('coarse_shift_s', 0.0))

    progress(0.85, 'final fit on all pairs')
    # the coarse search moved the pairing: that offset is an effect found, refined here
    forced = shift != 0.0 and not any(CANDIDATES[a].acts_on == 'time' for a in found.accepted)
    accepted = ((TimeOffsetCandidate.name,) if forced else ()) + found.accepted
    final = found.ref[0]
    if forced or stride > 1:
        final = Model(data, accepted).fit(final.state, None, folds, K)
    # the gap before is the recording paired at the offset the user gave, if it was moved
    given_offset = (partial(_gap_at_given_offset, *context['before'], stream_a, cov_a, cov_b,
                            opts) if 'before' in context else None)
    gap_before, gap_after, before, after, counted = _gaps(
        data, base, final, accepted, folds, errors[1], opts, given_offset)
    n_res = len(sel.idx) * data.m
    findings = _accepted_findings(FitReading.of(final), found, forced, shift, n_res)
    stamps = context.get('stamps')
    if stamps is not None:
        findings = with_stamps(stamps, findings)
    excess_left, findings = structure_checks(data, final, after, counted, findings, gap_after)
    excess = noise_excess(data, after, counted, findings, gap_after)
    gap_detected = bool(detection.gap or findings or (stamps is not None and stamps.issues))
    report = DiagnosisReport(
        gap_detected=gap_detected, effects=findings, not_separable=found.not_separable,
        gap_before=gap_before, gap_after=gap_after, noise_excess=excess,
        excess_left=excess_left, location=location,
        verdict=verdict(gap_detected, findings, found.not_separable, gap_before, gap_after,
                        detection, location, excess, stamps),
        detection=detection,
        candidates=[[c.score(n_res) for c in sorted(cs, key=lambda c: -c.gain)]
                    for cs in found.rounds],
        calibration=CalibrationChange(transforms(base), transforms(final)),
        model=data.spec.name, n_pairs=int(data.n), n_pairs_selection=int(len(sel.idx)),
        duration_s=float(data.t[-1] - data.t[0]) if data.n > 1 else 0.0,
        stated_noise=StatedNoise(list(data.sigma_a), list(data.sigma_b)),
        stamps=stamps, coarse_offset_s=shift or None)
    progress(1.0, 'done')
    return Diagnosis(report=report, data=data, base=base, final=final, before=before,
                     after=after, rounds=found.rounds)


def _gaps(data: DiagData, base: Fit, final: Fit, accepted: tuple, folds: np.ndarray,
          sd: np.ndarray, opts: Options, given_offset) -> tuple:
    """
    Measure the gap before and after the accepted effects on held-out blocks of all pairs.

    Parameters
    ----------
    data : DiagData
        All pairs.
    base, final : Fit
        The base model and the model with the accepted effects, on all pairs.
    accepted : tuple of str
        The accepted effects.
    folds : ndarray of int, shape (N,)
        The time blocks the fits were made with.
    sd : ndarray, shape (N, m)
        Standard deviation of each raw error under the stated noise.
    opts : Options
        The number of blocks and the seed of the workspace cells.
    given_offset : callable or None
        ``given_offset(blocks_kind)``: the gap before at the offset the user gave
        (``_gap_at_given_offset``), when the pairs were made at another one.

    Returns
    -------
    gap_before, gap_after : gap.GapBefore, gap.GapAfter
    before, after : Heldout
        Held-out predictions of every pair by the base and the final model.
    counted : ndarray of bool, shape (N,)
        Pairs not set aside by an outlier model.

    """
    K = opts.n_folds
    gap_folds, blocks_kind = folds, 'time blocks'
    if any(CANDIDATES[a].spatial and CANDIDATES[a].acts_on == 'mean' for a in accepted):
        # a field is tested where it can be: on unseen cells of the workspace, between seen
        # ones (a time block may hold a region nothing else visits)
        gap_folds = spatial_folds(data.b_points[:, 0, :], K, seed=opts.seed)
        blocks_kind = 'workspace cells'
    before = base.heldout(gap_folds, K)
    after = final.heldout(gap_folds, K) if accepted else before
    held_after = gap_measures(data, final, after)
    everyone = np.ones(data.n, dtype=bool)
    counted = after.p_in > 0.5 if final.state.var.eps > 0 else everyone
    if given_offset is not None:
        held_before, stated_before = given_offset(blocks_kind)
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
    return gap_before, gap_after, before, after, counted


def _gap_at_given_offset(pairs: Pairs, settings: Settings, stream_a, cov_a, cov_b,
                         opts: Options, blocks_kind: str) -> tuple:
    """
    Measure the gap before on the recording paired at the offset the user gave (base model).

    Returns
    -------
    summary.HeldOutGap, gap.StatedGap
        On the same kind of held-out blocks as the gap after.

    """
    K = opts.n_folds
    data = prepare(pairs, settings, stream_a, cov_a, cov_b)
    folds = (time_folds(data.t, K) if blocks_kind == 'time blocks'
             else spatial_folds(data.b_points[:, 0, :], K, seed=opts.seed))
    result = calibrate(pairs, settings.updated(robust=False), cov_a=cov_a, cov_b=cov_b)
    fit = Model(data, ()).fit(start_state(_params_of(result, data.spec)), None, folds, K)
    held = fit.heldout(folds, K)
    return (gap_measures(data, fit, held),
            gp.stated_measures(data, held.quad_stated, held.e, base_errors(data, fit)[1],
                               np.ones(data.n, dtype=bool)))


def _accepted_findings(reading: FitReading, found: Selection, forced: bool, shift: float,
                       n_res: int) -> list:
    """
    Size the accepted effects in the final fit and name them as findings.

    Parameters
    ----------
    reading : FitReading
        The final fit.
    found : Selection
        What the selection accepted.
    forced : bool
        A time offset the coarse search found goes first (the selection named no clock).
    shift : float
        The offset the coarse search moved the pairing by, s (added to the clock's estimates).
    n_res : int
        Residuals of the selection pairs.

    """
    def sized(name):
        est = CANDIDATES[name].size(reading)
        return est.shifted(shift) if shift else est

    findings = []
    if forced:
        findings.append(Finding.of(replace(sized(TimeOffsetCandidate.name), coarse_s=shift),
                                   source=COARSE_SEARCH))
    for cand, not_sep in found.chosen:
        trend_checked = CANDIDATES[cand.name].trend_checked and found.drift_checks
        findings.append(Finding.of(
            sized(cand.name), held_out_gain=float(cand.gain),
            held_out_gain_per_residual=float(cand.gain / n_res),
            blocks_improved=int(np.sum(cand.fold_gains > 0)), blocks=int(len(cand.fold_gains)),
            spatial_held_out_gain=(None if cand.spatial_gain is None
                                   else float(cand.spatial_gain)),
            not_separable_with=list(not_sep) if not_sep else None,
            per_block_offsets=found.drift_checks[-1] if trend_checked else None))
    return findings
