"""
The coarse clock offset on its own: the main peak of the speeds' correlation and its width.

The fine step (``timing.offset_step``) pins τ where the motion's velocity determines it. Where
it cannot (nearly constant velocity, or a motion at the level of the stated noise), the coarse
search still says which lag the devices' speeds agree at; that lag is used when its peak is
clear (``offset_search``: its fit beats the fits at every other lag), with a σ that covers
the peak's half width: the peak cannot say more than where it is and how broad it is. Two
devices whose stamps never overlap cannot be paired at all without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.clock.timing import speed_correlation, SpeedCorrelation
from coreg_ros.core.clock.trajectory import Trajectory
from coreg_ros.core.types import PoseStream
import numpy as np

#: Other peaks closer than this many half widths to the main one are part of it.
SAME_PEAK_WIDTHS = 2.0


@dataclass(frozen=True)
class CoarsePeak:
    """
    The main peak of the speeds' correlation.

    Attributes
    ----------
    tau_s : float
        τ (s, B's clock minus A's) at the peak, refined by a parabola through it.
    r : float
        Correlation at the peak.
    sigma_s : float
        Half width of the peak at half its height (at least one grid step), s: a σ that
        covers where the peak could lie.
    runner_up_r : float
        Correlation of the strongest other peak (-inf when there is none).
    runner_up_tau_s : float or None
        τ of that peak, s.

    """

    tau_s: float
    r: float
    sigma_s: float
    runner_up_r: float = -np.inf
    runner_up_tau_s: Optional[float] = None

    def describe(self) -> str:
        """One phrase: the peak, and the runner-up it is compared with."""
        text = f'r = {self.r:.3f} at {self.tau_s:.3f} s'
        if self.runner_up_tau_s is not None:
            text += f', next r = {self.runner_up_r:.3f} at {self.runner_up_tau_s:.3f} s'
        return text


def _half_width(corr: SpeedCorrelation, k: int) -> float:
    """Half width (s) of the peak at index ``k`` at half its height (at least one step)."""
    r = corr.r
    half = 0.5 * r[k]
    lo = k
    while lo > 0 and np.isfinite(r[lo - 1]) and r[lo - 1] > half:
        lo -= 1
    hi = k
    while hi < len(r) - 1 and np.isfinite(r[hi + 1]) and r[hi + 1] > half:
        hi += 1
    return max(1.0, 0.5 * (hi - lo)) * corr.step_s


def main_peak(corr: Optional[SpeedCorrelation]) -> Optional[CoarsePeak]:
    """Return the strongest peak of ``corr`` with its width and runner-up (None: no peak)."""
    if corr is None:
        return None
    peaks = corr.peaks()
    if peaks.size == 0:
        return None
    k = int(peaks[0])
    tau = corr.tau(k)
    width = _half_width(corr, k)
    others = [int(j) for j in peaks[1:]
              if abs(corr.tau(int(j)) - tau) > SAME_PEAK_WIDTHS * width]
    if not others:
        return CoarsePeak(tau, float(corr.r[k]), width)
    j = max(others, key=lambda i: corr.r[i])
    return CoarsePeak(tau, float(corr.r[k]), width, float(corr.r[j]), corr.tau(j))


def coarse_peak(stream_a: PoseStream, streams_b: Sequence[PoseStream], *, angular: bool,
                trajectory_a: Optional[Trajectory] = None) -> Optional[CoarsePeak]:
    """
    Find the main peak of the devices' speeds cross-correlated over every overlapping lag.

    Arguments as ``timing.coarse_offsets``; None when the signals give no peak (too short,
    constant).
    """
    return main_peak(speed_correlation(stream_a, streams_b, angular=angular,
                                       trajectory_a=trajectory_a))
