"""
The clock offset estimated jointly with T0 and T1 from the streams (and the fit at a given one).

With ``settings.estimate_time_offset`` the offset τ (and, if asked, the drift κ) is estimated
jointly with T0 and T1: candidates from the cross-correlation of the devices' angular speeds
(``clock.timing.coarse_offsets``) and the given value are each fitted on a subsample of B's
samples; the best is refined by Gauss-Newton steps on τ with φ eliminated
(``clock.timing.offset_step``), re-pairing at every step, first on the subsample and then on all
samples, until a step is below ``LINEAR_STEP_S`` (where the pairs are linear in τ to well below
the noise); that last step is applied to τ and φ together, and the covariance of φ is
marginalised over τ. Every round's fit is the robust fit of ``calibrate``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from coreg_ros.core.calibration.calibrate import calibrate, MAX_REJECTED_SHARE
from coreg_ros.core.calibration.observability import held_basis, result_covariances
from coreg_ros.core.calibration.pairing import own_rows, pair_for, validated_streams
from coreg_ros.core.clock.coarse import (
    clock_step,
    CoarsePeak,
    lever_speed_correlation,
    main_peak,
    MAX_CANDIDATES,
    offsets_by_block,
    SAME_PEAK_WIDTHS,
    speed_correlation,
    SpeedCorrelation,
)
from coreg_ros.core.clock.timing import OffsetStep, query_seconds, velocity_step
from coreg_ros.core.clock.trajectory import Trajectory, VELOCITY_HALF_WINDOW
from coreg_ros.core.distributions import chi2_sf
from coreg_ros.core.errors import CoregError, InconsistentDataError, TooFewPairsError
from coreg_ros.core.estimator import output_covariance
from coreg_ros.core.estimator.linearized import PairData
from coreg_ros.core.estimator.posterior import tangent_map
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, PairingReport, PoseStream, TimeOffset
import numpy as np

#: A step of τ below this (s) is applied without re-pairing (the pairs are linear in τ over
#: it: ½ a δτ² is 0.5 µm at 1 m/s² acceleration).
LINEAR_STEP_S = 1e-3
#: B samples of the subsample on which the offset candidates are compared and refined.
SUBSAMPLE_B = 1500
#: Gauss-Newton rounds on τ (each re-pairs and refits).
MAX_ROUNDS = 8
#: Candidates refined after their first round.
REFINED_CANDIDATES = 2
#: Iteration limit of the fits that compare candidates.
TRIAL_ITERATIONS = 8
#: Blocks whose coarse offsets differ by more than this (s) witness a clock step.
STEP_TOLERANCE_S = 0.1
#: Candidates closer than this (s) are one.
SAME_CANDIDATE_S = 2e-3
#: A further search's lag is a new candidate only this far (s) from every other: within a
#: correlation peak's width it is the same lag, which the fit refines anyway.
NEW_LAG_S = 0.25
#: The coarse estimate replaces the given offset only if it lies more than this many of its
#: σ from it (otherwise the given value is kept, as the motion cannot tell them apart).
COARSE_EXCLUDES_SIGMAS = 3.0
#: A coarse lag is clear when its trial fit's median residual is at most this share of the
#: best fit at any other lag (a wrong lag leaves residuals of the motion's size).
FIT_CLEAR_RATIO = 0.2


def fit_at_offset(stream_a: PoseStream, streams_b: list, settings: Settings,
                  prior: Optional[Prior], timing: TimeOffset
                  ) -> tuple[CalibrationResult, PairingReport]:
    """Pair at the offset ``timing`` (given, not estimated) and run the robust fit there."""
    pairs, report = pair_for(stream_a, streams_b, settings, timing)
    try:
        result = calibrate(pairs, settings, prior)
    except TooFewPairsError as e:
        raise TooFewPairsError(f'{e} ({report.summary()})') from e
    return replace(result, time_offset=timing), report


@dataclass
class _Context:
    """What every round of the offset search needs: the validated streams and the noise."""

    stream_a: PoseStream
    streams_b: list
    settings: Settings
    prior: Optional[Prior]
    trajectory: Trajectory
    origin_ns: int
    reference_ns: int
    half: float
    cov_a: np.ndarray
    cov_b: np.ndarray
    max_rejected_share: float = MAX_REJECTED_SHARE

    @classmethod
    def build(cls, stream_a, streams_b, settings, prior):
        spec = SPECS[settings.model]
        a, bs = validated_streams(stream_a, streams_b, settings.model == 'full_pose')
        origin = int(a.stamps[0])
        t = (a.stamps - np.int64(origin)).astype(float) * 1e-9
        trajectory = Trajectory(t, a.position, a.quat_wxyz)
        step = trajectory.median_step() if len(t) > 1 else 0.0
        ref = (int(bs[0].stamps[0]) + int(bs[0].stamps[-1])) // 2
        return cls(a, bs, settings, prior, trajectory, origin, ref,
                   max(VELOCITY_HALF_WINDOW, 1.5 * step),
                   settings.cov_a, output_covariance(settings.cov_b, spec))

    def timing(self, tau: float, kappa: Optional[float]) -> TimeOffset:
        return TimeOffset(tau, drift_ppm=None if kappa is None else kappa * 1e6,
                          reference_ns=self.reference_ns)


@dataclass
class _Round:
    """The state after a round: the fit at (τ, κ) and the step it proposes."""

    result: CalibrationResult
    report: PairingReport
    params: Parameters
    step: OffsetStep
    tau: float
    kappa: Optional[float]
    half: float

    def score(self) -> float:
        """
        Median squared residual per pair.

        A wrong offset for part of the data (a clock step) does not hide a candidate that fits
        the rest.
        """
        r = self.result.residuals
        return float(np.median(np.sum(r * r, axis=1))) if len(r) else float('inf')


def _subsampled(streams_b: list, target: int) -> list:
    """Every k-th sample of B (marker 1 for three markers) so that about ``target`` remain."""
    first = streams_b[0]
    k = max(1, len(first) // target)
    if k == 1:
        return streams_b
    sub = PoseStream(first.stamps[::k], first.position[::k], first.quat_wxyz[::k],
                     first.frame_id, None if first.receive_stamps is None
                     else first.receive_stamps[::k])
    return [sub] + streams_b[1:]


def _round(ctx: _Context, streams_b: list, tau: float, kappa: Optional[float],
           start: Optional[Parameters]) -> _Round:
    """Pair at (τ, κ), fit (from ``start`` if given) and compute the offset step."""
    settings = ctx.settings
    timing = ctx.timing(tau, kappa)
    pairs, report = pair_for(ctx.stream_a, streams_b, settings, timing, validated=True)
    try:
        result = calibrate(pairs, settings, ctx.prior, start=start, warm=start is not None,
                           max_rejected_share=ctx.max_rejected_share)
    except TooFewPairsError as e:
        raise TooFewPairsError(f'{e} ({report.summary()})') from e
    spec = SPECS[settings.model]
    params = Parameters(spec, result.params, list(result.charts))
    keep = np.flatnonzero(result.inliers)
    # the pairs are this round's own (pair_for made them): the inliers are moved to the front
    # of the arrays the pairing allocated instead of copied (the same values; B's rows may be
    # views of B's stream and are copied)
    data = PairData(*(None if x is None else own_rows(x, keep) for x in (
        pairs.pos_a, pairs.quat_a, pairs.pos_b, pairs.quat_b)), ctx.cov_a, ctx.cov_b,
        None if pairs.a_var_scale is None else own_rows(pairs.a_var_scale, keep),
        settings.method == 'tls')
    stamps = np.take(pairs.stamps, keep)
    del pairs
    t_a = query_seconds(stamps, tau, 0.0 if kappa is None else kappa, ctx.reference_ns,
                        ctx.origin_ns)
    since = None if kappa is None else (stamps - np.int64(ctx.reference_ns)).astype(
        float) * 1e-9
    step, half = velocity_step(ctx.trajectory, t_a, ctx.half, settings.max_gap, params, data,
                               since, result.param_cov, ctx.cov_a,
                               _prior_information(ctx, params))
    return _Round(result, report, params, step, tau, kappa, half)


def _prior_information(ctx: _Context, params: Parameters) -> Optional[np.ndarray]:
    """JᵀJ of the prior rows at φ (None without a prior)."""
    if ctx.prior is None:
        return None
    rows = [term(params)[1] for term in ctx.prior.terms(params.spec)]
    J = np.vstack(rows) if rows else np.zeros((0, params.spec.n_params))
    return J.T @ J


def _step_is_linear(rnd: _Round, span_s: float) -> bool:
    d = rnd.step.delta
    shift = abs(d[0]) + (abs(d[1]) * span_s if d.size > 1 else 0.0)
    return shift < LINEAR_STEP_S


def _refine(ctx: _Context, streams_b: list, rnd: _Round) -> _Round:
    """Gauss-Newton rounds on (τ, κ) from ``rnd`` until the step is linear (or τ is lost)."""
    span = 0.5 * float(streams_b[0].stamps[-1] - streams_b[0].stamps[0]) * 1e-9
    kappa = rnd.kappa
    for _ in range(MAX_ROUNDS - 1):
        if rnd.step.cov is None or not rnd.step.determined()[0] or _step_is_linear(rnd, span):
            break
        d = rnd.step.delta
        kappa = None if kappa is None else kappa + float(d[1])
        rnd = _round(ctx, streams_b, rnd.tau + float(d[0]), kappa, rnd.params)
    return rnd


def _candidates(ctx: _Context) -> tuple[list, Optional[SpeedCorrelation]]:
    """
    Return the given τ, then the coarse search's peaks, without near-duplicates.

    And the speeds' correlation they come from (None when the signals give none).
    """
    angular = ctx.settings.model != 'position_only'
    corr = speed_correlation(ctx.stream_a, ctx.streams_b, angular=angular,
                             trajectory_a=ctx.trajectory)
    found = [] if corr is None else [corr.tau(k) for k in corr.peaks()[:MAX_CANDIDATES]]
    out = []
    for tau in [float(ctx.settings.time_offset)] + found:
        if all(abs(tau - t) > SAME_CANDIDATE_S for t in out):
            out.append(tau)
    if ctx.settings.model == 'position_only':
        # the tool origin's speed may miss the marker's lag (a long lever, much rotation):
        # the lags where some point of the tool moves as the marker does, if new
        lever = lever_speed_correlation(ctx.stream_a, ctx.streams_b[0],
                                        trajectory_a=ctx.trajectory)
        for k in [] if lever is None else lever.peaks()[:MAX_CANDIDATES]:
            tau = lever.tau(k)
            if all(abs(tau - t) > NEW_LAG_S for t in out):
                out.append(tau)
    return out, corr


def fit_with_offset_search(stream_a: PoseStream, streams_b: list, settings: Settings,
                           prior: Optional[Prior], noise_from=None
                           ) -> tuple[CalibrationResult, PairingReport]:
    """
    Estimate τ (and κ if asked) jointly with T0 and T1 (the module docstring says how).

    ``noise_from(timing, result)``, if given, returns the settings the rounds on all samples
    use, from the best subsample round's offset and fit (``auto_noise``: the noise estimated
    on all samples paired there at that fit, so that the fit of all samples is made at it
    once).
    """
    ctx = _Context.build(stream_a, streams_b, settings, prior)
    kappa0 = 0.0 if settings.estimate_clock_drift else None
    sub_b = _subsampled(ctx.streams_b, SUBSAMPLE_B)
    # candidates are compared by OLS with few iterations (a wrong one is far off either way),
    # never refused: near the right offset the pairs do not fit the noise yet, and where the
    # data change (a clock step) the candidate that fits a part is the one to find
    trial = replace(ctx, max_rejected_share=1.0, settings=settings.updated(
        method='ols', max_iterations=min(int(settings.max_iterations), TRIAL_ITERATIONS)))
    # one round per candidate, then the best few refined: a wrong lag is far off at once
    firsts = []
    plain = replace(trial, settings=trial.settings.updated(robust=False))
    candidates, corr = _candidates(ctx)
    failures = {}
    for tau in candidates:
        try:  # scored by the median residual: robust without rejecting
            firsts.append(_round(plain, sub_b, tau, kappa0, None))
        except CoregError as e:
            failures[tau] = e
    firsts.sort(key=_Round.score)
    best = None
    for first in firsts[:REFINED_CANDIDATES]:
        try:
            rnd = _refine(trial, sub_b, first)
        except CoregError:
            continue
        if best is None or rnd.score() < best.score():
            best = rnd
    given = float(settings.time_offset)
    if best is None:
        # no candidate fits: the fit at the given offset says why, in its own words
        try:
            result, report = fit_at_offset(stream_a, streams_b, settings, prior, TimeOffset(
                given, message='not estimated: no offset within the overlap gave a fit'))
        except TooFewPairsError as e:
            error = _no_offset_error(e, given, main_peak(corr), failures)
            if corr is None and settings.model == 'full_pose' and np.ptp(
                    ctx.streams_b[0].quat_wxyz, axis=0).max() == 0.0:
                error = error.with_message(
                    f"{error}; device B's orientation never changes: a position-only tracker "
                    f'needs --model position_only')
            raise error from e
        return result, report
    if noise_from is not None:
        settings = noise_from(ctx.timing(best.tau, best.kappa), best.result)
        ctx = replace(ctx, settings=settings, cov_a=settings.cov_a,
                      cov_b=output_covariance(settings.cov_b, SPECS[settings.model]))
    try:
        full = _refine(ctx, ctx.streams_b,
                       _round(ctx, ctx.streams_b, best.tau, best.kappa, best.params))
    except InconsistentDataError as e:
        # refused as a whole: a clock step is a cheap explanation, seen in the blocks' offsets
        blocks = offsets_by_block(ctx.stream_a, ctx.streams_b,
                                  angular=settings.model != 'position_only')
        step = clock_step(blocks, STEP_TOLERANCE_S)
        if step:
            raise InconsistentDataError(f'{step} ({e})') from e
        raise
    ok, why = full.step.determined()
    if not ok:
        peak = main_peak(corr)
        if peak is not None and abs(full.tau - given) > COARSE_EXCLUDES_SIGMAS * peak.sigma_s:
            return _coarse_or_refused(full, ctx, plain, sub_b, firsts, peak, why), full.report
        return fit_at_offset(stream_a, streams_b, settings, prior, TimeOffset(
            given, message=f'not estimated ({why}); kept the given {given:g} s'))
    return _final(full, ctx), full.report


def _no_offset_error(error: CoregError, given: float, peak: Optional[CoarsePeak],
                     failures: dict) -> CoregError:
    """
    Build the error when no lag gave a fit and the given offset pairs too little.

    The coarse peak's own failure (a tool that never moves, say) is the reason when there is
    one; the message says that the stamps do not pair at the given offset and how to give it.
    """
    how = ("give the offset (coreg calibrate --time-offset S, node time_offset: B's clock "
           "minus A's, in s)")
    if peak is None:
        return error.with_message(
            f"{error}; the offset search found no peak in the devices' speeds at any lag where "
            f'they overlap: {how}')
    near = [tau for tau in failures if abs(tau - peak.tau_s) <= SAME_PEAK_WIDTHS * peak.sigma_s]
    if near:
        cause = failures[near[0]]
        return cause.with_message(
            f"{cause} (at the clock offset where the devices' speeds agree best, "
            f'{peak.describe()}; the given offset {given:g} s pairs too few samples); or '
            f'{how}')
    return error.with_message(
        f"{error}; no lag gives a fit where the devices' speeds agree ({peak.describe()}): "
        f'{how}')


def _coarse_or_refused(full: _Round, ctx: _Context, plain: _Context, sub_b: list,
                       firsts: list, peak: CoarsePeak, why: str) -> CalibrationResult:
    """
    Return the fit at the coarse lag with the peak's σ when the lag is clear; else refuse.

    The fine step cannot pin τ (``why``) but the coarse lag excludes the given offset. The
    lag is clear when its trial fit beats every fit at another lag by ``FIT_CLEAR_RATIO``
    (the correlation's runner-up peak is tried when no candidate lies outside the peak).
    """
    width = SAME_PEAK_WIDTHS * peak.sigma_s
    best = min((f for f in firsts if abs(f.tau - full.tau) <= width), key=_Round.score,
               default=None)
    others = [f.score() for f in firsts if abs(f.tau - full.tau) > width]
    if not others and peak.runner_up_tau_s is not None:
        try:
            others.append(_round(plain, sub_b, peak.runner_up_tau_s, full.kappa, None).score())
        except CoregError:
            pass
    clear = best is not None and (not others
                                  or best.score() <= FIT_CLEAR_RATIO * min(others))
    if not clear:
        raise TooFewPairsError(
            f'the clock offset is not determined: the fine step cannot pin it ({why}) and no '
            f"lag gives a clear peak in the devices' speeds ({peak.describe()}; the fits "
            f'there are no better than elsewhere); give the offset (coreg calibrate '
            f"--time-offset S, node time_offset: B's clock minus A's, in s) or record a "
            f'livelier motion')
    message = (f'coarse estimate: the fine step cannot pin it ({why}); σ is the half width '
               f"of the devices' speed correlation peak ({peak.describe()})")
    return _final(full, ctx, sigma_s=peak.sigma_s, message=message)


def _final(rnd: _Round, ctx: _Context, sigma_s: Optional[float] = None,
           message: str = 'estimated jointly with the transforms') -> CalibrationResult:
    """
    Apply the last (linear) step to τ and φ; marginalise φ's covariance over τ.

    With ``sigma_s`` (the coarse estimate), τ stays where it is, with that σ (no drift).
    """
    step, result = rnd.step, rnd.result
    if sigma_s is not None:
        step = replace(step, delta=np.zeros(1), cov=np.array([[sigma_s ** 2]]),
                       dphi=step.dphi[:, :1])
    elif rnd.half != ctx.half:
        message += (f"; A's velocity over ±{rnd.half:.2g} s (its stated noise dominates "
                    f'shorter windows)')
    d = step.delta
    params = rnd.params.stepped(step.dphi @ d)
    cov = step.marginal_cov(result.param_cov)
    t0, t1, joint, determined = result_covariances(params, cov,
                                                   held_basis(result, params.spec))
    T, _ = tangent_map(params)
    cross = T @ (step.dphi @ step.cov)
    kappa = rnd.kappa if rnd.kappa is None or d.size < 2 else rnd.kappa + float(d[1])
    drift_sigma = None if kappa is None or d.size < 2 else float(np.sqrt(step.cov[1, 1])) * 1e6
    timing = TimeOffset(rnd.tau + float(d[0]), step.sigma, True,
                        drift_ppm=None if kappa is None else kappa * 1e6,
                        drift_sigma_ppm=drift_sigma, reference_ns=ctx.reference_ns,
                        message=message, cross_cov=cross, cov=step.cov)
    chi2 = max(0.0, result.chi2 - float(d @ np.linalg.solve(step.cov, d)))
    dof = result.dof - d.size
    p_value = float(chi2_sf(chi2, dof)) if dof > 0 else float('nan')
    return replace(result, base_to_base=t0, tool_to_marker=t1, markers=params.markers.copy(),
                   params=params.phi.copy(), param_cov=cov, cov_joint=joint, chi2=chi2,
                   dof=dof, p_value=p_value, time_offset=timing, cov_determined=determined)


def refit_at(stream_a: PoseStream, streams_b: list, settings: Settings,
             prior: Optional[Prior], result: CalibrationResult
             ) -> tuple[CalibrationResult, PairingReport]:
    """
    Fit again at ``result``'s clock offset from its calibration, e.g. at another noise.

    An estimated offset gets one more round of the search there (its step and φ's covariance
    marginalised over τ, with the new settings' noise); a given one is paired at and fitted
    from ``result``'s φ.
    """
    timing = result.time_offset or TimeOffset(settings.time_offset, message='given')
    spec = SPECS[settings.model]
    start = Parameters(spec, result.params, list(result.charts))
    if timing.estimated:
        ctx = _Context.build(stream_a, streams_b, settings, prior)
        kappa = None if timing.drift_ppm is None else timing.drift_ppm * 1e-6
        rnd = _round(ctx, ctx.streams_b, timing.value_s, kappa, start)
        ok, _ = rnd.step.determined()
        if ok:
            return _final(rnd, ctx), rnd.report
        return replace(rnd.result, time_offset=timing), rnd.report
    pairs, report = pair_for(stream_a, streams_b, settings, timing)
    try:
        fitted = calibrate(pairs, settings, prior, start=start, warm=True)
    except TooFewPairsError as e:
        raise TooFewPairsError(f'{e} ({report.summary()})') from e
    return replace(fitted, time_offset=timing), report
