"""
Both devices' noise from one recording: still segments found (or a window given), measured.

``measure_recording`` is what ``coreg noise`` runs: for device A and device B (each marker of
a three-marker tracker, pooled) it finds the still segments (``still``) or takes the window
``[t0, t1]`` (seconds from the recording's first stamp), and measures each device there
(``measure``). The orientation of B is measured only for the full-pose model (a position-only
or three-marker tracker's orientation means nothing).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Optional

from coreg_ros.core.errors import InputError
from coreg_ros.core.noise.measure import (
    channel_noise,
    DEFAULT_PRECISION,
    DeviceMeasurement,
    measure_device,
)
from coreg_ros.core.noise.still import (
    longest_still,
    segments_of,
    still_mask,
    window_segment,
)
from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.core.types import PoseStream
import numpy as np


@dataclass(frozen=True)
class NoiseReport:
    """
    Both devices' measured noise.

    Attributes
    ----------
    device_a, device_b : DeviceMeasurement
    model : str
    origin_ns : int
        The recording's first stamp: segment times are seconds from it.
    window : tuple of float or None
        The window given (s from ``origin_ns``), None when the segments were found.

    """

    device_a: DeviceMeasurement
    device_b: DeviceMeasurement
    model: str
    origin_ns: int
    window: Optional[tuple] = None

    def devices(self) -> list:
        """Return ``[device_a, device_b]``."""
        return [self.device_a, self.device_b]

    def noise(self, stated_a: DeviceNoise, stated_b: DeviceNoise) -> tuple:
        """Return the measured DeviceNoise of A and B (a channel not measured: the stated one)."""
        return self.device_a.device_noise(stated_a), self.device_b.device_noise(stated_b)


def _segments(stream: PoseStream, rotation: bool, window, origin_ns: int):
    """Return the still segments of one stream (or the window), and its longest still stretch."""
    if window is not None:
        t0, t1 = (origin_ns + int(round(v * 1e9)) for v in window)
        return window_segment(stream.stamps, t0, t1), float(window[1] - window[0])
    mask = still_mask(stream.stamps, stream.position, stream.quat_wxyz if rotation else None)
    return segments_of(stream.stamps, mask), longest_still(stream.stamps, mask)


def _pooled_markers(measured: list, streams: list) -> DeviceMeasurement:
    """One B of three markers: position noise pooled over the markers (one tracker's)."""
    first = measured[0]
    if len(measured) == 1:
        return first
    parts = [np.asarray(st.position[s.start:s.stop], dtype=float)
             for m, st in zip(measured, streams, strict=True) for s in m.segments]
    pooled = channel_noise('position', parts, 1.0 / first.sampling.nominal_hz)
    return replace(first, channels={'position': pooled},
                   warnings=[w for m in measured for w in m.warnings])


def measure_recording(stream_a: PoseStream, streams_b: Sequence[PoseStream], model: str,
                      topics: Sequence[str] = ('', ''), window: Optional[tuple] = None,
                      precision: float = DEFAULT_PRECISION) -> NoiseReport:
    """
    Measure the noise of devices A and B where each stands still.

    Parameters
    ----------
    stream_a : PoseStream
        Device A (tool pose in A's base frame).
    streams_b : sequence of PoseStream
        Device B (three streams for ``three_marker``, pooled).
    model : str
        The measurement model (B's orientation is measured for ``full_pose`` only).
    topics : sequence of str
        Topic of A, then of B, for the messages.
    window : (float, float), optional
        Measure in ``[t0, t1]`` s from the recording's first stamp instead of the still
        segments found.
    precision : float
        Relative precision of σ that a refusal asks to record for.

    Raises
    ------
    InputError
        A device without a still segment (or only frozen ones), or a window without samples.

    """
    streams_b = list(streams_b)
    origin = int(min(int(stream_a.stamps[0]), *(int(s.stamps[0]) for s in streams_b)))
    if window is not None and not window[1] > window[0]:
        raise InputError(f'--window {window[0]:g} {window[1]:g}: the end must come after the '
                         "start (seconds from the recording's first stamp)")
    out = []
    for device, streams, rotation, topic in (('a', [stream_a], True, topics[0]),
                                             ('b', streams_b, model == 'full_pose',
                                              topics[-1])):
        measured = []
        for stream in streams:
            if len(stream) < 2:
                raise InputError(f'device {device.upper()} ({topic}) has {len(stream)} '
                                 f'sample(s); a still recording needs many')
            segments, longest = _segments(stream, rotation, window, origin)
            measured.append(measure_device(stream, segments, device, topic, rotation, origin,
                                           precision, longest))
        out.append(_pooled_markers(measured, streams))
    return NoiseReport(out[0], out[1], model, origin, window)
