"""
The noise effects: a wrong noise level, noise growing with distance, stamp jitter, outliers.

They change the noise model only (``variance.py``): the first three describe the noise and
never close the gap (kind ``'noise'``); outliers set pairs aside, which count as unexplained.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from coreg_ros.core.diagnosis import noise_shape as ns
from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.effects.base import CandidateEffect, ms_text
from coreg_ros.core.diagnosis.record import optional
import numpy as np


@dataclass(frozen=True, kw_only=True)
class NoiseScaleCandidate(CandidateEffect):
    """
    The noise of both devices a factor off the stated (variance × s²).

    Attributes
    ----------
    factor, sigma : float
        The factor s and its standard uncertainty.
    text : str

    """

    name = 'noise_scale'
    device = 'A and B'
    kind = 'noise'
    acts_on = 'variance'
    var_params = ('log_s2',)
    sets_noise_level = True

    factor: float
    sigma: float
    text: str

    @classmethod
    def size(cls, reading):
        """Read the factor from the fitted log variance factor."""
        f, s = reading.noise_factor('log_s2')
        return cls(factor=f, sigma=s, text=f'× {f:.3f} ± {s:.3f}')


@dataclass(frozen=True, kw_only=True)
class DistanceNoiseCandidate(CandidateEffect):
    """
    B's noise growing with the distance from its source: variance × c (r / r0)^(2k).

    Attributes
    ----------
    exponent, sigma : float
        k and its standard uncertainty.
    edge_to_centre : float
        B's noise σ at the farthest pair over that at the median distance.
    level : float
        √c: B's noise σ at the median distance over the stated.
    source_m : list of float
        Where the noise grows from, B's base frame, m.
    text : str

    """

    name = 'distance_noise'
    device = 'B'
    kind = 'noise'
    acts_on = 'variance'
    var_params = ('log_c', 'k')
    spatial = True
    simpler = 'noise_scale'
    sets_noise_level = True

    exponent: float
    sigma: float
    edge_to_centre: float
    level: float
    source_m: list
    text: str

    @classmethod
    def size(cls, reading):
        """Read the exponent and the level from the fit, the source from the model."""
        model, var = reading.model, reading.var
        edge = float((np.exp(model.log_g).max()) ** var.k)
        sigma = reading.var_sd('k')
        return cls(exponent=float(var.k), sigma=sigma, edge_to_centre=edge,
                   level=float(np.exp(0.5 * var.log_c)),
                   source_m=[float(v) for v in model.source],
                   text=f'exponent {var.k:.2f} ± {sigma:.2f} (edge/centre σ × {edge:.2f})')


@dataclass(frozen=True, kw_only=True)
class TimestampJitterCandidate(CandidateEffect):
    """
    Random errors of the stamps: the output moves along its rate, variance + σ_t² ḟ ḟᵀ.

    Attributes
    ----------
    sigma_s, sigma_sigma_s : float
        σ_t and its standard uncertainty, s.
    text : str
    sigma_s_from_stamps : float, optional
        σ_t read from the stamps themselves, s (``stamps.StampJitter``).
    dropped : int, optional
        Samples the stamps show dropped.
    gaps : list of [float, float], optional
        Gaps in the stamps: start and length, s.

    """

    name = 'timestamp_jitter'
    kind = 'noise'
    acts_on = 'variance'
    var_params = ('log_beta',)
    needs_motion = True

    sigma_s: float
    sigma_sigma_s: float
    text: str
    sigma_s_from_stamps: Optional[float] = optional()
    dropped: Optional[int] = optional()
    gaps: Optional[list] = optional()

    @classmethod
    def size(cls, reading):
        """Read σ_t from the fitted log variance."""
        sig = float(np.sqrt(reading.var.beta))
        s = 0.5 * sig * reading.var_sd('log_beta')
        return cls(sigma_s=sig, sigma_sigma_s=s, text=ms_text(sig, s))

    def with_stamps(self, stamps) -> TimestampJitterCandidate:
        """Add what the stamps say (``stamps.StampJitter``) to the jitter the residuals show."""
        return replace(self, sigma_s_from_stamps=stamps.sigma_s, dropped=stamps.dropped,
                       gaps=stamps.gaps, text=f'{self.text} (stamps: {stamps.text})')


@dataclass(frozen=True, kw_only=True)
class OutliersCandidate(CandidateEffect):
    """
    A share of the pairs far outside the stated noise (a mixture: covariance × λ²).

    Attributes
    ----------
    fraction, sigma : float
        The share ε and its standard uncertainty.
    count : int
        Pairs more likely outliers than not.
    scale : float
        λ: the outliers' standard deviation over the inliers'.
    text : str
    at_cap : bool, optional
        The share is at the model's cap (``variance.MAX_OUTLIER_SHARE``): a wrong noise
        model, not glitches.
    run_median, run_max : int, optional
        Outliers in a row (median, largest), when they come in bursts
        (``timeline.FlaggedRuns``).

    """

    name = 'outliers'
    acts_on = 'variance'
    var_params = ('logit_eps', 'log_lam')

    fraction: float
    sigma: float
    count: int
    scale: float
    text: str
    at_cap: Optional[bool] = optional()
    run_median: Optional[int] = optional()
    run_max: Optional[int] = optional()

    @classmethod
    def size(cls, reading):
        """Read the share from the fit; its uncertainty is binomial over the pairs."""
        var, stats = reading.var, reading.fit.stats
        eps = var.eps
        _, p_in, _ = vm.loglik(var, stats, with_parts=True)
        s = float(np.sqrt(max(eps * (1 - eps), 1e-12) / len(stats.z)))
        return cls(fraction=eps, sigma=s, count=int(np.sum(p_in < 0.5)),
                   scale=float(np.exp(var.log_lam)),
                   text=f'{eps * 100:.2f} ± {s * 100:.2f} % of the pairs')

    def capped(self, at_cap: bool) -> OutliersCandidate:
        """Say whether the share is at the model's cap (and, if so, what that means)."""
        text = self.text
        if at_cap:
            text += (f' (at the cap of {vm.MAX_OUTLIER_SHARE * 100:.0f} %: more pairs lie '
                     'outside the stated noise; these are not glitches)')
        return replace(self, at_cap=bool(at_cap), text=text)

    def in_runs(self, runs) -> OutliersCandidate:
        """Say that the outliers come in bursts (``timeline.FlaggedRuns``), when they do."""
        if not runs.bursts:
            return self
        return replace(self, run_median=runs.median_length, run_max=runs.max_length,
                       text=f'{self.text}, in bursts of up to {runs.max_length} samples '
                            f'(median {runs.median_length}) at random times')


@dataclass(frozen=True, kw_only=True)
class AnisotropicNoiseCandidate(CandidateEffect):
    """
    B's position noise larger along some axes of B's base frame: covariance σ² S (``noise_shape``).

    Attributes
    ----------
    factors : list of float
        σ's factor along S's principal axes, largest first (√ of S's eigenvalues).
    sigma : float
        Standard uncertainty of each factor (relative, from the pairs' count: σ_f ≈ f/√(2n)).
    axes : list of list of float
        The principal axes in B's base frame (unit vectors, rows; largest factor first).
    ratio : float
        Largest over smallest factor.
    text : str

    """

    name = 'anisotropic_noise'
    device = 'B'
    kind = 'noise'
    acts_on = 'variance'
    var_params = ('shape',)
    simpler = 'noise_scale'
    sets_noise_level = True

    factors: list
    sigma: float
    axes: list
    ratio: float
    text: str

    @classmethod
    def size(cls, reading):
        """Read S's principal axes and factors from the fit."""
        S = ns.shape_matrix(reading.var.shape) if reading.var.shape else np.eye(3)
        w, U = np.linalg.eigh(0.5 * (S + S.T))
        order = np.argsort(w)[::-1]
        f = np.sqrt(np.clip(w[order], 0.0, None))
        axes = U[:, order].T
        axes *= np.where(axes[np.arange(3), np.abs(axes).argmax(axis=1)] < 0, -1.0, 1.0)[:, None]
        n = len(reading.fit.stats.z) * max(reading.fit.stats.markers, 1)
        s = float(f[0] / np.sqrt(2.0 * max(n, 1)))
        ratio = float(f[0] / max(f[-1], 1e-12))
        return cls(factors=f.tolist(), sigma=s, axes=axes.tolist(), ratio=ratio,
                   text=(f'σ × {f[0]:.2f} along [' + ', '.join(f'{v:+.2f}' for v in axes[0])
                         + f"] of B's base, × {f[1]:.2f} and × {f[2]:.2f} across "
                         f'(± {s:.2f})'))
