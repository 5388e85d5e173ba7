"""
``noise: auto``: each device's noise estimated with the calibration, the calibration refitted.

The calibration is first made at the stated noise (the offset search included); each device's
noise is then estimated from the pairs at that fit (``noise_components``: variance components
by REML, what the motion cannot separate held at the stated value), and the calibration is
fitted again, once more at its clock offset, with the estimated noise: its covariance is then
that of the estimated noise, and its chi-square is judged against it. The record of the
estimation (``noise_verdict.NoiseEstimate``) travels in ``CalibrationResult.noise``; the
verdict names the channels whose noise was misstated.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.calibration.noise_components import (
    estimate_components,
    linearised_pairs,
    noise_matrix,
    ols_stated,
    screened,
    stated_channels,
    unmodelled_correlation,
)
from coreg_ros.core.calibration.noise_verdict import noise_estimate, NoiseEstimate
from coreg_ros.core.calibration.offset_search import (
    fit_at_offset,
    fit_with_offset_search,
    refit_at,
)
from coreg_ros.core.calibration.pair_input import validated_arrays
from coreg_ros.core.calibration.pairing import pair_for
from coreg_ros.core.distributions import scipy_stats
from coreg_ros.core.errors import CoregError
from coreg_ros.core.estimator.priors import Prior
from coreg_ros.core.models import Parameters, SPECS
from coreg_ros.core.noise_model import DeviceNoise
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, PairingReport, Pairs, PoseStream, TimeOffset
import numpy as np

#: Rounds of "estimate, screen at the estimate" at most (the set settles in one or two).
SCREEN_ROUNDS = 4
#: A fit made at a noise within this share (of each variance, in every direction) of the final
#: estimate stands: its covariance is then within about as much of the estimate's.
AGREE = 0.03


def stated_noise(settings: Settings) -> tuple[DeviceNoise, DeviceNoise]:
    """Return the stated DeviceNoise of A and B (``noise_a``/``noise_b``, else the σ)."""
    out = []
    for d in 'ab':
        given = settings.device_noise(d)
        out.append(given if isinstance(given, DeviceNoise) else DeviceNoise.isotropic(given))
    return out[0], out[1]


def estimate_noise(pairs: Pairs, settings: Settings, result: CalibrationResult
                   ) -> NoiseEstimate:
    """
    Estimate each device's noise from the pairs of a calibration at the stated noise.

    Parameters
    ----------
    pairs : Pairs
        The pairs ``result`` was fitted to (those far outside the noise are left out, by the
        rule of the robust fit, at the stated noise and then at the estimate).
    settings : Settings
        Model, method and the stated noise.
    result : CalibrationResult
        The calibration at the stated noise.

    Returns
    -------
    NoiseEstimate

    """
    spec = SPECS[settings.model]
    pos_a, quat_a, pos_b, quat_b, scale = validated_arrays(pairs, spec, settings)
    params = Parameters(spec, result.params, list(result.charts))
    tls = settings.method == 'tls'
    sub, layout = linearised_pairs(params, pos_a, quat_a, pos_b, quat_b, scale, tls)
    stated = stated_channels(spec, settings.cov_a, settings.cov_b, tls)
    # the pairs within the noise, by the robust fit's rule, at the stated noise and then at
    # the estimate until they settle: the refit rejects by the estimate, and a variance
    # estimated with pairs it then rejects would be too large for those it keeps
    keep = screened(sub, layout, noise_matrix(layout, stated))
    for _ in range(SCREEN_ROUNDS):
        fit = estimate_components(sub.take(keep), layout, stated)
        now = screened(sub, layout, noise_matrix(layout, fit.covariances()))
        if np.array_equal(now, keep):
            break
        keep = now
    noise_a, noise_b = stated_noise(settings)
    ols = None if tls else ols_stated(sub, layout, stated, settings.cov_a)
    estimate = noise_estimate(fit, settings.method, noise_a, noise_b, ols)
    left = noise_matrix(layout, fit.covariances())
    corr = unmodelled_correlation(sub.take(keep), layout, left)
    return replace(estimate, correlation=corr, dof=int(keep.sum()) * spec.n_res)


def with_estimated_noise(settings: Settings, estimate: NoiseEstimate) -> Settings:
    """Return the settings with the estimated noise as ``noise_a``/``noise_b``."""
    return replace(settings, noise_a=estimate.estimated['a'], noise_b=estimate.estimated['b'])


def calibrate_with_noise(stream_a: PoseStream, streams_b: list, settings: Settings,
                         prior: Optional[Prior]
                         ) -> tuple[CalibrationResult, PairingReport, Settings]:
    """
    Calibrate with each device's noise estimated (``noise: auto``; the module docstring).

    With the clock offset estimated, the noise is first estimated at the search's best
    subsample round (its offset and fit, on all samples paired there: the subsample's 1500
    pairs alone leave each variance 3-7 % off, which the check below would refit for), and
    the rounds on all samples are made at it; then estimated again from the fit of all
    pairs. When the two agree (every channel's variance within ``AGREE``), that fit
    stands; else it is made again at the second (``offset_search.refit_at``). With the offset
    given: the fit at the stated noise, the estimate, the fit at it.

    Returns
    -------
    result : CalibrationResult
        The fit at the estimated noise, with ``noise`` (the ``NoiseEstimate``) and the p-value
        of ``with_estimate``.
    report : PairingReport
    settings : Settings
        The settings with the noise the fit used (what the verdict judges the fit against).

    """
    used = settings
    if settings.estimate_time_offset:
        def noise_from(timing, result):
            nonlocal used
            pairs, _ = pair_for(stream_a, streams_b, settings, timing)
            try:
                used = with_estimated_noise(settings, estimate_noise(pairs, settings, result))
            except CoregError:
                used = settings  # too little on the subsample: estimated on all pairs below
            return used

        result, report = fit_with_offset_search(stream_a, streams_b, settings, prior,
                                                noise_from=noise_from)
    else:
        result, report = fit_at_offset(stream_a, streams_b, settings, prior,
                                       TimeOffset(settings.time_offset, message='given'))
    pairs, _ = pair_for(stream_a, streams_b, settings, result.time_offset)
    estimate = estimate_noise(pairs, settings, result)
    if not _agree(estimate, used):
        used = with_estimated_noise(settings, estimate)
        result, report = refit_at(stream_a, streams_b, used, prior, result)
    return with_estimate(result, estimate), report, used


def _agree(estimate: NoiseEstimate, used: Settings) -> bool:
    """Tell whether the noise a fit used is the estimate's, each channel within ``AGREE``."""
    for d in 'ab':
        had = used.device_noise(d)
        if not isinstance(had, DeviceNoise):
            return False
        for kind in ('position', 'rotation'):
            a, b = estimate.estimated[d].channel(kind), had.channel(kind)
            L = np.linalg.inv(np.linalg.cholesky(a))
            if np.max(np.abs(np.linalg.eigvalsh(L @ b @ L.T) - 1.0)) > AGREE:
                return False
    return True


def with_estimate(result: CalibrationResult, estimate: NoiseEstimate) -> CalibrationResult:
    """
    Return a fit at the estimated noise with the estimate and the p-value that fits it.

    The noise was estimated from ``estimate.dof`` errors of the same data, so ``χ²/dof`` is a
    ratio of two estimates of one variance: its p-value is that of ``F(dof, estimate.dof)``,
    not of χ²_dof (which a noise estimated to 1 % fails at a million residuals, though the
    fit is as good as the noise is known).
    """
    if not result.dof > 0:
        return replace(result, noise=estimate)
    p = float(scipy_stats().f.sf(result.chi2 / result.dof, result.dof, max(estimate.dof, 1)))
    return replace(result, noise=estimate, p_value=p)


def calibrate_pairs(pairs: Pairs, settings: Optional[Settings] = None,
                    prior: Optional[Prior] = None, **kwargs) -> CalibrationResult:
    """
    Calibrate paired samples (``calibrate.calibrate``), estimating the noise if asked.

    With ``settings.noise == 'auto'`` each device's noise is estimated from the pairs of the
    fit at the stated noise (``estimate_noise``) and the pairs are fitted again with it: the
    result carries the estimate (``noise``) and its verdict names what was misstated. Keyword
    arguments go to ``calibrate.calibrate``.
    """
    settings = settings or Settings()
    result = calibrate(pairs, settings, prior, **kwargs)
    if settings.noise != 'auto':
        return result
    estimate = estimate_noise(pairs, settings, result)
    start = Parameters(SPECS[settings.model], result.params, list(result.charts))
    rest = {k: v for k, v in kwargs.items() if k not in ('start', 'warm')}
    refit = calibrate(pairs, with_estimated_noise(settings, estimate), prior, start=start,
                      warm=True, **rest)
    return replace(with_estimate(refit, estimate), verdict=estimate.verdict())


def noise_floor(pairs: Pairs, settings: Settings) -> tuple:
    """
    Return the noise estimated from the pairs' calibration, as the diagnosis' floor.

    Returns
    -------
    estimate : NoiseEstimate
    cov_a, cov_b : ndarray, shape (6, 6)
        The estimated covariances (ROS layout).

    """
    estimate = estimate_noise(pairs, settings, calibrate(pairs, settings))
    return estimate, estimate.estimated['a'].covariance(), estimate.estimated['b'].covariance()
