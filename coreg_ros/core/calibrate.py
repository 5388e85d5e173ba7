"""
Calibration from pairs: validation, closed-form start, OLS, TLS, observability, covariance.

This is the one entry point the CLI and the node use (through ``pipeline.calibrate_streams``),
so that both give the same numbers from the same pairs.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Optional

import numpy as np
from scipy import stats

from coreg_ros.core import quaternion as quat
from coreg_ros.core.covariance import Prior, result_poses
from coreg_ros.core.errors import (
    ConvergenceError,
    InconsistentDataError,
    InputError,
    TooFewPairsError,
)
from coreg_ros.core.estimator import Problem, Solution, solve_ols, solve_tls
from coreg_ros.core.initialize import initialize
from coreg_ros.core.linearized import PairData, normalised_squares
from coreg_ros.core.models import SPECS, ModelSpec, Parameters
from coreg_ros.core.observability import check_motion, check_observability
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, Pairs


def noise_covariance(sigma) -> np.ndarray:
    """6×6 covariance (ROS layout) of isotropic noise given as (position m, rotation rad)."""
    pos, rot = float(sigma[0]), float(sigma[1])
    return np.diag([pos ** 2] * 3 + [rot ** 2] * 3)


_METRIC = np.diag([1.0, 1.0, 1.0, -0.5, -0.5, -0.5])


def metric_covariance(cov: np.ndarray) -> np.ndarray:
    """
    Covariance of the error metric from a 6×6 ROS-layout covariance (rotation enters as Σθ/4).

    Parameters
    ----------
    cov : ndarray, shape (6, 6)
        Position (m²) and rotation-vector (rad²) covariance.

    Returns
    -------
    ndarray, shape (6, 6)

    """
    return _METRIC @ np.asarray(cov, dtype=float).reshape(6, 6) @ _METRIC


def output_covariance(cov_b: np.ndarray, spec: ModelSpec) -> np.ndarray:
    """Metric covariance of B's output (m×m): 6×6 full pose, 3×3 per marker otherwise."""
    metric = metric_covariance(cov_b)
    if spec.name == 'full_pose':
        return metric
    m = 3 * spec.n_markers
    out = np.zeros((m, m))
    for j in range(spec.n_markers):
        out[3 * j:3 * j + 3, 3 * j:3 * j + 3] = metric[0:3, 0:3]
    return out


def whitening(cov: np.ndarray, spec: Optional[ModelSpec], device: str) -> np.ndarray:
    """
    L with LᵀL the inverse covariance of the error metric, for device 'a' (6×6) or 'b' (m×m).

    The rotation metric is about half the angle (Ikits §3.2), so a rotation covariance Σθ
    enters as Σθ/4 (and position-rotation cross terms as -1/2).
    """
    metric = metric_covariance(cov) if device == 'a' else output_covariance(cov, spec)
    try:
        return np.linalg.inv(np.linalg.cholesky(metric))
    except np.linalg.LinAlgError as e:
        raise InputError(f'noise covariance of device {device.upper()} is not positive '
                         f'definite; give positive standard deviations') from e


def _validated(pairs: Pairs, spec: ModelSpec, settings: Settings):
    n = len(pairs)
    min_pairs = max(int(settings.min_pairs), spec.n_params // spec.n_res + 2)
    if n < min_pairs:
        raise TooFewPairsError(
            f'only {n} pairs (need at least {min_pairs}); record longer, move while recording, '
            f'or raise max_gap if the devices were not paired')
    pos_a = np.asarray(pairs.pos_a, dtype=float)
    pos_b = np.asarray(pairs.pos_b, dtype=float)
    want_b = (n, 3, 3) if spec.name == 'three_marker' else (n, 3)
    if pos_a.shape != (n, 3) or pos_b.shape != want_b:
        raise InputError(f'pairs have shapes {pos_a.shape} and {pos_b.shape}; model '
                         f'{spec.name} needs (N, 3) and {want_b}')
    for name, arr in (('device A position', pos_a), ('device B position', pos_b)):
        bad = ~np.isfinite(arr).reshape(n, -1).all(axis=1)
        if bad.any():
            raise InputError(f'{name}: {int(bad.sum())} pair(s) contain NaN or inf (first at '
                             f'pair {int(np.flatnonzero(bad)[0])}); drop those samples')
    orientations = (('device A orientation', pairs.quat_a), ('device B orientation', pairs.quat_b))
    for name, q in orientations:
        if q is not None and np.shape(q) != (n, 4):
            raise InputError(f'{name}: expected shape ({n}, 4) (one (w, x, y, z) per pair), got '
                             f'{np.shape(q)}')
    quat_a = quat.validate_quaternions(pairs.quat_a, 'device A orientation')
    quat_b = None
    if spec.has_q1:
        if pairs.quat_b is None:
            raise InputError('model full_pose needs device B orientations; use '
                             '--model position_only for a position-only tracker')
        quat_b = quat.validate_quaternions(pairs.quat_b, 'device B orientation')
    scale = None
    if pairs.a_var_scale is not None:
        scale = np.asarray(pairs.a_var_scale, dtype=float)
        if scale.shape != (n,) or not (np.isfinite(scale) & (scale > 0)).all():
            raise InputError('a_var_scale must be positive and finite, one per pair')
    return pos_a, quat_a, pos_b, quat_b, scale


#: Chance that the robust fit rejects a pair that fits the stated noise (per pair).
OUTLIER_ALPHA = 1e-4
#: Largest share of the pairs the robust fit may reject; beyond it the data do not fit.
MAX_REJECTED_SHARE = 0.25
#: Rounds of rejection and refit (the set of inliers settles in two or three).
MAX_ROUNDS = 10


class _Fitter:
    """One problem's data and noise; fits any subset of the pairs from any start."""

    def __init__(self, pairs: Pairs, spec: ModelSpec, settings: Settings,
                 prior: Optional[Prior], cov_a: np.ndarray, cov_b: np.ndarray):
        self.spec, self.settings = spec, settings
        (self.pos_a, self.quat_a, self.pos_b, self.quat_b,
         self.scale) = _validated(pairs, spec, settings)
        self.stamps = np.asarray(pairs.stamps, dtype=np.int64)
        self.whiten_a = whitening(cov_a, None, 'a')
        self.whiten_b = whitening(cov_b, spec, 'b')
        self.priors = prior.terms(spec) if prior is not None else []
        self.data = PairData(self.pos_a, self.quat_a, self.pos_b, self.quat_b,
                             np.asarray(cov_a, dtype=float).reshape(6, 6),
                             output_covariance(cov_b, spec),
                             self.scale, settings.method == 'tls')

    def solve(self, keep: np.ndarray, start: Optional[Parameters],
              warm: bool = False, with_priors: bool = True) -> Solution:
        """
        Fit the pairs in ``keep`` from ``start`` (closed form when None).

        OLS, then TLS if asked; a ``warm`` start (a fit of nearly the same pairs) goes to TLS
        directly.
        """
        def sub(x):
            return x if x is None or keep.all() else x[keep]

        settings = self.settings
        n_keep = int(keep.sum())
        min_pairs = max(int(settings.min_pairs), self.spec.n_params // self.spec.n_res + 2)
        if n_keep < min_pairs:
            raise TooFewPairsError(
                f'only {n_keep} pairs are left after rejecting outliers (need at least '
                f'{min_pairs}); record longer, or check the noise (sigma_b) and the units')
        quat_a = sub(self.quat_a)
        problem = Problem(self.spec, sub(self.pos_a), quat_a, sub(self.pos_b),
                          sub(self.quat_b), self.whiten_b, self.whiten_a, sub(self.scale),
                          self.priors if with_priors else [])
        tls = settings.method == 'tls'
        if start is None:
            start = initialize(self.spec, problem.pos_a, quat_a, problem.pos_b, problem.quat_b)
        if not (tls and warm):
            sol = solve_ols(problem, start, max_iterations=settings.max_iterations)
            check_observability(sol.info, sol.params, quat_a)
            start = sol.params
        if tls:
            sol = solve_tls(problem, start, max_iterations=settings.max_iterations)
            check_observability(sol.info, sol.params, quat_a)
        return sol

    def reject_outliers(self, sol: Solution, max_share: float = MAX_REJECTED_SHARE
                        ) -> tuple[np.ndarray, Solution]:
        """
        Reject pairs far outside the noise, refitting on the rest until the set settles.

        A pair is rejected when ``d² > s · χ²_m(1 - OUTLIER_ALPHA)`` with d² its normalised
        squared residual at the current fit (``linearized.normalised_squares``) and
        ``s = max(1, q25(d²) / q25(χ²_m))`` (lower quartiles, which outliers up to half the
        pairs do not reach): the stated noise, or the typical scatter of the inliers if that
        is larger (so that early rounds, fitted with the outliers in, keep the inliers, and a
        recording whose noise is understated throughout is judged by the fit verdict, not cut
        down). Rejected pairs are tested again each round. More than ``max_share`` rejected is
        refused (InconsistentDataError).
        """
        m = self.spec.n_res
        n = len(self.pos_a)
        limit = float(stats.chi2.isf(OUTLIER_ALPHA, m))
        quartile = float(stats.chi2.ppf(0.25, m))
        keep = np.ones(n, dtype=bool)
        for _ in range(MAX_ROUNDS):
            d2 = normalised_squares(sol.params, self.data)
            scale = max(1.0, float(np.quantile(d2[keep], 0.25)) / quartile)
            new = d2 <= scale * limit
            if np.array_equal(new, keep):
                break
            self._refuse_if_mostly_outside(~new, max_share)
            keep = new
            sol = self.solve(keep, sol.params, warm=True, with_priors=False)
        return keep, sol

    def _refuse_if_mostly_outside(self, outside: np.ndarray, max_share: float) -> None:
        share = float(outside.mean())
        if share > max_share:
            raise InconsistentDataError(
                f'{share:.0%} of the pairs lie far outside the stated noise: the data are '
                f'not the model plus a few outliers{_where(outside, self.stamps)}; check the '
                f'units and the noise (sigma_a, sigma_b) and run coreg diagnose')


def _where(rejected: np.ndarray, stamps: np.ndarray) -> str:
    """Say so when the rejected pairs form one block in time (a clock step, a moved device)."""
    idx = np.flatnonzero(rejected)
    if idx.size < 10:
        return ''
    lo, hi = int(idx[0]), int(idx[-1])
    if rejected[lo:hi + 1].mean() < 0.9 or hi - lo + 1 > 0.9 * rejected.size:
        return ''
    t = (stamps - stamps[0]).astype(float) * 1e-9
    return (f': they form one block from {t[lo]:.2f} s to {t[hi]:.2f} s into the recording, '
            f'where the data change (a clock step, or a device or marker moved); split the '
            f'recording there')


def calibrate(pairs: Pairs, settings: Optional[Settings] = None, prior: Optional[Prior] = None,
              cov_a: Optional[np.ndarray] = None, cov_b: Optional[np.ndarray] = None,
              start: Optional[Parameters] = None, warm: bool = False,
              max_rejected_share: float = MAX_REJECTED_SHARE) -> CalibrationResult:
    """
    Estimate T0 = T_bbase_abase and T1 = T_atool_bmarker from paired samples.

    Closed-form start (no guess needed), OLS (Ikits B.1) refined by TLS (B.2) when
    ``settings.method == 'tls'``, a priori estimates (B.3), chi-square goodness of fit (B.4.1)
    and posterior covariance (B.4.2) converted to the ROS layout. With ``settings.robust``,
    pairs far outside the noise are rejected and the fit is repeated on the rest.

    Parameters
    ----------
    pairs : Pairs
    settings : Settings
        Model, method, noise (``sigma_a``, ``sigma_b``), iteration limit, minimum pairs,
        robust.
    prior : Prior, optional
    cov_a, cov_b : ndarray, shape (6, 6), optional
        Full noise covariances (ROS layout) overriding ``sigma_a`` / ``sigma_b``.
    start : Parameters, optional
        A starting φ instead of the closed form.
    warm : bool
        ``start`` is a fit of nearly the same pairs (e.g. at a nearby time offset): TLS starts
        from it without an OLS pass.
    max_rejected_share : float
        Largest share of rejected pairs before the data are refused (1 never refuses, e.g.
        while comparing candidate time offsets).

    Returns
    -------
    CalibrationResult
        ``success`` is False (with the reason in ``message``) if the estimator did not converge.

    Raises
    ------
    TooFewPairsError, InputError, UnobservableError, InconsistentDataError

    """
    settings = settings or Settings()
    spec = SPECS[settings.model]
    cov_a = noise_covariance(settings.sigma_a) if cov_a is None else cov_a
    cov_b = noise_covariance(settings.sigma_b) if cov_b is None else cov_b
    fitter = _Fitter(pairs, spec, settings, prior, cov_a, cov_b)
    check_motion(fitter.quat_a, spec, float(np.sqrt(np.max(np.diag(cov_a)[3:6]))))
    keep = np.ones(len(pairs), dtype=bool)
    # outliers are a property of the data: they are found without the prior, which is then
    # tested against the data (verdict.prior_check) instead of pulling pairs out of the fit
    with_priors = not (settings.robust and prior is not None)
    try:
        sol = fitter.solve(keep, start, warm and start is not None, with_priors)
        if settings.robust:
            keep, sol = fitter.reject_outliers(sol, max_rejected_share)
            if prior is not None:
                sol = fitter.solve(keep, sol.params, warm=True)
    except np.linalg.LinAlgError as e:  # e.g. positions of 1e300 m: SVD does not converge
        raise ConvergenceError(
            f'the numbers do not allow a solution ({e}); check the data for absurd values '
            f'(units, a corrupt sample) with coreg diagnose') from e
    result = _result(sol, spec, settings, len(pairs))
    return replace(result, inliers=keep,
                   rejected_stamps=np.asarray(pairs.stamps, dtype=np.int64)[~keep])


def _result(sol: Solution, spec: ModelSpec, settings: Settings, n: int) -> CalibrationResult:
    t0, t1, joint = result_poses(sol.params, sol.cov)
    dof = sol.n_rows - spec.n_params
    p_value = float(stats.chi2.sf(sol.chi2, dof)) if dof > 0 else float('nan')
    success = sol.status > 0 and sol.cov is not None
    message = sol.message if sol.cov is not None else (
        sol.message + '; the covariance is singular (see observability)')
    return CalibrationResult(
        success=success, status=sol.status, message=message, model=spec.name,
        method=settings.method, n_pairs=n, base_to_base=t0, tool_to_marker=t1,
        markers=sol.params.markers.copy(), params=sol.params.phi.copy(), param_cov=sol.cov,
        chi2=float(sol.chi2), dof=int(dof), p_value=p_value, residuals=sol.residuals,
        iterations=sol.iterations, cov_joint=joint, input_residuals=sol.input_residuals,
        charts=tuple(sol.params.charts))
