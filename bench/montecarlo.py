"""
Monte Carlo evidence for the estimators: bias, efficiency, covariance consistency, chi-square.

Every scenario keeps the truth and the motion fixed (one seed) and redraws only the device
noise, trial by trial (``simulate_pairs`` with synchronised pairs). Each trial calibrates with
the public ``calibrate`` (OLS and/or TLS) and records the ROS-layout error of the estimate,
``e = (p0_true - p0, log(q0_true ⊗ q0*), p1_true - p1, log(q1_true ⊗ q1*))``, with the
reported joint covariance ``cov_joint`` and the chi-square p-value. The checks:

- bias: Hotelling's T² of the mean error (exact F reference with the sample covariance) and
  the Bonferroni-corrected largest |mean|/standard error;
- efficiency: MSE against the Cramér-Rao bound of the errors-in-variables model at the true
  parameters and noise-free inputs (``core.planning.crlb``), as trace(MSE)/trace(CRLB) and
  whitened as the mean of the per-component ratios MSE_jj/CRLB_jj;
- consistency: mean NEES ``eᵀ C⁻¹ e`` against the dimension d, and the share of trials inside
  the 95 % ellipsoid;
- chi-square calibration: Kolmogorov-Smirnov test of the p-values against U(0, 1).

Tolerances: the full-size targets (5 % of d for the mean NEES, 93-97 % coverage, efficiency in
[0.95, 1.05]) widened, where the trials are fewer, to 3.29 standard errors of the sampling
spread (two-sided 0.1 %), computed from the chi-square / binomial laws or from the trials.

Run alone: ``python bench/montecarlo.py [--scale 1] [--workers N] [--scheduler ADDRESS]
[--json out.json]`` (``coreg_ros.parallel``: local processes or a Dask cluster; every trial is
seeded on its own, so the numbers do not depend on either).
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, replace
import json
import sys
import time
from typing import Optional

from coreg_ros.cli.argtypes import add_parallel_arguments
from coreg_ros.core import quaternion as quat
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.estimator import noise_covariance
from coreg_ros.core.planning.crlb import cramer_rao_bound
from coreg_ros.core.settings import Settings
from coreg_ros.parallel import CaseFailure, failures, run_cases
from coreg_ros.sim import make_motion, random_truth, simulate_pairs
import numpy as np
from scipy import stats

#: Two-sided 0.1 % normal quantile: sampling tolerances are this many standard errors.
Z_TOL = float(stats.norm.isf(0.0005))
#: Significance level of the "unbiased" tests (false alarm rate of a correct estimator).
ALPHA_UNBIASED = 1e-3
#: An estimator is shown biased when Hotelling's p is below this and ...
ALPHA_BIASED = 1e-6
#: ... its largest |mean error| is at least this many standard errors.
MIN_BIAS_SE = 5.0
#: Pass level of the KS test of the chi-square p-values.
ALPHA_KS = 0.01
#: A trial's reported covariance may differ from the CRLB by at most this factor (eigenvalues).
COV_FACTOR = 1.5
COMPONENTS = ('p0x', 'p0y', 'p0z', 'th0x', 'th0y', 'th0z',
              'p1x', 'p1y', 'p1z', 'th1x', 'th1y', 'th1z')


@dataclass(frozen=True)
class Scenario:
    """
    One Monte Carlo configuration: fixed truth and motion, noise redrawn per trial.

    Attributes
    ----------
    name : str
    model : str
        ``full_pose`` or ``position_only``.
    n_pairs : int
        Synchronised pairs per trial.
    n_trials : int
        Trials at full size (scaled by ``scale`` in ``run_scenario``).
    sigma_a, sigma_b : tuple of float
        Noise (position m, rotation rad) of A and B, simulated and assumed by the estimator.
    lever : float, optional
        Length of the tool-to-marker offset p1, m (direction from the drawn truth).
    methods : tuple of str
        Estimators to run.
    expect : dict
        Per method, the claims to check: any of ``unbiased``, ``biased``, ``efficient``,
        ``consistent``, ``chi2``.
    seed : int
        Seed of the truth and motion.

    """

    name: str
    model: str = 'full_pose'
    n_pairs: int = 500
    n_trials: int = 2000
    sigma_a: tuple = (2e-4, 5e-4)
    sigma_b: tuple = (5e-4, 2e-3)
    lever: Optional[float] = None
    methods: tuple = ('ols', 'tls')
    expect: tuple = ()
    seed: int = 2000
    note: str = ''

    def expected(self, method: str) -> tuple:
        """Claims to check for ``method``."""
        return dict(self.expect).get(method, ())


ALL_CLAIMS = ('unbiased', 'efficient', 'consistent', 'chi2')

#: The scenarios of the benchmark and of test/test_montecarlo.py.
SCENARIOS = (
    Scenario('output_noise_only', sigma_a=(1e-9, 1e-9), n_trials=3000,
             expect=(('ols', ALL_CLAIMS), ('tls', ALL_CLAIMS)),
             note='A noise-free (1e-9): OLS is the ML estimator, TLS must agree'),
    Scenario('both_noisy_default', methods=('tls',), n_trials=3000,
             expect=(('tls', ALL_CLAIMS),),
             note='default device noise on A and B (product settings)'),
    Scenario('input_noise_long_lever', sigma_a=(1e-3, 0.05), sigma_b=(1e-3, 0.05), lever=0.5,
             n_trials=1000, expect=(('ols', ('biased',)), ('tls', ALL_CLAIMS)),
             note='A rotation noise 50 mrad on a 0.5 m lever: OLS shrinks p1 by ~σ²'),
    Scenario('position_only_default', model='position_only', methods=('tls',), n_trials=1000,
             expect=(('tls', ALL_CLAIMS),),
             note='B gives positions only (9 parameters)'),
)


# ----------------------------------------------------------------------------------------------
# Setup and trials
# ----------------------------------------------------------------------------------------------

def setup(scenario: Scenario):
    """Return the fixed truth, motion and noise-free pairs of a scenario (truth, motion, clean)."""
    rng = np.random.default_rng(scenario.seed)
    truth = random_truth(rng, scenario.model)
    motion = make_motion(rng)
    if scenario.lever is not None:
        p1 = truth.p1 / np.linalg.norm(truth.p1) * scenario.lever
        truth = replace(truth, p1=p1, markers=p1[None, :])
    _, clean, truth = simulate_pairs(np.random.default_rng(0), scenario.n_pairs, scenario.model,
                                     sigma_a=scenario.sigma_a, sigma_b=scenario.sigma_b,
                                     truth=truth, motion=motion)
    return truth, motion, clean


def dimension(model: str) -> int:
    """Dimension of the pose error: 12 (full pose) or 9 (q1 not estimated)."""
    return 12 if model == 'full_pose' else 9


def pose_error(result, truth) -> np.ndarray:
    """ROS-layout error (true minus estimate, δθ with R_true = Exp(δθ) R_est), shape (d,)."""
    t0, t1 = result.base_to_base, result.tool_to_marker
    e = [truth.p0 - t0.position,
         quat.log(quat.multiply(truth.q0, quat.conjugate(t0.quat_wxyz))),
         truth.p1 - t1.position]
    if result.model == 'full_pose':
        e.append(quat.log(quat.multiply(truth.q1, quat.conjugate(t1.quat_wxyz))))
    return np.concatenate(e)


def one_trial(k: int, scenario: Scenario, truth, motion) -> dict:
    """
    Trial ``k``: fresh noise from ``default_rng([seed, k])``, calibrated by every method.

    Returns
    -------
    dict of method -> dict with ``errors`` (d,), ``covs`` (d, d), ``chi2``, ``dof``,
    ``p_value``, ``iterations``, ``success``.

    """
    d = dimension(scenario.model)
    rng = np.random.default_rng([scenario.seed, int(k)])
    noisy, _, _ = simulate_pairs(rng, scenario.n_pairs, scenario.model,
                                 sigma_a=scenario.sigma_a, sigma_b=scenario.sigma_b,
                                 truth=truth, motion=motion)
    out = {}
    for method in scenario.methods:
        # the estimator's own statistics: plain least squares (the robust layer's
        # false-rejection rate and NEES are checked in test/test_spatiotemporal.py)
        settings = Settings(model=scenario.model, method=method, sigma_a=scenario.sigma_a,
                            sigma_b=scenario.sigma_b, robust=False)
        r = calibrate(noisy, settings)
        out[method] = {'errors': pose_error(r, truth),
                       'covs': (np.full((d, d), np.nan) if r.cov_joint is None
                                else r.cov_joint[:d, :d]),
                       'chi2': r.chi2, 'dof': r.dof, 'p_value': r.p_value,
                       'iterations': r.iterations, 'success': r.success}
    return out


def run_trials(scenario: Scenario, n_trials: int, workers: int = 1,
               scheduler: Optional[str] = None) -> dict:
    """
    Calibrate ``n_trials`` noisy copies of the scenario (``coreg_ros.parallel.run_cases``).

    Trial k draws its noise from ``default_rng([seed, k])``, so the outcome does not depend on
    ``workers`` or ``scheduler``. A trial that raises is left out of the arrays and listed
    under ``failed`` (index, seed, error).

    Returns
    -------
    dict of method -> dict with ``errors`` (K, d), ``covs`` (K, d, d), ``chi2``, ``dof``,
    ``p_value``, ``iterations``, ``success`` (K,); and ``failed``: list of dict.

    """
    truth, motion, _ = setup(scenario)
    # trials take ~10-50 ms: ~8 chunks per worker keep the pickling overhead small
    chunk = max(1, n_trials // (8 * max(1, workers)))
    results = run_cases(one_trial, range(n_trials), args=(scenario, truth, motion),
                        workers=workers, scheduler=scheduler, chunksize=chunk,
                        label=lambda k: f'{scenario.name} trial {k} (seed [{scenario.seed}, '
                                        f'{k}])', title=scenario.name)
    ok = [r for r in results if not isinstance(r, CaseFailure)]
    data = {m: {key: np.asarray([r[m][key] for r in ok]) for key in TRIAL_KEYS}
            for m in scenario.methods}
    data['failed'] = [f.as_dict() for f in failures(results)]
    return data


#: What one trial records per method.
TRIAL_KEYS = ('errors', 'covs', 'chi2', 'dof', 'p_value', 'iterations', 'success')


# ----------------------------------------------------------------------------------------------
# Statistics
# ----------------------------------------------------------------------------------------------

def bias_test(errors: np.ndarray) -> dict:
    """
    Is the mean error zero? Hotelling's T² and the Bonferroni-corrected largest z.

    Returns ``hotelling_p`` (exact under Gaussian errors: ``(K-d)/(d(K-1)) T² ~ F(d, K-d)``),
    ``bonferroni_p``, ``max_z`` (largest |mean|/standard error), ``z`` per component.
    """
    K, d = errors.shape
    mean = errors.mean(axis=0)
    cov = np.cov(errors, rowvar=False)
    t2 = float(K * mean @ np.linalg.solve(cov, mean))
    f = (K - d) / (d * (K - 1)) * t2
    z = mean / np.sqrt(np.diag(cov) / K)
    max_z = float(np.max(np.abs(z)))
    return {'hotelling_t2': t2, 'hotelling_p': float(stats.f.sf(f, d, K - d)),
            'bonferroni_p': float(min(1.0, d * 2.0 * stats.norm.sf(max_z))), 'max_z': max_z,
            'z': z.tolist()}


def efficiency(errors: np.ndarray, crlb: np.ndarray) -> dict:
    """
    MSE against the CRLB: trace ratio and whitened ratio, each with its sampling standard error.

    ``trace_ratio = tr(MSE)/tr(CRLB)``; ``whitened_ratio = mean_j MSE_jj / CRLB_jj``; the
    standard errors are those of a mean over the trials (``std/√K``).
    """
    K = len(errors)
    sq = errors ** 2
    per_trial_trace = sq.sum(axis=1) / np.trace(crlb)
    per_trial_white = (sq / np.diag(crlb)).mean(axis=1)
    ratios = sq.mean(axis=0) / np.diag(crlb)
    return {'trace_ratio': float(per_trial_trace.mean()),
            'trace_ratio_se': float(per_trial_trace.std(ddof=1) / np.sqrt(K)),
            'whitened_ratio': float(per_trial_white.mean()),
            'whitened_ratio_se': float(per_trial_white.std(ddof=1) / np.sqrt(K)),
            'component_ratios': ratios.tolist()}


def nees(errors: np.ndarray, covs: np.ndarray) -> dict:
    """Mean NEES and 95 % ellipsoid coverage of the reported covariances."""
    K, d = errors.shape
    ok = np.isfinite(covs).reshape(K, -1).all(axis=1)
    values = np.full(K, np.inf)
    values[ok] = np.einsum('ki,ki->k', errors[ok], np.linalg.solve(covs[ok],
                                                                   errors[ok][..., None])[..., 0])
    return {'mean_nees': float(np.mean(values)), 'dim': d,
            'coverage95': float(np.mean(values <= stats.chi2.ppf(0.95, d))),
            'n_missing_cov': int(K - ok.sum())}


def collapsed_covariances(covs: np.ndarray, crlb: np.ndarray) -> dict:
    """
    Trials whose reported covariance is off the CRLB by more than a factor COV_FACTOR.

    At these sample sizes the covariance at the estimate is within a few per cent of the bound
    at the truth, so a trial far off it reports a wrong covariance (e.g. a damped one).
    Compared by the largest generalised eigenvalue of (C_k, CRLB) and its inverse.
    """
    K = len(covs)
    off = np.zeros(K, dtype=bool)
    L = np.linalg.cholesky(crlb)
    for k in range(K):
        if not np.isfinite(covs[k]).all():
            off[k] = True
            continue
        M = np.linalg.solve(L, np.linalg.solve(L, covs[k]).T)
        ev = np.linalg.eigvalsh(0.5 * (M + M.T))
        off[k] = ev[0] <= 0 or max(ev[-1], 1.0 / ev[0]) > COV_FACTOR
    return {'n_off': int(off.sum()), 'trials': np.flatnonzero(off).tolist()}


def chi2_calibration(p_values: np.ndarray) -> dict:
    """KS test of the chi-square p-values against U(0, 1)."""
    ks = stats.kstest(p_values, 'uniform')
    return {'ks_stat': float(ks.statistic), 'ks_p': float(ks.pvalue),
            'p_value_mean': float(np.mean(p_values))}


def tolerances(K: int, d: int) -> dict:
    """
    Return acceptance half-widths for K trials: full-size target or 3.29 sampling standard errors.

    Mean NEES of a χ²_d variable has standard error √(2d/K); coverage of a 95 % region has
    √(0.95·0.05/K).
    """
    return {'nees': max(0.05 * d, Z_TOL * np.sqrt(2.0 * d / K)),
            'coverage': max(0.02, Z_TOL * np.sqrt(0.95 * 0.05 / K))}


def _check(name: str, value: float, lo: float, hi: float) -> dict:
    return {'check': name, 'value': float(value), 'lo': float(lo), 'hi': float(hi),
            'passed': bool(lo <= value <= hi)}


def evaluate(scenario: Scenario, data: dict, crlb: np.ndarray) -> dict:
    """Statistics and pass/fail checks of one scenario's trials, per method."""
    out = {}
    for method, o in data.items():
        if method == 'failed':
            continue
        errors, covs = o['errors'], o['covs']
        K, d = errors.shape
        tol = tolerances(K, d)
        mean_cov = np.nanmean(covs, axis=0)
        stat = {'n_trials': K, 'n_success': int(o['success'].sum()),
                'iterations_mean': float(o['iterations'].mean()),
                'bias': bias_test(errors), 'efficiency': efficiency(errors, crlb),
                'nees': nees(errors, covs), 'chi2': chi2_calibration(o['p_value']),
                'reported_vs_crlb_trace': float(np.trace(mean_cov) / np.trace(crlb)),
                'reported_vs_crlb_whitened': float(np.mean(np.diag(mean_cov) / np.diag(crlb))),
                'collapsed_cov': collapsed_covariances(covs, crlb),
                'rmse': np.sqrt((errors ** 2).mean(axis=0)).tolist(),
                'crlb_sd': np.sqrt(np.diag(crlb)).tolist()}
        checks = [_check('all trials converged', stat['n_success'], K, K)]
        claims = scenario.expected(method)
        b = stat['bias']
        if 'unbiased' in claims:
            checks.append(_check('bias: Hotelling p', b['hotelling_p'], ALPHA_UNBIASED, 1.0))
            checks.append(_check('bias: Bonferroni p', b['bonferroni_p'], ALPHA_UNBIASED, 1.0))
        if 'biased' in claims:
            checks.append(_check('bias shown: Hotelling p', b['hotelling_p'], 0.0, ALPHA_BIASED))
            checks.append(_check('bias shown: max |mean|/se', b['max_z'], MIN_BIAS_SE, np.inf))
        if 'efficient' in claims:
            e = stat['efficiency']
            for key in ('trace_ratio', 'whitened_ratio'):
                w = max(0.05, Z_TOL * e[key + '_se'])
                checks.append(_check(f'efficiency: {key.replace("_", " ")}', e[key],
                                     1.0 - w, 1.0 + w))
        if 'consistent' in claims:
            n = stat['nees']
            checks.append(_check(f'NEES mean (d={d})', n['mean_nees'], d - tol['nees'],
                                 d + tol['nees']))
            checks.append(_check('95% coverage', n['coverage95'], 0.95 - tol['coverage'],
                                 0.95 + tol['coverage']))
            cc = stat['collapsed_cov']
            checks.append(_check(f'trials whose covariance is off the CRLB by > x{COV_FACTOR:g}',
                                 cc['n_off'], 0, 0))
            ok = np.ones(K, dtype=bool)
            ok[cc['trials']] = False
            stat['nees_on_crlb_trials'] = nees(errors[ok], covs[ok])
        if 'chi2' in claims:
            checks.append(_check('chi2 p-values ~ U(0,1): KS p', stat['chi2']['ks_p'], ALPHA_KS,
                                 1.0))
        stat['checks'] = checks
        stat['passed'] = all(c['passed'] for c in checks)
        out[method] = stat
    return out


def scenario_crlb(scenario: Scenario) -> np.ndarray:
    """CRLB (ROS tangent at the truth) for the scenario's noise-free inputs."""
    truth, _, clean = setup(scenario)
    crlb, _ = cramer_rao_bound(scenario.model, truth.p0, truth.q0, truth.markers, clean.pos_a,
                               clean.quat_a, noise_covariance(scenario.sigma_a),
                               noise_covariance(scenario.sigma_b))
    return crlb


def run_scenario(scenario: Scenario, scale: float = 1.0, workers: int = 1,
                 n_trials: Optional[int] = None, scheduler: Optional[str] = None) -> dict:
    """
    Trials, CRLB and checks of one scenario; ``n_trials`` defaults to its size × scale.

    Trials that raised are listed under ``failed_trials`` and fail the scenario.
    """
    K = int(n_trials or max(50, round(scenario.n_trials * scale)))
    t0 = time.perf_counter()
    data = run_trials(scenario, K, workers, scheduler)
    failed = data.pop('failed')
    report = {'scenario': asdict(scenario), 'n_trials': K,
              'methods': evaluate(scenario, data, scenario_crlb(scenario)),
              'failed_trials': failed, 'seconds': time.perf_counter() - t0}
    report['passed'] = not failed and all(m['passed'] for m in report['methods'].values())
    return report


def run_all(scale: float = 1.0, workers: int = 1, scenarios=SCENARIOS, log=None,
            scheduler: Optional[str] = None) -> list:
    """Run every scenario; ``log(str)`` is called after each (and per failed trial)."""
    reports = []
    for s in scenarios:
        r = run_scenario(s, scale, workers, scheduler=scheduler)
        for f in r['failed_trials'] if log is not None else ():
            log(f'{f["label"]}: {f["error"]}')
        reports.append(r)
        if log is not None:
            log(f'{s.name}: {r["n_trials"]} trials in {r["seconds"]:.1f} s, '
                f'{"passed" if r["passed"] else "FAILED"}')
    return reports


# ----------------------------------------------------------------------------------------------
# Tables
# ----------------------------------------------------------------------------------------------

def summary_rows(reports: list) -> list:
    """One row per (scenario, method) with the headline numbers."""
    rows = []
    for r in reports:
        for method, m in r['methods'].items():
            rows.append({
                'scenario': r['scenario']['name'], 'method': method.upper(),
                'N': r['scenario']['n_pairs'], 'trials': r['n_trials'],
                'hotelling_p': m['bias']['hotelling_p'], 'max_z': m['bias']['max_z'],
                'mse_crlb_trace': m['efficiency']['trace_ratio'],
                'mse_crlb_white': m['efficiency']['whitened_ratio'],
                'nees': m['nees']['mean_nees'], 'dim': m['nees']['dim'],
                'coverage95': m['nees']['coverage95'], 'ks_p': m['chi2']['ks_p'],
                'passed': m['passed'],
                'failed': [c['check'] for c in m['checks'] if not c['passed']]})
    return rows


def markdown_table(reports: list) -> str:
    """Markdown table of the Monte Carlo results."""
    head = ('| scenario | est. | N | trials | Hotelling p | max abs(z) | MSE/CRLB (trace) '
            '| MSE/CRLB (whitened) | mean NEES (d) | 95 % coverage | χ² KS p | checks |')
    lines = [head, '|' + '---|' * 12]
    for row in summary_rows(reports):
        verdict = 'pass' if row['passed'] else 'FAIL: ' + '; '.join(row['failed'])
        lines.append(
            f'| {row["scenario"]} | {row["method"]} | {row["N"]} | {row["trials"]} '
            f'| {_p(row["hotelling_p"])} | {row["max_z"]:.1f} | {row["mse_crlb_trace"]:.3f} '
            f'| {row["mse_crlb_white"]:.3f} | {row["nees"]:.2f} ({row["dim"]}) '
            f'| {100 * row["coverage95"]:.1f} % | {_p(row["ks_p"])} | {verdict} |')
    return '\n'.join(lines)


def _p(p: float) -> str:
    return f'{p:.3f}' if p >= 1e-3 else f'{p:.1e}'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--scale', type=float, default=1.0, help='trials × this factor')
    add_parallel_arguments(parser)
    parser.add_argument('--json', help='write the reports here')
    args = parser.parse_args(argv)
    reports = run_all(args.scale, args.workers, log=lambda s: print(s, file=sys.stderr),
                      scheduler=args.scheduler)
    print(markdown_table(reports))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(reports, f, indent=1, default=float)
    return 0 if all(r['passed'] for r in reports) else 1


if __name__ == '__main__':
    sys.exit(main())
