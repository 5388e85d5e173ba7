"""
Calibration from pairs: validation, closed-form start, OLS, TLS, observability, covariance.

This is the one entry point the CLI and the node use (through ``pipeline.calibrate_streams``),
so that both give the same numbers from the same pairs. Ikits' robust loop: start, fit,
reject, refit, the verdict's numbers; on a rig that cannot move in every direction the
directions the motion does not determine are held at the start's value and marked unknown
(``observability``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

from coreg_ros.core.calibration import observability, screening
from coreg_ros.core.calibration.initialize import initialize
from coreg_ros.core.calibration.observability import (
    hold_prior,
    refuse_if_nothing_moved,
    result_covariances,
    Undetermined,
    undetermined,
)
from coreg_ros.core.calibration.pair_input import validated_arrays
from coreg_ros.core.calibration.turn_family import turn_angles, turn_axis, turned
from coreg_ros.core.distributions import chi2_isf, chi2_ppf, chi2_sf
from coreg_ros.core.errors import (
    ConvergenceError,
    InconsistentDataError,
    TooFewPairsError,
)
from coreg_ros.core.estimator import (
    can_take_out,
    carried_inputs,
    heading,
    InputState,
    normal_equations,
    ols_cost,
    ols_information,
    output_covariance,
    paused,
    Problem,
    reweighted,
    Solution,
    solve_ols,
    solve_tls,
    tls_residuals,
    weighable,
    whitening,
    without_pairs,
)
from coreg_ros.core.estimator.linearized import PairData, reference_squares
from coreg_ros.core.estimator.priors import gauge_terms, Prior, prior_rows
from coreg_ros.core.models import ModelSpec, Parameters, SPECS
from coreg_ros.core.settings import Settings
from coreg_ros.core.types import CalibrationResult, Pairs
import numpy as np

#: Chance that the robust fit rejects a pair that fits the stated noise (per pair).
OUTLIER_ALPHA = 1e-4
#: Largest share of the pairs the robust fit may reject; beyond it the data do not fit.
MAX_REJECTED_SHARE = 0.25
#: Rounds of rejection and refit (the set of inliers settles in two or three).
MAX_ROUNDS = 10

#: Convergence tolerance of calibrate's fits (the solvers' default, ``estimator.XTOL``, is
#: 1e-5 σ): stop when the next step would move every parameter by at most this many posterior
#: σ. Near the minimum the steps shrink linearly (0.5° rotation noise on A, TLS, 1M pairs:
#: 32 σ, 7.9 σ, 1.5e-3 σ, 2.8e-4 σ, then by ~0.17 a step), so the estimate is within
#: ~1.2·XTOL σ of the minimum: 5e-3 σ changes no statistic (+2.5e-5 on the mean squared error;
#: scipy's 1e-8 relative to |φ| is ~1e-2 σ at 100k pairs); ten times tighter is one more pass.
XTOL = 5e-3

#: Pairs the start (closed form, then OLS) uses at most, every k-th pair, before the fit of
#: all pairs (see ``_Fitter._start``): for OLS on all pairs, a start close enough that it
#: converges in two passes; for TLS, whose first steps from the measured inputs are many σ
#: anyway, fewer (the same three TLS passes at 100k and 1M pairs from either size).
SUBSAMPLE = 100_000
SUBSAMPLE_TLS = 25_000
#: Pairs (every k-th) a restricted rig's closed-form start is refined on by OLS when the
#: recording is below ``SUBSAMPLE`` (``_Fitter.start``).
RESTRICTED_SUBSAMPLE = 10_000
#: First LM damping of a TLS refit that starts at the last fit's inputs.
WARM_DAMPING = 1e-9
#: Pairs (every k-th) the information is taken on to see what the data determine: the
#: eigenvalue shares of the scaled information do not depend on N.
OBSERVABILITY_SAMPLE = 25_000
#: Pairs (every k-th) the turns of a turntable's start are compared on (``along_the_turn``).
TURN_SAMPLE = 2_000
#: Times the held directions are looked for again at the solution (a start far from it may
#: name them a little differently); the fit is repeated when they changed.
HOLD_ROUNDS = 2


@dataclass(frozen=True)
class FastPaths:
    """
    The fast paths of ``calibrate``, each of which gives the answer of the plain one.

    To within the stopping rule: ``test_calibrate_speed_paths.py`` compares them. Switched off
    only to compare with the plain paths (``PLAIN``).

    Attributes
    ----------
    start : bool
        The start from a subsample (``_Fitter._start``).
    refit : bool
        Robust refits that go on from the last fit (``estimator.refit``): TLS from its inputs,
        or from its sums less the removed pairs; OLS from its normal equations with 0/1
        weights.
    squares : bool
        The robust statistic in one light pass (``screening``).
    screen : bool
        The first robust TLS fit screened where its second step leads, before the pass that
        would prove it converged (``_Fitter.reject_outliers``).

    """

    start: bool = True
    refit: bool = True
    squares: bool = True
    screen: bool = True


#: Every fast path on (the default).
FAST = FastPaths()
#: Every fast path off: the plain paths the fast ones are compared with.
PLAIN = FastPaths(start=False, refit=False, squares=False, screen=False)


class _Fitter:
    """One problem's data and noise; fits any subset of the pairs from any start."""

    def __init__(self, pairs: Pairs, spec: ModelSpec, settings: Settings,
                 prior: Optional[Prior], cov_a: np.ndarray, cov_b: np.ndarray,
                 paths: FastPaths = FAST):
        self.spec, self.settings, self.paths = spec, settings, paths
        self.stated = f'sigma_a {_stated(cov_a)}, sigma_b {_stated(cov_b)}'
        (self.pos_a, self.quat_a, self.pos_b, self.quat_b,
         self.scale) = validated_arrays(pairs, spec, settings)
        self.stamps = np.asarray(pairs.stamps, dtype=np.int64)
        self.whiten_a = whitening(cov_a, None, 'a')
        self.whiten_b = whitening(cov_b, spec, 'b')
        self.prior = prior
        self.priors = prior.terms(spec) if prior is not None else []
        self.data = PairData(self.pos_a, self.quat_a, self.pos_b, self.quat_b,
                             np.asarray(cov_a, dtype=float).reshape(6, 6),
                             output_covariance(cov_b, spec),
                             self.scale, settings.method == 'tls')
        # all pairs, for the robust statistic of every pair (rejected ones are tested again)
        self.everything = Problem(spec, self.pos_a, self.quat_a, self.pos_b, self.quat_b,
                                  self.whiten_b, self.whiten_a, self.scale)
        self.sigma_rot_a = float(np.sqrt(np.max(np.diag(np.asarray(cov_a).reshape(6, 6))[3:6])))
        # the directions the motion does not determine, and the gauge that holds them (part
        # of every fit, with or without the user's prior: it is not knowledge, a convention)
        self.found = Undetermined(np.zeros((spec.n_params, 0)), np.zeros((spec.n_params, 0)),
                                  np.ones(spec.n_params))
        self.gauge, self.held_components = [], []

    def problem(self, keep: np.ndarray, with_priors: bool = True,
                lazy: bool = False) -> Problem:
        """
        Return the pairs in ``keep`` as a Problem (the arrays themselves if all are kept).

        ``lazy``: gathered chunk by chunk as read (``Problem.subset``), for a fit that reads
        them a few times, without a second copy of nearly all pairs.
        """
        idx = None if keep.all() else np.flatnonzero(keep)
        return self.everything.subset(idx, self.gauge + (self.priors if with_priors else []),
                                      lazy=lazy)

    def undetermined_at(self, params: Parameters, keep: np.ndarray) -> Undetermined:
        """
        Find what the pairs in ``keep`` and the prior leave undetermined at ``params``.

        From the OLS information of every k-th pair (at most ``OBSERVABILITY_SAMPLE``), the
        prior's rows at ``params`` beside it (``observability.undetermined``).
        """
        idx = np.flatnonzero(keep)
        idx = idx[::max(1, len(idx) // OBSERVABILITY_SAMPLE)]
        data_info = ols_information(self.everything.subset(idx), params)
        prior_info = None
        if self.priors:
            _, J = prior_rows(self.everything.subset(None, self.priors), params)
            prior_info = J.T @ J
        return undetermined(data_info, prior_info, params, self.sigma_rot_a)

    def hold_undetermined(self, start: Parameters, keep: np.ndarray) -> Parameters:
        """
        Look for what the data leave undetermined at ``start``; hold it there from now on.

        Directions the prior determines are moved to the prior first (``towards_prior``):
        the start's value along them is arbitrary, and the prior alone pulls the fit there,
        over a cost nearly flat along them. Returns the start to fit from.
        """
        found = self.undetermined_at(start, keep)
        if found.by_prior.shape[1]:
            turned = self.along_the_turn(start, keep)
            if turned is not start:  # the directions turn with the calibration
                start, found = turned, self.undetermined_at(turned, keep)
            start = self.towards_prior(found, start, keep)
        self.found = found
        if found.held.shape[1]:
            self.hold(found, start)
        return start

    def along_the_turn(self, start: Parameters, keep: np.ndarray) -> Parameters:
        """
        Return the member of a turntable's curve of calibrations the prior prefers.

        On a turntable the start's turn about the tool's axis is arbitrary, and a prior that
        fixes it may lie half a turn away, beyond what linear steps travel
        (``turn_family``). The data and prior cost of every ``TURN_SAMPLE``-th pair at
        ``turn_family.TURN_ANGLES`` turns of the start; off a turntable the turned starts
        no longer fit the data, and the start itself is returned.
        """
        idx = np.flatnonzero(keep)
        idx = idx[::max(1, len(idx) // TURN_SAMPLE)]
        axis = turn_axis(self.pos_a[idx], self.quat_a[idx])
        if axis is None:
            return start
        phis = turn_angles()
        # a SCARA arm or a mobile robot turns about one axis too, but moves off the circle:
        # half a turn no longer fits its data (the lever, ~0.1 m, against mm of noise), and
        # the other turns need not be made nor tried
        data = self.everything.subset(idx)
        half = turned(start, axis, phis[len(phis) // 2])
        if ols_cost(data, half) > 4.0 * ols_cost(data, start) + 10.0 * len(idx):
            return start
        candidates = [turned(start, axis, phi) for phi in phis]
        problem = replace(data, priors=self.priors)  # the same pairs, the prior's terms too
        costs = [ols_cost(problem, p) for p in candidates]
        best = int(np.argmin(costs))
        return start if best == 0 else candidates[best]

    def towards_prior(self, found: Undetermined, start: Parameters,
                      keep: np.ndarray) -> Parameters:
        """
        Move ``start`` along the directions the prior determines to the prior's values.

        An OLS fit of (at most ``OBSERVABILITY_SAMPLE``) pairs with those directions pinned at
        the prior's poses (``hold_prior(..., at=prior)``) and the held ones at the start.
        """
        pinned = Undetermined(np.hstack([found.by_prior, found.held]), found.held[:, :0],
                              found.scale)
        gauge, _ = hold_prior(pinned, start, at=self.prior)
        idx = np.flatnonzero(keep)
        idx = idx[::max(1, len(idx) // OBSERVABILITY_SAMPLE)]
        try:
            return solve_ols(self.everything.subset(idx, gauge_terms(gauge, self.spec)), start,
                             max_iterations=self.settings.max_iterations, xtol=XTOL).params
        except (np.linalg.LinAlgError, ValueError, ConvergenceError):
            return start  # the fit of all pairs starts from what there is

    def hold(self, found: Undetermined, start: Parameters) -> None:
        """Hold ``found``'s undetermined directions at ``start`` in every later fit."""
        prior, self.held_components = hold_prior(found, start)
        self.found = found
        self.gauge = gauge_terms(prior, self.spec) if prior is not None else []
        # the masked OLS refits weigh all pairs: the gauge goes with them
        self.everything = replace(self.everything, priors=list(self.gauge))

    def solve(self, keep: np.ndarray, start: Parameters, warm: bool = False,
              with_priors: bool = True, screened: bool = False,
              inputs: Optional[InputState] = None, fitted: bool = False,
              residuals: bool = True) -> Solution:
        """
        Fit the pairs in ``keep`` from ``start`` (``start()``, or a fit of nearly these pairs).

        OLS, then TLS if asked; a ``warm`` start (a fit of nearly the same pairs) or a
        ``fitted`` one (an OLS fit of a subsample) goes to TLS directly, its inputs starting at
        ``inputs`` (``carried``) if given. A fit to be ``screened`` for outliers may pause
        (``FastPaths.screen``, ``reject_outliers``). ``residuals`` False: a TLS fit leaves its
        residuals to ``with_residuals``.
        """
        settings = self.settings
        n_keep = int(keep.sum())
        min_pairs = max(int(settings.min_pairs), self.spec.n_params // self.spec.n_res + 2)
        if n_keep < min_pairs:
            raise TooFewPairsError(
                f'only {n_keep} pairs are left after rejecting outliers (need at least '
                f'{min_pairs}); record longer, or check the noise (sigma_b) and the units')
        problem = self.problem(keep, with_priors)
        tls = settings.method == 'tls'
        if not (tls and (warm or fitted)):
            sol = solve_ols(problem, start, max_iterations=settings.max_iterations, xtol=XTOL)
            start = sol.params
        if tls:
            # next to the minimum (inputs of nearly the same fit), the first step needs
            # hardly any damping
            pause = 2 if (screened and self.paths.screen and inputs is None
                          and normal_equations.applies(problem)) else None
            sol = solve_tls(problem, start, max_iterations=settings.max_iterations, xtol=XTOL,
                            inputs=inputs, damping=1e-6 if inputs is None else WARM_DAMPING,
                            pause_at=pause, residuals=residuals)
        return sol

    def with_residuals(self, handed: list, keep: np.ndarray) -> Solution:
        """
        Return the fit of the pairs ``keep`` handed over (one-item list) with its residuals.

        A robust refit leaves them out (``refit``): the screening reads its own statistic, and
        a refit that is not the last would have made them for nothing. The fit's resume state
        (its factors, ~200 MB at 2M pairs) goes before they are made; the numbers are those
        the fit would have made (``estimator.tls_residuals``).
        """
        sol = handed.pop()
        if sol.residuals is not None:
            return sol
        x = sol.resume.inputs
        sol = replace(sol, resume=None)
        res_y, res_x = tls_residuals(self.problem(keep, with_priors=False, lazy=True),
                                     sol.params, x)
        return replace(sol, residuals=res_y, input_residuals=res_x)

    def start(self, keep: np.ndarray) -> tuple[Parameters, bool]:
        """
        Closed-form start; for many pairs the OLS fit of a subsample (then True).

        The closed form on every pair costs as much as two passes of the solver, and OLS on
        all pairs only leads TLS to the same minimum. The OLS fit of SUBSAMPLE pairs (every
        k-th, so the whole motion is seen) is within a few σ of the OLS fit of all pairs;
        TLS (or OLS) on all pairs converges from there to the same minimum under the same
        stopping rule. (A TLS fit of the subsample saves no pass: from measured inputs TLS
        needs three linearisations from either start.)

        What the motion does not determine is held at the closed form's value from here on
        (``hold_undetermined``), the subsample's fit included.
        """
        size = SUBSAMPLE_TLS if self.settings.method == 'tls' else SUBSAMPLE
        n = int(keep.sum())
        stride = n // size if self.paths.start else 0
        sub = keep
        if stride >= 2:
            sub = np.zeros(len(keep), dtype=bool)
            sub[np.flatnonzero(keep)[::stride]] = True
        small = self.problem(sub, with_priors=False)
        start = initialize(self.spec, small.pos_a, small.quat_a, small.pos_b, small.quat_b)
        start = self.hold_undetermined(start, keep)
        if stride < 2 and self.found.held.shape[1] and self.paths.start:
            # a restricted rig's closed form (the angle about the axis from a grid, the axis
            # from a sample) is tens of σ from the fit: the OLS fit of a small even sample
            # brings it within a few σ for a fraction of a pass over all pairs
            stride = n // RESTRICTED_SUBSAMPLE
            if stride >= 2:
                sub = np.zeros(len(keep), dtype=bool)
                sub[np.flatnonzero(keep)[::stride]] = True
        if stride < 2:
            return start, False
        small = self.problem(sub, with_priors=False)  # with the gauge, if any
        try:
            start = solve_ols(small, start, max_iterations=self.settings.max_iterations,
                              xtol=XTOL).params
        except (np.linalg.LinAlgError, ValueError, ConvergenceError):
            pass  # the fit of all pairs starts from what there is, and says what is wrong
        return start, True

    def carried(self, sol: Solution, fitted: np.ndarray, keep: np.ndarray
                ) -> Optional[InputState]:
        """Return the inputs of ``sol`` (a fit of ``fitted``) for ``keep`` (paths.refit)."""
        return carried_inputs(sol, self.everything, fitted, keep) if self.paths.refit else None

    def squares(self, params: Parameters) -> np.ndarray:
        """Every pair's normalised squared residual d² at ``params`` (robust statistic)."""
        tls = self.settings.method == 'tls'
        if self.paths.squares and screening.exact_for(self.everything, tls):
            return screening.normalised_squares(self.everything, params, tls)
        return reference_squares(params, self.data)

    def reject_outliers(self, handed: list, max_share: float = MAX_REJECTED_SHARE
                        ) -> tuple[np.ndarray, Solution]:
        """
        Reject pairs far outside the noise, refitting on the rest until the set settles.

        ``handed`` is a one-item list holding the fit of all pairs, emptied here: no frame
        keeps a fit once its refit has what it needs from it (its input state and residuals
        are ~300 MB at 2M pairs; ``refit``).

        A pair is rejected when ``d² > s · χ²_m(1 - OUTLIER_ALPHA)`` with d² its normalised
        squared residual at the current fit (``linearized.reference_squares``) and
        ``s = max(1, q25(d²) / q25(χ²_m))`` (lower quartiles, which outliers up to half the
        pairs do not reach): the stated noise, or the typical scatter of the inliers if that
        is larger (so that early rounds, fitted with the outliers in, keep the inliers, and a
        recording whose noise is understated throughout is judged by the fit verdict, not cut
        down). Rejected pairs are tested again each round. More than ``max_share`` rejected is
        refused (InconsistentDataError). A round that changes nothing ends the loop without
        a refit.

        A paused TLS fit (``estimator.paused``; the first robust fit, ``FastPaths.screen``) is
        screened where its step leads (``estimator.heading``), which after the inputs' first
        move is within ~XTOL σ of its minimum (the 1M-pair steps of ``XTOL``'s comment), and
        goes on from its sums less the removed pairs: the pass that would have proved the fit
        of all pairs converged is not made.
        """
        sol = handed.pop()
        keep = np.ones(len(self.pos_a), dtype=bool)
        # OLS of all pairs weighted 0/1: each fit gives every pair's residuals, hence its d²
        masked = self.paths.refit and weighable(sol, self.everything)
        at = None  # where the last d² was taken
        for _ in range(MAX_ROUNDS):
            if masked:  # OLS residuals of every pair: d² = ‖r‖² (screening, OLS)
                d2 = np.einsum('ij,ij->i', sol.residuals, sol.residuals)
            elif at is None or not at.same_as(sol.params):  # else d² is the last one
                at = heading(sol)
                d2 = self.squares(at)
            new = self._inliers(d2, keep)
            if np.array_equal(new, keep) and not paused(sol):
                break
            self._refuse_if_mostly_outside(~new, max_share)
            handed.append(sol)
            sol = None  # the refit frees the last fit as soon as it can
            sol = self.refit(handed, keep, new, masked)
            keep = new
        if masked:
            # the residuals are stored pair-last (m, N): gather along the contiguous rows
            res = np.take(sol.residuals.T, np.flatnonzero(keep), axis=1).T
            sol = replace(sol, residuals=res)
        return keep, sol

    def _inliers(self, d2: np.ndarray, keep: np.ndarray) -> np.ndarray:
        """Return the pairs within the rejection limit (``reject_outliers``)."""
        m = self.spec.n_res
        limit = float(chi2_isf(OUTLIER_ALPHA, m))
        quartile = float(chi2_ppf(0.25, m))
        # the quartile of a copy (d2 is read again), partitioned in place: one copy, not two
        scale = max(1.0, float(np.quantile(d2[keep], 0.25, overwrite_input=True)) / quartile)
        return d2 <= scale * limit

    def refit(self, handed: list, fitted: np.ndarray, kept: np.ndarray,
              masked: bool) -> Solution:
        """
        Fit the pairs ``kept`` again after ``sol``, a fit of the pairs ``fitted``.

        ``sol`` comes as the one item of ``handed`` (taken out): it is dropped before the
        refit's first pass, so that its inputs and residuals are not held beside the refit's.

        Going on from ``sol`` where it can (``FastPaths.refit``), so that the first step costs
        no pass over all pairs: OLS (``masked``) from its normal equations with the changed pairs
        weighted in or out (``estimator.reweighted``); TLS that only takes pairs out from its
        last linearisation less theirs (``estimator.without_pairs``; a paused fit goes on so).
        Otherwise a warm fit of ``kept``, its inputs from ``sol``.
        """
        settings = self.settings
        sol = handed.pop()
        params = sol.params
        if masked:
            normal = reweighted(sol, self.everything, fitted, kept)
            del sol
            return solve_ols(replace(self.everything, weights=kept.astype(float)), params,
                             max_iterations=settings.max_iterations, xtol=XTOL, normal=normal)
        if self.paths.refit and can_take_out(sol, fitted, kept):
            # the seed handed over: solve_tls alone holds it (its inputs go when spent)
            seed = [without_pairs(sol, self.everything, fitted, kept)]
            del sol
            return solve_tls(self.problem(kept, with_priors=False, lazy=True), params,
                             max_iterations=settings.max_iterations, xtol=XTOL,
                             seed=seed.pop(), residuals=False)
        inputs = self.carried(sol, fitted, kept)
        del sol
        return self.solve(kept, params, warm=True, with_priors=False, inputs=inputs,
                          residuals=False)

    def _refuse_if_mostly_outside(self, outside: np.ndarray, max_share: float) -> None:
        share = float(outside.mean())
        if share > max_share:
            raise InconsistentDataError(
                f'{share:.0%} of the pairs lie far outside the stated noise: the data are '
                f'not the model plus a few outliers{_where(outside, self.stamps)}; check the '
                f'units and the noise (stated: {self.stated}) and run coreg diagnose')


def _stated(cov: np.ndarray) -> str:
    """Say the largest position and rotation σ of a 6×6 noise covariance (ROS layout)."""
    sd = np.sqrt(np.abs(np.diag(np.asarray(cov, dtype=float).reshape(6, 6))))
    return f'{sd[0:3].max():g} m, {sd[3:6].max():g} rad'


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
              max_rejected_share: float = MAX_REJECTED_SHARE,
              paths: FastPaths = FAST) -> CalibrationResult:
    """
    Estimate T0 = T_bbase_abase and T1 = T_atool_bmarker from paired samples.

    Closed-form start (no guess needed), OLS (Ikits B.1) refined by TLS (B.2) when
    ``settings.method == 'tls'``, a priori estimates (B.3), chi-square goodness of fit (B.4.1)
    and posterior covariance (B.4.2) converted to the ROS layout. With ``settings.robust``,
    pairs far outside the noise are rejected and the fit is repeated on the rest.

    Parameters
    ----------
    pairs : Pairs
        Paired samples of A and B.
    settings : Settings
        Model, method, noise (``sigma_a``, ``sigma_b``), iteration limit, minimum pairs,
        robust.
    prior : Prior, optional
        Prior knowledge of the parameters, added to the fit.
    cov_a, cov_b : ndarray, shape (6, 6), optional
        Full noise covariances (ROS layout) overriding the settings' (``Settings.cov_a``:
        ``noise_a`` if given, else ``sigma_a``).
    start : Parameters, optional
        A starting φ instead of the closed form.
    warm : bool
        ``start`` is a fit of nearly the same pairs (e.g. at a nearby time offset): TLS starts
        from it without an OLS pass.
    max_rejected_share : float
        Largest share of rejected pairs before the data are refused (1 never refuses, e.g.
        while comparing candidate time offsets).
    paths : FastPaths
        The fast paths taken (all by default; ``PLAIN`` none, to compare with).

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
    cov_a = settings.cov_a if cov_a is None else cov_a
    cov_b = settings.cov_b if cov_b is None else cov_b
    fitter = _Fitter(pairs, spec, settings, prior, cov_a, cov_b, paths)
    cov_a6 = np.asarray(cov_a, dtype=float).reshape(6, 6)
    refuse_if_nothing_moved(fitter.pos_a, fitter.quat_a,
                            np.sqrt(np.max(np.diag(cov_a6).reshape(2, 3), axis=1)))
    keep = np.ones(len(pairs), dtype=bool)
    # outliers are a property of the data: they are found without the prior, which is then
    # tested against the data (verdict.prior_check) instead of pulling pairs out of the fit
    with_priors = not (settings.robust and prior is not None)
    try:
        # start (closed form, or OLS of a subsample), what the motion does not determine held
        fitted = False
        if start is None:
            start, fitted = fitter.start(keep)
        else:
            start = fitter.hold_undetermined(start, keep)
        # fit all pairs: OLS (B.1), TLS (B.2)
        sol = fitter.solve(keep, start, warm and not fitted, with_priors,
                           screened=settings.robust, fitted=fitted)
        for _ in range(HOLD_ROUNDS):
            if settings.robust:
                # reject the pairs far outside the noise, refit the rest (from the last fit)
                handed, sol = [sol], None  # reject_outliers frees it when it can
                keep, sol = fitter.reject_outliers(handed, max_rejected_share)
                if prior is not None:  # the prior (B.3) joins the fit of the inliers
                    sol = fitter.solve(keep, sol.params, warm=True,
                                       inputs=fitter.carried(sol, keep, keep))
            # held what the data leave undetermined at the solution, and nothing else? else
            # hold that and fit all pairs again (the robust rejection starts from all pairs)
            found = fitter.undetermined_at(sol.params, keep)
            if found.same_held(fitter.found):
                fitter.found = replace(fitter.found, by_prior=found.by_prior)  # at the solution
                break
            fitter.hold(found, start)
            every = np.ones(len(pairs), dtype=bool)
            sol = fitter.solve(every, sol.params, warm=True, with_priors=with_priors,
                               screened=settings.robust,
                               inputs=fitter.carried(sol, keep, every))
            keep = every
    except np.linalg.LinAlgError as e:  # e.g. positions of 1e300 m: SVD does not converge
        raise ConvergenceError(
            f'the numbers do not allow a solution ({e}); check the data for absurd values '
            f'(units, a corrupt sample) with coreg diagnose') from e
    handed, sol = [sol], None
    sol = fitter.with_residuals(handed, keep)
    # the verdict's numbers: chi-square (B.4.1), posterior covariance (B.4.2) in ROS layout
    result = _result(sol, spec, settings, len(pairs), fitter.found)
    return replace(result, inliers=keep,
                   rejected_stamps=np.asarray(pairs.stamps, dtype=np.int64)[~keep],
                   unobservable=observability.report(fitter.found, sol.params,
                                                     fitter.held_components, prior))


def _result(sol: Solution, spec: ModelSpec, settings: Settings, n: int,
            found: Undetermined) -> CalibrationResult:
    t0, t1, joint, determined = result_covariances(sol.params, sol.cov, found.held)
    dof = sol.n_rows - spec.n_params
    p_value = float(chi2_sf(sol.chi2, dof)) if dof > 0 else float('nan')
    message = sol.message if sol.cov is not None else (
        sol.message + '; the covariance is singular (see observability)')
    return CalibrationResult(
        success=sol.status > 0 and sol.cov is not None, status=sol.status, message=message,
        model=spec.name, method=settings.method, n_pairs=n, base_to_base=t0, tool_to_marker=t1,
        markers=sol.params.markers.copy(), params=sol.params.phi.copy(), param_cov=sol.cov,
        chi2=float(sol.chi2), dof=int(dof), p_value=p_value, residuals=sol.residuals,
        iterations=sol.iterations, cov_joint=joint, input_residuals=sol.input_residuals,
        charts=tuple(sol.params.charts), cov_determined=determined)
