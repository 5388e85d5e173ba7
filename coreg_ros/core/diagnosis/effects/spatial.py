"""The spatial effects of B: its positions scaled per axis, a smooth error field."""

from __future__ import annotations

from dataclasses import dataclass

from coreg_ros.core.diagnosis.effects.base import CandidateEffect
from coreg_ros.core.diagnosis.terms import FieldDistortion, Scale
from coreg_ros.core.rigid import rigid_part
import numpy as np

#: Parametric bootstrap draws of the field for its uncertainty and bias.
FIELD_DRAWS = 40


@dataclass(frozen=True, kw_only=True)
class ScaleCandidate(CandidateEffect):
    """
    B's positions scaled by (1 + s) per axis of B's base frame.

    Attributes
    ----------
    scale, sigma : list of float
        s per axis and its standard uncertainty (fractions).
    text : str

    """

    name = 'scale'
    device = 'B'
    acts_on = 'mean'
    term = Scale
    spatial = True

    scale: list
    sigma: list
    text: str

    @classmethod
    def size(cls, reading):
        """Read s per axis from the fit."""
        theta, sd = reading.theta(cls.name), reading.sd(cls.name)
        return cls(scale=theta.tolist(), sigma=sd.tolist(),
                   text='per axis ' + ', '.join(f'{v * 100:+.3f}' for v in theta)
                        + f' % (± {np.max(sd) * 100:.3f} %)')


@dataclass(frozen=True, kw_only=True)
class FieldDistortionCandidate(CandidateEffect):
    """
    A smooth error field of B, sized by the part a rigid registration cannot absorb.

    Attributes
    ----------
    max_mm, sigma_max_mm : float
        The largest error beyond the field's rigid part over every recorded sample, mm (its
        upward bias taken off), and its standard uncertainty.
    rms_mm : float
        The RMS of that error, mm.
    whole_field_max_mm : float
        The largest error of the whole field, rigid part included, mm.
    text : str

    """

    name = 'field_distortion'
    device = 'B'
    acts_on = 'mean'
    term = FieldDistortion
    spatial = True
    simpler = 'scale'

    max_mm: float
    sigma_max_mm: float
    rms_mm: float
    whole_field_max_mm: float
    text: str

    @classmethod
    def size(cls, reading):
        """Size the fitted field on the samples; its uncertainty and bias from draws."""
        model = reading.model
        term = next(e for e in model.mean if e.name == cls.name)
        theta = reading.theta(cls.name)
        # over every recorded sample of every marker, as the truth is defined (a subsample
        # misses the steep edge of a near-source field); the bootstrap draws use a subsample
        all_pts = model.data.b_points.reshape(-1, 3)
        pts = model.data.b_points
        pts = pts[:: max(1, len(pts) // 2000)].reshape(-1, 3)
        size = _field_size(term, all_pts, theta)
        whole = _field_size(term, all_pts, theta, rigid=False)
        sub = _field_size(term, pts, theta)[0]
        draws = []
        C = reading.cov_of(cls.name)
        if C is not None:
            rng = np.random.default_rng(0)
            try:
                Ls = np.linalg.cholesky(C + 1e-30 * np.eye(len(C)))
                for _ in range(FIELD_DRAWS):
                    draws.append(_field_size(term, pts, theta + Ls @ rng.standard_normal(len(C))))
            except np.linalg.LinAlgError:
                pass
        s = float(np.std([d[0] for d in draws])) if draws else float('nan')
        if draws:
            # the largest value of a noisy field is biased up (its noise adds where the field
            # is largest, and the cubic terms overshoot where samples are few): the bias is
            # read from the draws (parametric bootstrap) and taken off
            bias = float(np.mean([d[0] for d in draws])) - sub
            size = (max(size[0] - max(bias, 0.0), 0.5 * size[0]), size[1])
        return cls(max_mm=size[0], sigma_max_mm=s, rms_mm=size[1], whole_field_max_mm=whole[0],
                   text=f'{size[0]:.2f} ± {s:.2f} mm at most beyond what a rigid registration '
                        f'absorbs (whole field {whole[0]:.2f} mm)')


def _field_size(term: FieldDistortion, pts: np.ndarray, theta: np.ndarray,
                rigid: bool = True) -> tuple:
    """Largest and RMS size (mm) of the field, without its rigid part unless ``rigid``."""
    d = term.field(pts, theta[:term.n_pos])
    if rigid:
        d = d - rigid_part(pts, d)
    norm = np.linalg.norm(d, axis=1) * 1e3
    return float(norm.max()), float(np.sqrt(np.mean(norm ** 2)))
