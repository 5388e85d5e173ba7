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
from coreg_ros.core.calibration.offset_search import fit_at_offset, fit_with_offset_search
from coreg_ros.core.calibration.pairing import stream_list
from coreg_ros.core.calibration.stream_directions import (
    CHECK_BELOW_P,
    check_directions,
    DirectionReport,
)
from coreg_ros.core.calibration.verdict import judge, unit_mismatch
from coreg_ros.core.errors import ConvergenceError, InconsistentDataError, UnobservableError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, PairingReport, PoseStream, TimeOffset


def calibrate_streams(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                      settings: Settings, prior: Optional[Prior] = None,
                      frames: Optional[tuple] = None, direction_check: bool = True
                      ) -> tuple[CalibrationResult, PairingReport]:
    """
    Pair device A and device B samples, estimate the clock offset (if asked), calibrate, judge.

    After a fit the data contradict (p below ``stream_directions.CHECK_BELOW_P``), and when the
    data are refused as a whole, the stream directions are checked (``check_directions``): a
    stream given the wrong way round (``T_tool_base`` for ``T_base_tool``) makes every fit bad,
    and is named instead of the symptom.

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
        messages' frame ids when the fit is bad.
    direction_check : bool
        Check the stream directions after a bad fit (False fits the data as given).

    Returns
    -------
    result : CalibrationResult
        With ``time_offset``, ``rejected_stamps``, ``fit_consistent``, ``verdict`` and
        ``direction_check`` (the check's report when it ran); ``success`` only if the
        estimator converged, the fit matches the stated noise and no stream fits far better
        inverted.
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
    streams_b = stream_list(streams_b)
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
        # positions in other units make every fit fail somehow: name the cause, not the symptom
        units = unit_mismatch(stream_a, streams_b[0])
        error = e.with_message(f'{e}; but first: {units}') if (
            units and 'likely in' not in str(e)) else e
        if isinstance(e, InconsistentDataError) and direction_check:
            # refused as a whole: a stream given the wrong way round is a cheap explanation
            check = check_directions(stream_a, streams_b, settings)
            if check.flagged:
                error = error.with_message(f'{check.message} ({error})')
        if error is e:
            raise
        raise error from e
    result = judge(result, stream_a, streams_b, settings, prior, frames)
    if result.noise is not None:  # which device's noise was misstated, and how
        said = result.noise.verdict()
        result = replace(result, verdict='; '.join(v for v in (result.verdict, said) if v))
    if direction_check and not float(result.p_value) >= CHECK_BELOW_P:  # NaN checks too
        result = with_direction_check(result, check_directions(stream_a, streams_b, settings))
    return result, report


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
