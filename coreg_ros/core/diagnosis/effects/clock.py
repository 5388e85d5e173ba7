"""The clock effects: B's clock off A's by a constant offset, or drifting from it."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from coreg_ros.core.diagnosis.effects.base import CandidateEffect, ms_text
from coreg_ros.core.diagnosis.record import optional
from coreg_ros.core.diagnosis.terms import DriftShift, OffsetShift, StepShift
import numpy as np


@dataclass(frozen=True, kw_only=True)
class TimeOffsetCandidate(CandidateEffect):
    """
    B's clock off A's by a constant τ (B's clock minus A's, as ``Settings.time_offset``).

    Attributes
    ----------
    tau_s, sigma_s : float
        The offset and its standard uncertainty, s.
    text : str
    coarse_s : float, optional
        The part the coarse search found before pairing, s (included in ``tau_s``).

    """

    name = 'time_offset'
    device = 'B'
    acts_on = 'time'
    term = OffsetShift
    needs_motion = True

    tau_s: float
    sigma_s: float
    text: str
    coarse_s: Optional[float] = optional()

    @classmethod
    def size(cls, reading):
        """Read τ from the fit."""
        tau, s = float(reading.theta(cls.name)[0]), float(reading.sd(cls.name)[0])
        return cls(tau_s=tau, sigma_s=s, text=ms_text(tau, s))

    def shifted(self, shift_s):
        """Add the shift the pairs were made at to τ."""
        tau = self.tau_s + shift_s
        return replace(self, tau_s=tau, text=ms_text(tau, self.sigma_s))


@dataclass(frozen=True, kw_only=True)
class ClockDriftCandidate(CandidateEffect):
    """
    B's clock running fast or slow against A's: an offset that grows linearly in time.

    Attributes
    ----------
    ppm, sigma_ppm : float
        The drift and its standard uncertainty, parts per million.
    offset_at_start_s, sigma_offset_at_start_s : float
        The offset at the first pair and its standard uncertainty, s.
    offset_at_end_s : float
        The offset at the last pair, s.
    text : str

    """

    name = 'clock_drift'
    device = 'B'
    acts_on = 'time'
    term = DriftShift
    needs_motion = True
    simpler = 'time_offset'
    trend_checked = True

    ppm: float
    sigma_ppm: float
    offset_at_start_s: float
    sigma_offset_at_start_s: float
    offset_at_end_s: float
    text: str

    @classmethod
    def size(cls, reading):
        """Read the offset at the start and the drift (θ = (τ0, κ T)) from the fit."""
        theta, sd = reading.theta(cls.name), reading.sd(cls.name)
        duration = reading.model.duration
        kappa, s_k = theta[1] / duration, sd[1] / duration
        return cls(ppm=float(kappa * 1e6), sigma_ppm=float(s_k * 1e6),
                   offset_at_start_s=float(theta[0]), sigma_offset_at_start_s=float(sd[0]),
                   offset_at_end_s=float(theta[0] + theta[1]),
                   text=f'{kappa * 1e6:.1f} ± {s_k * 1e6:.1f} ppm')

    def shifted(self, shift_s):
        """Add the shift the pairs were made at to the offsets (the drift is unchanged)."""
        return replace(self, offset_at_start_s=self.offset_at_start_s + shift_s,
                       offset_at_end_s=self.offset_at_end_s + shift_s)


@dataclass(frozen=True, kw_only=True)
class ClockStepCandidate(CandidateEffect):
    """
    B's clock jumps once: the offset is τ before an instant and τ + Δ after it.

    Attributes
    ----------
    step_s, sigma_s : float
        Δ and its standard uncertainty, s.
    offset_before_s, offset_after_s : float
        The offset before and after the step, s.
    sigma_before_s, sigma_after_s : float
        Their standard uncertainties, s.
    at_s : float
        When: s from the first pair (between the last pair before and the first after).
    text : str

    """

    name = 'clock_step'
    device = 'B'
    changes_at = 'clock_step'
    acts_on = 'time'
    term = StepShift
    needs_motion = True
    simpler = 'time_offset'

    step_s: float
    sigma_s: float
    offset_before_s: float
    offset_after_s: float
    sigma_before_s: float
    sigma_after_s: float
    at_s: float
    text: str

    @classmethod
    def size(cls, reading):
        """Read τ and Δ (and the instant) from the fit."""
        theta, sd = reading.theta(cls.name), reading.sd(cls.name)
        C = reading.cov_of(cls.name)
        after_sd = (float(np.sqrt(max(C[0, 0] + C[1, 1] + 2 * C[0, 1], 0.0)))
                    if C is not None else float('nan'))
        term = next(t for t in reading.model.time if t.name == cls.name)
        return cls._of(float(theta[0]), float(theta[1]), float(sd[1]), float(sd[0]),
                       after_sd, term.at)

    @classmethod
    def _of(cls, before, step, s_step, s_before, s_after, at):
        return cls(step_s=step, sigma_s=s_step, offset_before_s=before,
                   offset_after_s=before + step, sigma_before_s=s_before,
                   sigma_after_s=s_after, at_s=at,
                   text=(f'{ms_text(step, s_step)} at {at:.2f} s (offset '
                         f'{before * 1e3:.2f} ms before, {(before + step) * 1e3:.2f} ms after)'))

    def shifted(self, shift_s):
        """Add the shift the pairs were made at to the offsets (the step is unchanged)."""
        return self._of(self.offset_before_s + shift_s, self.step_s, self.sigma_s,
                        self.sigma_before_s, self.sigma_after_s, self.at_s)
