"""
The cheap causes first: mistakes a check names at once, before any effect is modelled.

A unit error, devices swapped, a stream given the wrong way round, a position-only device read
as a full pose, a device whose stream froze: each makes every pair wrong, and any effect fitted
to that would only describe the mistake with a confident size. These are ``coreg calibrate``'s
own checks (``calibration.verdict``, ``calibration.stream_directions``,
``calibration.observability``), run here on the streams (``stream_cause``) and after the base
fit (``fit_cause``); what they find is the diagnosis' answer (``Cause``), and no effect is
looked for. A recording in which nothing moved is refused as ``calibrate`` refuses it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.calibration.observability import (
    refuse_if_nothing_moved,
    rotation_spread,
    STILL_M,
    STILL_RAD,
)
from coreg_ros.core.calibration.stream_directions import CHECK_BELOW_P, check_directions
from coreg_ros.core.calibration.verdict import swapped_frames, unit_mismatch
from coreg_ros.core.diagnosis.record import Record
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import PoseStream
import numpy as np

#: A device whose samples repeat one pose exactly for this long (s) ...
FROZEN_S = 1.0
#: ... and this many samples, while the other device moves, has stopped tracking.
FROZEN_SAMPLES = 10
#: The direction check (several fits) runs when the base fit's median pair lies this far
#: outside the stated noise (χ²/dof): a stream the wrong way round puts every pair at the
#: scale of the workspace, which no effect of realistic size does.
DIRECTIONS_MEDIAN_CHI2 = 100.0


@dataclass(frozen=True, kw_only=True)
class Cause(Record):
    """
    A cheap cause a check names: the answer of the diagnosis, instead of any effect.

    Attributes
    ----------
    check : str
        ``units``, ``swapped_devices``, ``stream_direction``, ``orientation_missing`` or
        ``frozen_device``.
    text : str
        What is wrong and how to fix it.

    """

    check: str
    text: str


def _orientation_missing(stream_a: PoseStream, stream_b: PoseStream) -> Optional[str]:
    """Name a device whose orientation never changes while the other's turns."""
    spread_a = float(rotation_spread(np.asarray(stream_a.quat_wxyz))[0][0])
    spread_b = float(rotation_spread(np.asarray(stream_b.quat_wxyz))[0][0])
    for still, turning, s_still, s_turn, fix in (
            ('B', 'A', spread_b, spread_a, 'use --model position_only'),
            ('A', 'B', spread_a, spread_b, "device A must report its tool's orientation")):
        if s_still < 0.1 * STILL_RAD and s_turn > STILL_RAD:
            return (f"device {still}'s orientation does not change ({np.degrees(s_still):.3f}° "
                    f"RMS) while device {turning}'s turns {np.degrees(s_turn):.1f}° RMS: "
                    f'{still} reports a position only, read as a full pose; {fix}')
    return None


def _frozen_run(stream: PoseStream) -> Optional[tuple]:
    """Return the longest run of exactly repeated positions: (first, last) sample, or None."""
    p = np.asarray(stream.position)
    same = np.all(p[1:] == p[:-1], axis=1)
    if not same.any():
        return None
    edges = np.diff(np.concatenate([[0], same.astype(int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    k = int(np.argmax(ends - starts))
    return int(starts[k]), int(ends[k])


def _frozen_device(stream_a: PoseStream, stream_b: PoseStream) -> Optional[str]:
    """Name a device that repeats one pose for a while the other moves (it lost tracking)."""
    origin = min(int(stream_a.stamps[0]), int(stream_b.stamps[0]))
    for name, frozen, other in (('B', stream_b, stream_a), ('A', stream_a, stream_b)):
        run = _frozen_run(frozen)
        if run is None or run[1] - run[0] + 1 < FROZEN_SAMPLES:
            continue
        t0, t1 = int(frozen.stamps[run[0]]), int(frozen.stamps[run[1]])
        if (t1 - t0) * 1e-9 < FROZEN_S:
            continue
        inside = (other.stamps >= t0) & (other.stamps <= t1)
        if inside.sum() < 2:
            continue
        p = np.asarray(other.position)[inside]
        moved = float(np.max(np.linalg.norm(p - p[0], axis=1)))
        turned = float(rotation_spread(np.asarray(other.quat_wxyz)[inside])[0][0])
        if moved > STILL_M or turned > STILL_RAD:
            return (f'device {name} repeats one pose exactly from {(t0 - origin) * 1e-9:.1f} s '
                    f'to {(t1 - origin) * 1e-9:.1f} s ({run[1] - run[0] + 1} samples) while '
                    f'the other device moves {moved * 1e3:.0f} mm: {name} stopped tracking; '
                    'leave those samples out')
    return None


def stream_cause(stream_a: PoseStream, streams_b: Sequence[PoseStream], settings: Settings,
                 frames: Optional[Sequence[str]] = None) -> Optional[Cause]:
    """
    Run the checks on the streams: units, swapped devices, a missing orientation, a frozen device.

    Raises
    ------
    UnobservableError
        Device A's tool did not move: nothing can be estimated (``calibrate``'s refusal).

    """
    refuse_if_nothing_moved(np.asarray(stream_a.position), np.asarray(stream_a.quat_wxyz),
                            settings.sigma_a)
    b = streams_b[0]
    # a frozen stream first: its still half shrinks the spread the unit check compares
    checks = (('frozen_device', lambda: _frozen_device(stream_a, b)),
              ('units', lambda: unit_mismatch(stream_a, b)),
              ('swapped_devices', lambda: swapped_frames(stream_a, b, frames)),
              ('orientation_missing', lambda: _orientation_missing(stream_a, b)
               if settings.model == 'full_pose' else None))
    for check, run in checks:
        text = run()
        if text:
            return Cause(check=check, text=text)
    return None


def fit_cause(stream_a: PoseStream, streams_b: Sequence[PoseStream], settings: Settings,
              quad: np.ndarray, m: int, p_value: float) -> Optional[Cause]:
    """
    After the base fit: a stream given the wrong way round (``check_directions``).

    Run only when the fit contradicts the stated noise (p below ``CHECK_BELOW_P``, as
    ``calibrate_streams``) and its median pair lies ``DIRECTIONS_MEDIAN_CHI2`` outside it.

    Parameters
    ----------
    stream_a : PoseStream
        Device A, as the diagnosis was given it.
    streams_b : sequence of PoseStream
        Device B, as given.
    settings : Settings
        As given.
    quad : ndarray, shape (N,)
        The base fit's squared normalised error per pair at the stated noise.
    m : int
        Residuals per pair.
    p_value : float
        The base fit's chi-square p-value.

    """
    if not (p_value < CHECK_BELOW_P) or float(np.median(quad)) / m < DIRECTIONS_MEDIAN_CHI2:
        return None
    check = check_directions(stream_a, list(streams_b), settings)
    return Cause(check='stream_direction', text=check.message) if check.flagged else None
