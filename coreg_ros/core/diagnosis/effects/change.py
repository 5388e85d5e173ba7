"""
Changes that stay: the calibration or B's noise changes at one instant and stays changed.

A bumped base moves T0, a marker that slips on the tool moves T1 (``pose_step``); metal
brought near an EM tracker, or a tracker losing sight of some markers, raises B's noise from
then on (``noise_step``). The instant is located once per recording (``steps``); a change
in B's clock is ``clock.ClockStepCandidate``.
"""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core.diagnosis.effects.base import CandidateEffect
from coreg_ros.core.diagnosis.terms import PoseStep
import numpy as np


def _norm_sd(v: np.ndarray, C) -> tuple:
    """Length of a 3-vector and its standard uncertainty along its direction."""
    size = float(np.linalg.norm(v))
    if C is None or not np.all(np.isfinite(C)):
        return size, float('nan')
    u = v / size if size > 0 else np.array([1.0, 0.0, 0.0])
    return size, float(np.sqrt(max(u @ C @ u, 0.0)))


@dataclass(frozen=True, kw_only=True)
class PoseStepCandidate(CandidateEffect):
    """
    The calibration moves once: T0 (a bumped base) or T1 (a slipped marker) from an instant on.

    Attributes
    ----------
    moved : str
        ``'T0'`` or ``'T1'``: the transform whose step stands out more from its uncertainty.
    t0_mm, sigma_t0_mm : float
        T0's translation step (B's base frame) and its standard uncertainty, mm.
    t0_deg, sigma_t0_deg : float
        T0's rotation step and its standard uncertainty, deg.
    t1_mm, sigma_t1_mm : float
        T1's (the marker's) translation step (A's tool frame) and its uncertainty, mm.
    t1_deg, sigma_t1_deg : float
        T1's rotation step (full pose; 0 otherwise), deg.
    at_s : float
        When: s from the first pair.
    text : str

    """

    name = 'pose_step'
    changes_at = 'pose_step'
    acts_on = 'mean'
    term = PoseStep

    moved: str
    t0_mm: float
    sigma_t0_mm: float
    t0_deg: float
    sigma_t0_deg: float
    t1_mm: float
    sigma_t1_mm: float
    t1_deg: float
    sigma_t1_deg: float
    at_s: float
    text: str

    @classmethod
    def size(cls, reading):
        """Read the step of ψ (T0's then T1's translation and rotation) from the fit."""
        theta = reading.theta(cls.name)
        C = reading.cov_of(cls.name)

        def part(sl, unit):
            sub = None if C is None else C[sl, sl]
            v, s = _norm_sd(theta[sl], sub)
            return v * unit, s * unit

        t0 = part(slice(0, 3), 1e3)
        r0 = part(slice(3, 6), np.degrees(1.0))
        t1 = part(slice(6, 9), 1e3)
        r1 = part(slice(9, 12), np.degrees(1.0)) if len(theta) == 12 and (
            reading.model.data.spec.has_q1) else (0.0, 0.0)

        def z(a):
            return a[0] / a[1] if a[1] and np.isfinite(a[1]) and a[1] > 0 else a[0]

        moved = 'T0' if max(z(t0), z(r0)) >= max(z(t1), z(r1)) else 'T1'
        term = next(t for t in reading.model.mean if t.name == cls.name)
        text = (f'{moved} moved at {term.at:.2f} s: T0 by {t0[0]:.2f} ± {t0[1]:.2f} mm, '
                f'{r0[0]:.3f} ± {r0[1]:.3f} deg; T1 by {t1[0]:.2f} ± {t1[1]:.2f} mm'
                + (f', {r1[0]:.3f} ± {r1[1]:.3f} deg' if reading.model.data.spec.has_q1
                   else ''))
        return cls(moved=moved, t0_mm=t0[0], sigma_t0_mm=t0[1], t0_deg=r0[0],
                   sigma_t0_deg=r0[1], t1_mm=t1[0], sigma_t1_mm=t1[1], t1_deg=r1[0],
                   sigma_t1_deg=r1[1], at_s=float(term.at), text=text)


@dataclass(frozen=True, kw_only=True)
class NoiseStepCandidate(CandidateEffect):
    """
    B's noise changes once: σ × f from an instant on (metal brought near, markers lost).

    Attributes
    ----------
    factor, sigma : float
        f and its standard uncertainty.
    at_s : float
        When: s from the first pair.
    text : str

    """

    name = 'noise_step'
    device = 'B'
    changes_at = 'noise_step'
    kind = 'noise'
    acts_on = 'variance'
    var_params = ('log_f',)

    factor: float
    sigma: float
    at_s: float
    text: str

    @classmethod
    def size(cls, reading):
        """Read f from the fitted log variance factor, the instant from the located one."""
        f, s = reading.noise_factor('log_f')
        found = reading.model.data.cache.get('noise_step')
        at = float(found.at_s) if found is not None else float('nan')
        return cls(factor=f, sigma=s, at_s=at,
                   text=f"B's noise × {f:.3f} ± {s:.3f} from {at:.2f} s on")
