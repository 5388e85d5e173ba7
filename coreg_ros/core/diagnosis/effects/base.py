"""
What every effect the diagnosis can name shares: ``CandidateEffect``, and the fit it is read from.

An effect's class says what the effect is (its name, whether it is structure or noise, how it
enters the model, whether it is tied to the workspace or needs motion, which simpler effect it
extends) and how large it is: ``size(reading)`` reads its estimate, with its standard
uncertainty, from the final fit (``FitReading``) and returns an instance of the class, whose
fields are the estimate's keys in the JSON document.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from coreg_ros.core.diagnosis import variance as vm
from coreg_ros.core.diagnosis.record import Record
import numpy as np


class CandidateEffect(Record):
    """
    Base of the effects: class attributes say what the effect is; an instance is its size.

    Attributes
    ----------
    name : str
        The effect's name (``coreg_ros.sim.injected``'s for the simulated ones).
    kind : str
        ``'structured'`` (an error the model can take off) or ``'noise'`` (it only describes
        the noise; it never closes the gap).
    acts_on : str or None
        How it extends the model: ``'time'`` (A evaluated at shifted times), ``'mean'`` (a
        term added to the output error), ``'variance'`` (the noise model); None for an effect
        named from what the fitted ones leave (not a candidate of the selection).
    term : type or None
        The model term (``terms.py``) of a time or mean effect.
    var_params : tuple of str
        The noise parameters (``variance.VarState``) a variance effect fits.
    spatial : bool
        Tied to the workspace: also cross-validated on unseen cells of it.
    needs_motion : bool
        Shows only while the tool moves (not a candidate of a static recording).
    simpler : str or None
        The effect this one extends (a special case of it); the simpler is preferred unless
        this one gains clearly more.
    sets_noise_level : bool
        Sets B's noise level: at most one such effect in a model.
    trend_checked : bool
        Accepted only if the offsets fitted per time block trend (``drift.drift_check``).
    device : str
        Whose effect it is (issue 23, item 5): ``'A'``, ``'B'`` (the device calibrated against
        A: a rig's device of that calibration), ``'A and B'`` (both), ``'A or B'`` (the data
        cannot tell which) or ``'link'`` (what joins the devices' tracked bodies).
    changes_at : str or None
        A change at one instant: the key of ``data.cache`` where the instant is located
        (``steps``); it is judged on the time blocks from that instant on (before it, it
        changes nothing).

    """

    name = ''
    kind = 'structured'
    acts_on: Optional[str] = None
    term = None
    var_params: tuple = ()
    spatial = False
    needs_motion = False
    simpler: Optional[str] = None
    sets_noise_level = False
    trend_checked = False
    device = 'A or B'
    changes_at: Optional[str] = None

    @classmethod
    def size(cls, reading: FitReading) -> CandidateEffect:
        """
        Read the effect's size, with its standard uncertainty, from the final fit.

        Parameters
        ----------
        reading : FitReading
            The final fit (every accepted effect) with its covariances.

        Returns
        -------
        CandidateEffect
            An instance of the class: the estimate.

        """
        raise NotImplementedError(f'{cls.name} is not fitted: it has no size of its own')

    @classmethod
    def model_term(cls, data):
        """Return the effect's model term (``term``) set up for the data (``DiagData``)."""
        term = cls.term()
        term.setup(data)
        return term

    def shifted(self, shift_s: float) -> CandidateEffect:
        """
        Return the estimate for pairs made ``shift_s`` (s) from the given clock offset.

        Only estimates on B's clock change; the others are returned as they are.
        """
        return self


@dataclass(frozen=True)
class FitReading:
    """
    The final fit as the effects' sizes read it.

    Attributes
    ----------
    fit : fit.Fit
        The model with every accepted effect, on all pairs.
    cov : ndarray or None
        Covariance of the mean parameters (φ, θ); None if singular.
    var_cov : ndarray or None
        Covariance of the noise parameters (order of ``fit.model.var_names``).
    inflation : float
        Factor (>= 1) on parameter variances: the chi-square per dof left under the fit.

    """

    fit: object
    cov: Optional[np.ndarray]
    var_cov: Optional[np.ndarray]
    inflation: float

    @classmethod
    def of(cls, fit) -> FitReading:
        """Read a fit: its covariances and the inflation of their variances."""
        var_cov = fit.var_cov() if fit.model.var_names else None
        return cls(fit, fit.mean_cov(), var_cov, vm.inflation(fit.state.var, fit.stats))

    @property
    def model(self):
        """Return the fitted ``fit.Model``."""
        return self.fit.model

    @property
    def var(self):
        """Return the fitted noise parameters (``variance.VarState``)."""
        return self.fit.state.var

    def theta(self, name: str) -> np.ndarray:
        """Return the parameters θ of the time or mean effect ``name``."""
        return self.fit.state.theta[name]

    def sd(self, name: str) -> np.ndarray:
        """Return the standard uncertainties of θ of ``name`` (NaN without a covariance)."""
        sl = self.model.slices[name]
        if self.cov is None:
            return np.full(sl.stop - sl.start, np.nan)
        return np.sqrt(np.clip(np.diag(self.cov)[sl], 0.0, None) * self.inflation)

    def cov_of(self, name: str) -> Optional[np.ndarray]:
        """Return the covariance of θ of ``name``, inflated (None without a covariance)."""
        if self.cov is None:
            return None
        sl = self.model.slices[name]
        return self.cov[sl, sl] * self.inflation

    def var_sd(self, param: str) -> float:
        """Return the standard uncertainty of the noise parameter ``param`` (NaN if not fitted)."""
        names = list(self.model.var_names)
        if self.var_cov is None or param not in names:
            return float('nan')
        i = names.index(param)
        return float(np.sqrt(max(self.var_cov[i, i], 0.0) * self.inflation))

    def noise_factor(self, param: str) -> tuple[float, float]:
        """
        Return the factor on the noise σ that a fitted log variance ``param`` gives, and its σ.

        f = exp(ℓ / 2) with ℓ the fitted log variance factor; σ_f = f σ_ℓ / 2 (delta method).
        """
        f = float(np.exp(0.5 * getattr(self.var, param)))
        return f, 0.5 * f * self.var_sd(param)


def ms_text(value_s: float, sigma_s: float) -> str:
    """Return a time and its uncertainty as text in ms, e.g. ``'12.10 ± 0.30 ms'``."""
    return f'{value_s * 1e3:.2f} ± {sigma_s * 1e3:.2f} ms'
