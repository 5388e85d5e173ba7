"""
Streams in, calibration out: pairing by timestamp, the clock offset, the estimator, the verdict.

The live node, the offline ``coreg calibrate`` and ``coreg_ros.calibrate`` all call
``calibrate_streams`` on the raw samples they hold, so they pair and estimate identically: at
the given clock offset, or with the offset estimated jointly (``offset_search``), then judged
against the stated noise (``verdict``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Optional, Union

from coreg_ros.core.calibration.auto_noise import calibrate_with_noise
from coreg_ros.core.calibration.clock_check import clock_problem
from coreg_ros.core.calibration.offset_search import fit_at_offset, fit_with_offset_search
from coreg_ros.core.calibration.pairing import stream_list, validated_streams
from coreg_ros.core.calibration.stream_directions import (
    CHECK_BELOW_P,
    check_directions,
    DirectionReport,
)
from coreg_ros.core.calibration.verdict import (
    cheap_causes,
    CONSISTENT_P,
    judge,
    orientation_missing,
    unit_mismatch,
)
from coreg_ros.core.errors import (
    ConvergenceError,
    InconsistentDataError,
    InputError,
    UnobservableError,
)
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.provenance import shared_samples
from coreg_ros.core.settings import check_settings, Settings
from coreg_ros.core.types import CalibrationResult, PairingReport, PoseStream, TimeOffset


def calibrate_streams(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                      settings: Settings, prior: Optional[Prior] = None,
                      frames: Optional[tuple] = None, direction_check: bool = True,
                      roles_confirmed: bool = False
                      ) -> tuple[CalibrationResult, PairingReport]:
    """
    Pair device A and device B samples, estimate the clock offset (if asked), calibrate, judge.

    After a fit the data contradict (p below ``stream_directions.CHECK_BELOW_P``), and when the
    data are refused as a whole, the stream directions are checked (``check_directions``): a
    stream given the wrong way round (``T_tool_base`` for ``T_base_tool``) makes every fit bad,
    and is named instead of the symptom. A bad fit that neither this nor the streams' cheap
    causes explain (``verdict.cheap_causes``) is checked for a clock problem
    (``clock_check.clock_problem``: a wrong fixed offset, a drift, a step), named with the
    option that models it.

    Parameters
    ----------
    stream_a : PoseStream
        Device A: tool pose in A's base frame.
    streams_b : PoseStream or sequence of PoseStream
        Device B: marker pose(s) in B's base frame (three streams for ``three_marker``).
    settings : Settings
        The configuration (model, method, noise, pairing, robust fit). With ``noise ==
        'auto'`` each device's noise is estimated with the calibration (``auto_noise``): the
        result then carries it (``noise``), is fitted and judged with it, and its verdict
        names the noise that was misstated.
    prior : Prior, optional
        Prior knowledge of the parameters, added to the fit.
    frames : (str, str), optional
        The configured base frames of A and B, to recognise swapped devices from the
        messages' frame ids: a swap is named as the cause of a bad fit, and refuses a good
        one (``verdict.judge``).
    direction_check : bool
        Check the stream directions after a bad fit (False fits the data as given).
    roles_confirmed : bool
        The user confirms that the topics are A and B as configured: frame ids that say
        otherwise refuse nothing.

    Returns
    -------
    result : CalibrationResult
        With ``time_offset``, ``rejected_stamps``, ``fit_consistent``, ``verdict``,
        ``refusals`` and ``direction_check`` (the check's report when it ran); ``success``
        only if the estimator converged, the fit matches the stated noise, no stream fits far
        better inverted and the devices are not swapped.
    report : PairingReport

    Raises
    ------
    TooFewPairsError
        With the pairing counts, so the user sees why samples were not paired.
    InconsistentDataError
        Data refused as a whole, naming a stream given the wrong way round when that explains
        it.
    UnobservableError
        With its ``directions``, whatever this layer adds to its message.

    """
    check_settings(settings)
    if prior is not None and not isinstance(prior, Prior):
        raise InputError(f'prior must be a coreg_ros.Prior, got {type(prior).__name__}; read a '
                         f'file or a dict with coreg_ros.load_prior or prior_from_dict '
                         f'(coreg_ros.calibrate loads them itself)')
    streams_b = stream_list(streams_b)
    same_data_prior(prior, streams_b)
    if len(streams_b) in (1, 3):  # (any other count is refused below, in the pairing's words)
        # checked and normalised once: every step below (the offset search, the noise
        # estimate's rounds, the verdict's checks) takes these as they are
        stream_a, streams_b = validated_streams(stream_a, streams_b,
                                                settings.model == 'full_pose')
    try:
        if settings.noise == 'auto':  # the noise estimated with the fit, and the fit at it
            result, report, settings = calibrate_with_noise(stream_a, streams_b, settings,
                                                            prior)
        elif settings.estimate_time_offset:
            result, report = fit_with_offset_search(stream_a, streams_b, settings, prior)
        else:
            result, report = fit_at_offset(stream_a, streams_b, settings, prior,
                                           TimeOffset(settings.time_offset, message='given'))
    except (UnobservableError, InconsistentDataError, ConvergenceError) as e:
        # positions in other units, or a position-only B taken for a full pose, make every
        # fit fail somehow: name the cause, not the symptom
        first = '; '.join(c for c in (
            unit_mismatch(stream_a, streams_b[0]) if 'likely in' not in str(e) else None,
            orientation_missing(stream_a, streams_b[0], settings.model)) if c)
        error = e.with_message(f'{e}; but first: {first}') if first else e
        if isinstance(e, InconsistentDataError) and direction_check:
            # refused as a whole: a stream given the wrong way round is a cheap explanation
            check = check_directions(stream_a, streams_b, settings)
            if check.flagged:
                error = error.with_message(f'{check.message} ({error})')
        if error is e:
            raise
        raise error from e
    fitted = result
    result = with_noise_verdict(judge(fitted, stream_a, streams_b, settings, prior,
                                      frames, roles_confirmed))
    check = None
    if direction_check and not float(result.p_value) >= CHECK_BELOW_P:  # NaN checks too
        check = check_directions(stream_a, streams_b, settings)
        result = with_direction_check(result, check)
    if (float(result.p_value) < CONSISTENT_P and not (check is not None and check.flagged)
            and not cheap_causes(stream_a, streams_b, settings, frames, roles_confirmed)):
        # a bad fit nothing cheaper explains: is it the clock? (a few block fits)
        clock = clock_problem(stream_a, streams_b, settings)
        if clock:
            result = with_noise_verdict(judge(fitted, stream_a, streams_b, settings, prior,
                                              frames, roles_confirmed, clock))
            if check is not None:
                result = with_direction_check(result, check)
    return result, report


def with_noise_verdict(result: CalibrationResult) -> CalibrationResult:
    """Return the result with the noise estimate's verdict (noise: auto) added to its own."""
    if result.noise is None:
        return result
    said = result.noise.verdict()  # which device's noise was misstated, and how
    return replace(result, verdict='; '.join(v for v in (result.verdict, said) if v))


def same_data_prior(prior: Optional[Prior], streams_b: Sequence[PoseStream]) -> None:
    """
    Refuse a prior calibrated on these same samples: it would count them twice.

    Raises
    ------
    InputError
        Naming the shares of the samples in common and the fix.

    """
    shared = shared_samples(prior.data_sketch, streams_b) if (
        prior is not None and prior.data_sketch) else None
    if shared is None:
        return
    of_prior, of_this = shared
    raise InputError(
        f'the prior was calibrated on these same samples (about {of_this:.0%} of this '
        f"recording's B samples are among its, {of_prior:.0%} of its here): it would count "
        f'them twice (σ too small by up to √2, the prior agreeing by construction); '
        f'calibrate without the prior (`prior`), or take one from another recording')


def with_direction_check(result: CalibrationResult, check: DirectionReport
                         ) -> CalibrationResult:
    """
    Return the result with the direction check's report; refused when a stream is inverted.

    A stream that fits ``check.threshold`` times better inverted is the wrong way round: the
    transforms fitted as given are meaningless, so the result is not a success (whatever its
    chi-square) and its verdict says which stream to invert and how.
    """
    if not check.flagged:
        return replace(result, direction_check=check)
    verdict = '; '.join(v for v in (f'a stream is the wrong way round: {check.message}',
                                    result.verdict) if v)
    return replace(result, direction_check=check, success=False, verdict=verdict)
