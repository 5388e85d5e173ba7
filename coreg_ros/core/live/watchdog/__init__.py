"""
Watchdog of a published calibration: does every new pair still fit it, and if not, what changed.

1. **Per pair**, the residual of B's measurement against the calibration's prediction from A,
   in the ROS tangents of ``crlb`` (position m, small rotation ``R_meas = Exp(r) R_pred``),
   ``r = y ⊖ f(x, ψ̂)``, is normalised by its covariance at the stated noise with the
   calibration's own uncertainty included:
   ``S = Σ_b + s F_x Σ_a F_xᵀ + F C Fᵀ`` with ``F = [F_ψ, c]`` (``c = -F_x ẋ_A``, the clock
   offset's column) and C the joint covariance of (ψ, τ). ``d² = rᵀ S⁻¹ r ~ χ²_m`` while the
   calibration holds.
2. **Sequential test**: a CUSUM of the log-likelihood ratio of "the residuals' covariance is
   inflated by ``DESIGN_INFLATION``" against "as stated", per pair
   ``ℓ = ½ (1 - 1/λ) min(d², c) - ½ m ln λ``. A change of T0, T1 or the clock adds a mean
   to r, a noise or field change scales it: both raise d² and the CUSUM detects either. d² is
   clipped at the χ²_m ``1 - CLIP_TAIL`` quantile, so an isolated outlier cannot raise an
   alarm alone. The threshold h is set from the CUSUM's in-control run length computed exactly
   for χ²_m residuals (Brook & Evans' Markov chain): the mean number of pairs between false
   alarms is ``TARGET_RUN_LENGTH`` (10⁹ pairs: one per 116 days at 100 Hz, per 11.6 days at
   1 kHz).
3. **Attribution**: after an alarm, the pairs since the CUSUM last stood at zero (the change
   point estimate) are fitted with each alternative, linear in its own parameters: T0 moved
   (δp0, δθ0: the base was bumped), T1 moved (δp1[, δθ1]; the marker set as a rigid body for
   three markers: the marker slipped), the clock offset changed (δτ), or the noise or field
   changed (residual covariance × λ, no mean). The alternatives are compared by their
   -2 log-likelihood (clipped per pair, so outliers do not decide) plus ``k ln n`` (BIC); the
   winner is decided when it beats the runner-up by ``DECISIVE``. Its size is reported with σ
   (fit covariance plus the calibration's own uncertainty of that part).
4. **States**: OK; WARN from the alarm until the attribution is decided (or, if the window
   fits the calibration after all, back to OK: a transient); ERROR once decided, kept until
   the watchdog is reset with a new calibration. ERROR means the calibration is stale.

Units SI (m, rad, s); stamps int64 ns; quaternions (w, x, y, z).

Modules: ``keys`` (the /diagnostics vocabulary), ``threshold`` (1-2), ``residuals`` (1),
``attribution`` (3), ``monitor`` (4: ``Watchdog``, ``WatchState``).
"""

from coreg_ros.lazy import lazy_exports

#: Public name -> the submodule that defines it (imported on first use, PEP 562, so that light
#: readers such as ``coreg watch`` can import a submodule without the numerical machinery).
_HOMES = {
    'Attribution': 'attribution',
    'CHAIN_CELLS': 'threshold',
    'CLIP_TAIL': 'threshold',
    'Calibration': 'residuals',
    'DECISIVE': 'attribution',
    'DESIGN_INFLATION': 'threshold',
    'ERROR': 'keys',
    'FIT_CLIP_TAIL': 'attribution',
    'KEEP_S': 'monitor',
    'KEY_ALARM_STAMP': 'keys',
    'KEY_CHANGE': 'keys',
    'KEY_CHANGE_STAMP': 'keys',
    'KEY_CHECKED': 'keys',
    'KEY_CLOCK': 'keys',
    'KEY_MEAN_D2': 'keys',
    'KEY_MESSAGE': 'keys',
    'KEY_NOISE': 'keys',
    'KEY_ROTATION': 'keys',
    'KEY_STALE': 'keys',
    'KEY_STATE': 'keys',
    'KEY_STATISTIC': 'keys',
    'KEY_THRESHOLD': 'keys',
    'KEY_TRANSLATION': 'keys',
    'KINDS': 'keys',
    'KIND_TEXT': 'keys',
    'LEVEL_NAMES': 'keys',
    'Linearised': 'residuals',
    'MAX_FIT_PAIRS': 'monitor',
    'MAX_UNDECIDED_S': 'monitor',
    'MIN_WINDOW_PAIRS': 'monitor',
    'MIN_WINDOW_S': 'monitor',
    'OK': 'keys',
    'REFINE_S': 'monitor',
    'STATUS_NAME': 'keys',
    'TARGET_RUN_LENGTH': 'threshold',
    'WARN': 'keys',
    'WatchState': 'monitor',
    'Watchdog': 'monitor',
    'attribute': 'attribution',
    'cusum_threshold': 'threshold',
    'describe': 'attribution',
    'linearise': 'residuals',
    'llr_constants': 'threshold',
    'recalibration_prior': 'attribution',
    'residuals': 'residuals',
    'run_length': 'threshold',
}

__all__ = sorted(_HOMES)


__getattr__, __dir__ = lazy_exports(__name__, _HOMES, globals())
