"""
Streams in, calibration out: pairing by timestamp followed by the estimator.

The live node and the offline ``coreg calibrate`` both call ``calibrate_streams`` on the raw
samples they hold, so they pair and estimate identically.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Optional, Union

from coreg_ros.core.calibrate import calibrate
from coreg_ros.core.covariance import Prior
from coreg_ros.core.errors import TooFewPairsError
from coreg_ros.core.pairing import pair_streams
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, PairingReport, PoseStream


def pair_for(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
             settings: Settings):
    """Pair the streams with the settings' gap, offset and model; returns (Pairs, report)."""
    return pair_streams(stream_a, streams_b, max_gap_ns=settings.max_gap_ns,
                        offset_ns=settings.time_offset_ns,
                        with_orientation_b=settings.model == 'full_pose')


def calibrate_streams(stream_a: PoseStream, streams_b: Union[PoseStream, Sequence[PoseStream]],
                      settings: Settings, prior: Optional[Prior] = None
                      ) -> tuple[CalibrationResult, PairingReport]:
    """
    Pair device A and device B samples and calibrate.

    Parameters
    ----------
    stream_a : PoseStream
        Device A: tool pose in A's base frame.
    streams_b : PoseStream or sequence of PoseStream
        Device B: marker pose(s) in B's base frame (three streams for ``three_marker``).
    settings : Settings
    prior : Prior, optional

    Returns
    -------
    result : CalibrationResult
    report : PairingReport

    Raises
    ------
    TooFewPairsError
        With the pairing counts, so the user sees why samples were not paired.

    """
    pairs, report = pair_for(stream_a, streams_b, settings)
    try:
        return calibrate(pairs, settings, prior), report
    except TooFewPairsError as e:
        raise TooFewPairsError(f'{e} ({report.summary()})') from e
