"""The effects of the link between the devices: a link that flexes, A's backlash."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis.effects.base import CandidateEffect
from coreg_ros.core.diagnosis.record import optional
from coreg_ros.core.diagnosis.terms import Backlash, LinkFlex
import numpy as np


@dataclass(frozen=True, kw_only=True)
class LinkFlexCandidate(CandidateEffect):
    """
    A link that pivots under gravity: the marker sags (and, full pose, tilts).

    Attributes
    ----------
    sag_mm, sigma_mm : float
        The marker's sag when the link is horizontal and its standard uncertainty, mm.
    tilt_deg, sigma_tilt_deg : float, optional
        The largest tilt and its standard uncertainty, deg (full pose).
    gravity_in_a_base : list of float
        Gravity's direction in A's base frame.
    text : str

    """

    name = 'link_flex'
    device = 'link'
    acts_on = 'mean'
    term = LinkFlex

    sag_mm: float
    sigma_mm: float
    tilt_deg: Optional[float] = optional()
    sigma_tilt_deg: Optional[float] = optional()
    gravity_in_a_base: list
    text: str

    @classmethod
    def size(cls, reading):
        """Read the sag (θ[0:3]) and, full pose, the tilt (θ[3:6]) from the fit."""
        theta = reading.theta(cls.name)
        C = reading.cov_of(cls.name)
        if C is None:
            C = np.full((len(theta),) * 2, np.nan)
        u = theta[0:3]
        b = float(np.linalg.norm(u))
        g = u / b if b > 0 else np.array([0.0, 0.0, -1.0])
        s = float(np.sqrt(max(g @ C[0:3, 0:3] @ g, 0.0)))
        # the length of a noisy vector is biased up: E|û|² = |u|² + tr C. Taken off (the
        # across-gravity variance), small sags are not overstated
        tr = float(np.trace(C[0:3, 0:3])) if np.all(np.isfinite(C[0:3, 0:3])) else 0.0
        b = float(np.sqrt(max(b * b - max(tr - s * s, 0.0), 0.25 * b * b)))
        tilt = st = None
        if len(theta) == 6:
            w = theta[3:6]
            tilt = float(np.linalg.norm(w))
            gw = w / tilt if tilt > 0 else g
            st = float(np.sqrt(max(gw @ C[3:6, 3:6] @ gw, 0.0)))
            # gravity's direction from the better determined of the two vectors
            if tilt / max(st, 1e-30) > b / max(s, 1e-30):
                g = gw * np.sign(float(gw @ u)) if b > 0 else gw
                b, s = _sag_along(g, u, C[0:3, 0:3])
        text = f'{b * 1e3:.2f} ± {s * 1e3:.2f} mm sag'
        if tilt is not None:
            text += f', {np.degrees(tilt):.3f} ± {np.degrees(st):.3f} deg tilt'
        return cls(sag_mm=b * 1e3, sigma_mm=s * 1e3,
                   tilt_deg=None if tilt is None else float(np.degrees(tilt)),
                   sigma_tilt_deg=None if tilt is None else float(np.degrees(st)),
                   gravity_in_a_base=g.tolist(),
                   text=text + ' (gravity in A base ' + ', '.join(f'{v:+.2f}' for v in g) + ')')


def _sag_along(g: np.ndarray, u: np.ndarray, Cu: np.ndarray) -> tuple:
    """
    Sag (m) along gravity's direction g and its standard uncertainty, from u (3,), Cu (3, 3).

    Sag and tilt are one pivot's turn under one gravity (u = lever · w): with the direction
    fixed by the tilt, the sag is u's component along it (one noisy component instead of a
    vector length, which the two across-gravity components inflate). Best linear unbiased:
    u = b ĝ + noise (covariance Cu), so b is read with all three components weighted, not
    along ĝ alone (the motion may fix another direction far better than ĝ's).
    """
    try:
        Wg = np.linalg.solve(Cu, g)
        info = float(g @ Wg)
        b = abs(float(Wg @ u) / info)
        s = float(np.sqrt(1.0 / info))
    except (np.linalg.LinAlgError, ZeroDivisionError, FloatingPointError):
        b = abs(float(g @ u))
        s = float(np.sqrt(max(g @ Cu @ g, 0.0)))
    if not (np.isfinite(b) and np.isfinite(s)):
        b = abs(float(g @ u))
        s = float(np.sqrt(max(g @ Cu @ g, 0.0))) if np.all(np.isfinite(Cu)) else s
    return b, s


@dataclass(frozen=True, kw_only=True)
class BacklashCandidate(CandidateEffect):
    """
    Play in A's position along each axis of A's base frame, flipping with the motion.

    Attributes
    ----------
    width_mm, sigma_mm : float
        The play's width averaged over the axes and its standard uncertainty, mm.
    width_per_axis_mm, sigma_per_axis_mm : list of float
        The same per axis, mm.
    text : str

    """

    name = 'backlash'
    device = 'A'
    acts_on = 'mean'
    term = Backlash
    needs_motion = True

    width_mm: float
    sigma_mm: float
    width_per_axis_mm: list
    sigma_per_axis_mm: list
    text: str

    @classmethod
    def size(cls, reading):
        """Read the play's half-widths θ from the fit: the width is twice them."""
        w = 2.0 * reading.theta(cls.name) * 1e3
        ws = 2.0 * reading.sd(cls.name) * 1e3
        mean = float(np.mean(w))
        mean_sd = float(np.sqrt(np.sum(ws ** 2)) / 3.0)
        return cls(width_mm=mean, sigma_mm=mean_sd, width_per_axis_mm=w.tolist(),
                   sigma_per_axis_mm=ws.tolist(), text=f'{mean:.3f} ± {mean_sd:.3f} mm play')
