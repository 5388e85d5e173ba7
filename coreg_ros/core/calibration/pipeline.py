"""
Streams in, calibration out: pairing by timestamp, the clock offset, the estimator, the verdict.

The live node, the offline ``coreg calibrate`` and ``coreg_ros.calibrate`` all call
``calibrate_streams`` on the raw samples they hold, so they pair and estimate identically: at
the given clock offset, or with the offset estimated jointly (``offset_search``), then judged
against the stated noise (``verdict``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Optional, Union

from coreg_ros.core.calibration.offset_search import fit_at_offset, fit_with_offset_search
from coreg_ros.core.calibration.pairing import stream_list
from coreg_ros.core.calibration.verdict import judge, unit_mismatch
from coreg_ros.core.errors import ConvergenceError, InconsistentDataError, UnobservableError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, PairingReport, PoseStream, TimeOffset


def calibrate_streams(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                      settings: Settings, prior: Optional[Prior] = None,
                      frames: Optional[tuple] = None
                      ) -> tuple[CalibrationResult, PairingReport]:
    """
    Pair device A and device B samples, estimate the clock offset (if asked), calibrate, judge.

    Parameters
    ----------
    stream_a : PoseStream
        Device A: tool pose in A's base frame.
    streams_b : PoseStream or sequence of PoseStream
        Device B: marker pose(s) in B's base frame (three streams for ``three_marker``).
    settings : Settings
        The configuration (model, method, noise, pairing, robust fit).
    prior : Prior, optional
        Prior knowledge of the parameters, added to the fit.
    frames : (str, str), optional
        The configured base frames of A and B, to recognise swapped devices from the
        messages' frame ids when the fit is bad.

    Returns
    -------
    result : CalibrationResult
        With ``time_offset``, ``rejected_stamps``, ``fit_consistent`` and ``verdict``;
        ``success`` only if the estimator converged and the fit matches the stated noise.
    report : PairingReport

    Raises
    ------
    TooFewPairsError
        With the pairing counts, so the user sees why samples were not paired.

    """
    streams_b = stream_list(streams_b)
    try:
        if settings.estimate_time_offset:
            result, report = fit_with_offset_search(stream_a, streams_b, settings, prior)
        else:
            result, report = fit_at_offset(stream_a, streams_b, settings, prior,
                                           TimeOffset(settings.time_offset, message='given'))
    except (UnobservableError, InconsistentDataError, ConvergenceError) as e:
        # positions in other units make every fit fail somehow: name the cause, not the symptom
        units = unit_mismatch(stream_a, streams_b[0])
        if units and 'likely in' not in str(e):
            raise type(e)(f'{e}; but first: {units}') from e
        raise
    return judge(result, stream_a, streams_b, settings, prior, frames), report


