"""
The estimated noise against the stated: per device and channel, the record the result carries.

``noise_estimate`` turns a ``noise_components.ComponentFit`` into a ``NoiseEstimate``: each
device's estimated covariances (held channels as stated), their principal σ with standard
errors (the delta method on ``F⁻¹``), and one statement per channel or group of channels:

- an estimated channel: the ratio of its size to the stated one (``√(tr Σ̂ / tr Σ)`` ± SE)
  and, when anisotropic, the axis of the largest ratio (the generalised eigenvector of
  ``(Σ̂, Σ)``): "B position noise 2.1 ± 0.1× stated, mostly along B's z";
- channels the motion cannot tell apart (a held channel and its partners): their joint size in
  the pairs' errors, "A and B position noise together 1.4 ± 0.02× stated";
- with OLS, B's channels hold A's noise too: compared with B's stated noise plus A's carried
  through the model.

A statement is *misstated* when its ratio is off by more than ``MISSTATED`` and by more than
``MISSTATED_SIGMAS`` standard errors; the verdict names those.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from coreg_ros.core.calibration.noise_components import (
    component_of,
    ComponentFit,
    covariance_of_theta,
    weight,
)
from coreg_ros.core.noise_model import DeviceNoise, principal_axes, UNITS
import numpy as np

#: A ratio of estimated to stated σ off by more than this share (and ``MISSTATED_SIGMAS``
#: standard errors) is a misstated noise.
MISSTATED = 0.2
MISSTATED_SIGMAS = 3.0
#: A correlation of position with rotation errors beyond this is said (``correlation``).
CORRELATED = 0.5
#: An anisotropic excess is named along an axis when its largest ratio exceeds the smallest
#: by this factor.
ANISOTROPY = 1.3
_DEVICE = {'a': 'A', 'b': 'B'}


@dataclass(frozen=True)
class ChannelEstimate:
    """
    One device channel: estimated, held or absent.

    Attributes
    ----------
    status : {'estimated', 'held', 'absent'}
        ``absent``: the model does not use it (B's orientation of a position-only tracker,
        A's noise under OLS).
    mode : {'scale', 'full', ''}
        A factor on the stated covariance, or its six entries.
    covariance, stated : ndarray, shape (3, 3)
    sigma, sigma_se : ndarray, shape (3,)
        Principal σ (largest first) and their standard errors (0 when held).
    axes : ndarray, shape (3, 3)
        Principal axes (rows) in the device's base frame.
    note : str
        Why held (or what the estimate holds besides the channel).

    """

    status: str
    mode: str
    covariance: np.ndarray
    stated: np.ndarray
    sigma: np.ndarray
    sigma_se: np.ndarray
    axes: np.ndarray
    note: str = ''


@dataclass(frozen=True)
class NoiseStatement:
    """
    The estimated noise of a channel (or of channels together) against the stated.

    Attributes
    ----------
    channels : tuple of (str, str)
        (device, kind) pairs the statement is about.
    ratio : float
        Estimated over stated σ (size).
    ratio_se : float
        Estimated over stated σ (size), with its standard error.
    text : str
    misstated : bool

    """

    channels: tuple
    ratio: float
    ratio_se: float
    text: str
    misstated: bool


@dataclass(frozen=True)
class NoiseEstimate:
    """
    Each device's noise estimated jointly with the calibration (``--noise auto``).

    Attributes
    ----------
    method : str
    n_pairs : int
        Pairs the components were estimated on.
    devices : dict
        ``'a'``/``'b'`` -> {kind: ChannelEstimate}.
    stated : dict
        ``'a'``/``'b'`` -> the stated DeviceNoise.
    estimated : dict
        ``'a'``/``'b'`` -> the DeviceNoise the final fit used.
    statements : list of NoiseStatement
    converged : bool
    dof : int
        Errors the noise was estimated from (pairs × residuals per pair): the fit's p-value at
        the estimated noise is that of ``F(dof_fit, dof)`` (``auto_noise.with_estimate``).
    correlation : float
        The largest correlation of position with rotation errors the estimate leaves
        (``noise_components.unmodelled_correlation``); above ``CORRELATED`` it is said.

    """

    method: str
    n_pairs: int
    devices: dict
    stated: dict
    estimated: dict
    statements: list = field(default_factory=list)
    converged: bool = True
    correlation: float = 0.0
    dof: int = 0

    @property
    def misstated(self) -> list:
        """Return the statements of misstated noise."""
        return [s for s in self.statements if s.misstated]

    def verdict(self) -> str:
        """Return what the verdict says of the noise ('' when as stated)."""
        bad = self.misstated
        out = 'noise not as stated: ' + '; '.join(s.text for s in bad) if bad else ''
        if self.correlation > CORRELATED:
            out = '; '.join(v for v in (out, self.correlation_note()) if v)
        return out

    def correlation_note(self) -> str:
        """Say that position and rotation errors go together beyond the noise model."""
        return (f'position and rotation errors are correlated ({self.correlation:.2f}) '
                f'beyond the noise model (a pose from a camera and a target does this): no 3×3 '
                f"covariance per channel states it, so the fit's chi-square and covariance are "
                f'approximate')


def _theta_slices(fit: ComponentFit) -> dict:
    out, k = {}, 0
    for c in fit.components:
        if c.mode != 'held':
            out[c.channel] = slice(k, k + len(c.theta))
            k += len(c.theta)
    return out


def _size_gradient(c) -> np.ndarray:
    """∂ tr(Σ) / ∂θ of a component."""
    if c.mode == 'scale':
        return np.array([float(np.trace(c.stated))])
    return np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])


def _principal_se(c, cov_theta: np.ndarray) -> np.ndarray:
    """Return the standard errors of the principal σ of an estimated component (delta method)."""
    sig, axes = principal_axes(c.covariance())
    out = np.zeros(3)
    for j in range(3):
        v = axes[j]
        if c.mode == 'scale':
            g = np.array([float(v @ c.stated @ v)])
        else:
            g = np.array([v[0] ** 2, v[1] ** 2, v[2] ** 2, 2 * v[0] * v[1], 2 * v[0] * v[2],
                          2 * v[1] * v[2]])
        var = float(g @ cov_theta @ g)
        out[j] = np.sqrt(max(var, 0.0)) / max(2.0 * sig[j], 1e-300)
    return out


def _along(device: str, excess_axis: np.ndarray) -> str:
    k = int(np.argmax(np.abs(excess_axis)))
    if abs(excess_axis[k]) >= 0.9:
        return f"mostly along {_DEVICE[device]}'s {'xyz'[k]}"
    v = excess_axis * np.sign(excess_axis[k])
    return f"mostly along [{', '.join(f'{x:+.2f}' for x in v)}] of {_DEVICE[device]}'s base"


def _direction(c) -> str:
    """Name the axis of the largest ratio when the excess is anisotropic ('' otherwise)."""
    if c.mode != 'full':
        return ''
    L = np.linalg.cholesky(c.stated)
    Li = np.linalg.inv(L)
    lam, V = np.linalg.eigh(Li @ c.covariance() @ Li.T)
    if not lam[0] > 0 or np.sqrt(lam[-1] / lam[0]) < ANISOTROPY:
        return ''
    axis = Li.T @ V[:, -1]
    return ', ' + _along(c.channel[0], axis / np.linalg.norm(axis))


def _statement(channels: tuple, ratio: float, se: float, subject: str, extra: str = ''
               ) -> NoiseStatement:
    off = abs(ratio - 1.0)
    misstated = bool(off > MISSTATED and off > MISSTATED_SIGMAS * se)
    text = f'{subject} {ratio:.3g} ± {se:.2g}× stated{extra}'
    return NoiseStatement(tuple(channels), float(ratio), float(se), text, misstated)


def _name(channel: tuple) -> str:
    return f'{_DEVICE[channel[0]]} {channel[1]}'


def _statements(fit: ComponentFit, cov_theta: np.ndarray, method: str,
                ols_stated: Optional[dict]) -> list:
    slices = _theta_slices(fit)
    out = []
    grouped = set()
    for c in fit.components:
        if c.mode == 'held' and c.partners:
            group = [c.channel] + list(c.partners)
            grouped.update(group)
            est = sum(weight(fit.pairs, fit.layout, ch, component_of(fit, ch).covariance())
                      for ch in group)
            stated = sum(weight(fit.pairs, fit.layout, ch, component_of(fit, ch).stated)
                         for ch in group)
            var = 0.0
            for ch in c.partners:  # the size is linear in each partner's θ
                p = component_of(fit, ch)
                g = np.array([weight(fit.pairs, fit.layout, ch, b) for b in p.basis()])
                var += float(g @ cov_theta[slices[ch], slices[ch]] @ g)
            ratio = np.sqrt(est / stated)
            kinds = {ch[1] for ch in group}
            devices = ' and '.join(sorted(_DEVICE[ch[0]] for ch in group))
            subject = f'{devices} {"/".join(sorted(kinds))} noise together'
            where = ''.join(_direction(component_of(fit, ch)) for ch in c.partners)
            out.append(_statement(group, ratio, np.sqrt(var) / (2.0 * ratio * stated),
                                  subject, f'{where} (this motion cannot tell them apart: '
                                           f'{_name(c.channel)} held at the stated value)'))
    for c in fit.components:
        if c.channel in grouped:
            continue
        if c.mode == 'held':
            out.append(NoiseStatement((c.channel,), 1.0, 0.0,
                                      f'{_name(c.channel)} noise held at the stated value: '
                                      f'{c.why}', False))
            continue
        sl = slices[c.channel]
        g = _size_gradient(c)
        tr = float(np.trace(c.covariance()))
        if method == 'ols' and ols_stated is not None:
            # in the error metric, beside B's stated noise with A's carried through the model
            stated = ols_stated[c.channel]
            est = weight(fit.pairs, fit.layout, c.channel, c.covariance())
            g = np.array([weight(fit.pairs, fit.layout, c.channel, b) for b in c.basis()])
            ratio = np.sqrt(est / stated)
            se = np.sqrt(max(float(g @ cov_theta[sl, sl] @ g), 0.0)) / (2.0 * ratio * stated)
            out.append(_statement((c.channel,), ratio, se,
                                  f"{c.channel[1]} noise (OLS: A's and B's together)",
                                  _direction(c)))
            continue
        stated = float(np.trace(c.stated))
        ratio = np.sqrt(tr / stated)
        se = np.sqrt(max(float(g @ cov_theta[sl, sl] @ g), 0.0)) / (2.0 * ratio * stated)
        extra = _direction(c) + ('; at zero: what is held elsewhere exceeds what the pairs '
                                 'show' if c.why == 'at its bound' else '')
        out.append(_statement((c.channel,), ratio, se, f'{_name(c.channel)} noise', extra))
    return out


def noise_estimate(fit: ComponentFit, method: str, stated_a: DeviceNoise,
                   stated_b: DeviceNoise, ols_stated: Optional[dict] = None) -> NoiseEstimate:
    """
    Build the record of an estimation (module docstring).

    Parameters
    ----------
    fit : ComponentFit
        The estimation.
    method : {'ols', 'tls'}
        The calibration's method.
    stated_a, stated_b : DeviceNoise
        The stated noise.
    ols_stated : dict, optional
        OLS: (device, kind) -> the mean trace B's channel and A's noise carried through the
        model put in the pairs' errors, as stated (``noise_components.ols_stated``).

    """
    cov_theta = covariance_of_theta(fit.fisher)
    slices = _theta_slices(fit)
    stated = {'a': stated_a, 'b': stated_b}
    devices, estimated = {}, {}
    for d in 'ab':
        chans = {}
        for kind in ('position', 'rotation'):
            c = component_of(fit, (d, kind))
            st = stated[d].channel(kind)
            if c is None:
                note = ("OLS has no errors in A (its noise is in B's)" if d == 'a'
                        and method == 'ols' else 'the model does not use it')
                sig, axes = principal_axes(st)
                chans[kind] = ChannelEstimate('absent', '', st, st, sig, np.zeros(3), axes,
                                              note)
                continue
            sig, axes = principal_axes(c.covariance())
            if c.mode == 'held':
                note = c.why if not c.partners else (
                    'not separable from ' + ', '.join(_name(p) for p in c.partners))
                chans[kind] = ChannelEstimate('held', '', st, st, sig, np.zeros(3), axes, note)
            else:
                se = _principal_se(c, cov_theta[slices[c.channel], slices[c.channel]])
                chans[kind] = ChannelEstimate('estimated', c.mode, c.covariance(), st, sig, se,
                                              axes, c.why)
        devices[d] = chans
        estimated[d] = DeviceNoise.from_covariances(chans['position'].covariance,
                                                    chans['rotation'].covariance, d.upper())
    return NoiseEstimate(method, fit.n_pairs, devices, stated, estimated,
                         _statements(fit, cov_theta, method, ols_stated), fit.converged)


def stated_noise_dict(stated_a: DeviceNoise, stated_b: DeviceNoise) -> dict:
    """Return the ``noise`` JSON of a calibration whose noise was stated (not estimated)."""
    out = {}
    for d, noise in (('a', stated_a), ('b', stated_b)):
        block = {'estimated': False}
        for kind in ('position', 'rotation'):
            sig, _ = noise.principal(kind)
            block[f'{kind}_sigma_{UNITS[kind]}'] = sig.tolist()
            block[f'{kind}_covariance'] = noise.channel(kind).tolist()
        out[f'device_{d}'] = block
    return out


def estimate_dict(est: NoiseEstimate) -> dict:
    """
    Return the ``noise`` JSON of an estimation.

    Per device: ``estimated`` (any channel), per channel ``{kind}_sigma_{unit}`` (principal),
    ``{kind}_covariance``, ``{kind}_axes``, and ``sigma_of_estimate``, ``stated``,
    ``channels`` (status and note); then ``statements`` (ratio to stated) and ``verdict``.
    """
    out = {'method': est.method, 'n_pairs': est.n_pairs, 'converged': est.converged}
    for d in 'ab':
        chans = est.devices[d]
        block = {'estimated': any(ch.status == 'estimated' for ch in chans.values())}
        sigma_se, stated, status = {}, {}, {}
        for kind, ch in chans.items():
            unit = UNITS[kind]
            block[f'{kind}_sigma_{unit}'] = ch.sigma.tolist()
            block[f'{kind}_covariance'] = ch.covariance.tolist()
            block[f'{kind}_axes'] = ch.axes.tolist()
            sigma_se[f'{kind}_sigma_{unit}'] = ch.sigma_se.tolist()
            stated[f'{kind}_sigma_{unit}'] = principal_axes(ch.stated)[0].tolist()
            stated[f'{kind}_covariance'] = ch.stated.tolist()
            status[kind] = {'status': ch.status, 'mode': ch.mode, 'note': ch.note}
        block.update(sigma_of_estimate=sigma_se, stated=stated, channels=status)
        out[f'device_{d}'] = block
    out['unmodelled_correlation'] = est.correlation
    out['statements'] = [{'channels': [f'{_DEVICE[d]} {k}' for d, k in s.channels],
                          'ratio_to_stated': s.ratio, 'ratio_se': s.ratio_se, 'text': s.text,
                          'misstated': s.misstated} for s in est.statements]
    out['verdict'] = est.verdict()
    return out
