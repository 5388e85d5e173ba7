"""
The whole ``calibrate()`` at 100k and 1M pairs: what users call, beside the solver alone and scipy.

For each N and noise (``realistic``: 0.5° rotation noise on A; ``bench``: the default noise of
``estimator_bench``), full-pose pairs with the fixed truth and motion of ``estimator_bench``:

- ``calibrate`` with OLS and with TLS, best of ``repeats`` (robust rejection on, as users run
  it), and its tracemalloc peak per pair;
- the solvers alone on the whitened problem (``solve_ols`` from the closed form, ``solve_tls``
  from the OLS fit), as ``estimator_bench`` times them;
- scipy (``least_squares`` 'lm' for OLS, 'trf' with the sparse TLS Jacobian) on the same
  problem, in a child process abandoned after ``scipy_cap`` seconds (then reported as capped);
- ``calibrate`` at ``before_commit`` (the code before this work, a git worktree under /tmp)
  and at this tree, both in child processes on the same pairs, their repeats alternating:
  the before/after ratio of the same run (``× before``).

Goals (issue 15): TLS < 2 s and OLS < 1 s at 1M pairs on the project's 2-core machine, BLAS
pinned to one thread (as ``bench/run.py``). Run alone: ``python bench/calibrate_speed_bench.py``
prints the table and writes bench/results/calibrate_speed_bench.json.
"""

import argparse
import json
import os
from pathlib import Path
import pickle
import subprocess
import sys
import tempfile
from typing import Optional

# Before numpy is imported (the standard library above does not load BLAS).
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import estimator_bench as eb  # noqa: E402
from coreg_ros.core.calibration.calibrate import calibrate  # noqa: E402
from coreg_ros.core.calibration.initialize import initialize  # noqa: E402
from coreg_ros.core.estimator import (  # noqa: E402
    noise_covariance,
    Problem,
    solve_ols,
    solve_tls,
    whitening,
)
from coreg_ros.core.models import SPECS  # noqa: E402
from coreg_ros.core.settings import Settings  # noqa: E402
from coreg_ros.sim import make_motion, random_truth, simulate_pairs  # noqa: E402
import numpy as np  # noqa: E402

RESULTS = ROOT / 'bench' / 'results'
#: Goals at 1M pairs, seconds of the whole calibrate().
GOALS = {'tls_seconds_1m': 2.0, 'ols_seconds_1m': 1.0}
#: (σ_A, σ_B) as (position m, rotation rad).
NOISE = {
    'realistic': ((2e-4, float(np.radians(0.5))), (5e-4, 2e-3)),
    'bench': (eb.SIGMA_A, eb.SIGMA_B),
}
#: The commit before this work (issue 15, part 2): its calibrate() is the "before" figure.
BEFORE_COMMIT = '99cffb1'

_BEFORE_SCRIPT = r"""
import os, sys, time, pickle, json
for v in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[v] = '1'
sys.path.insert(0, sys.argv[1])
try:
    from coreg_ros.core.calibration.calibrate import calibrate
except ModuleNotFoundError:  # a tree from before the house's second level
    from coreg_ros.core.calibrate import calibrate
pairs, settings = pickle.load(open(sys.argv[2], 'rb'))
best = float('inf')
for _ in range(int(sys.argv[3])):
    t = time.perf_counter()
    r = calibrate(pairs, settings)
    best = min(best, time.perf_counter() - t)
print(json.dumps({'seconds': best, 'iterations': int(r.iterations),
                  'rejected': int((~r.inliers).sum()), 'params': [float(v) for v in r.params]}))
"""


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def make_pairs(n: int, noise: str, model: str = 'full_pose', seed: int = eb.SEED):
    """Noisy pairs with the truth and motion of ``estimator_bench`` (fixed for every n)."""
    sigma_a, sigma_b = NOISE[noise]
    rng = np.random.default_rng(seed)
    truth = random_truth(rng, model)
    motion = make_motion(rng)
    noisy, _, _ = simulate_pairs(np.random.default_rng([seed, n]), n, model, sigma_a=sigma_a,
                                 sigma_b=sigma_b, truth=truth, motion=motion)
    return noisy


def _problem(pairs, noise: str, model: str = 'full_pose') -> Problem:
    """Build the whitened problem ``calibrate`` builds (for the solver-only and scipy figures)."""
    sigma_a, sigma_b = NOISE[noise]
    spec = SPECS[model]
    qb = None if pairs.quat_b is None else np.asarray(pairs.quat_b, float)
    return Problem(spec, np.asarray(pairs.pos_a, float), np.asarray(pairs.quat_a, float),
                   np.asarray(pairs.pos_b, float), qb,
                   whitening(noise_covariance(sigma_b), spec, 'b'),
                   whitening(noise_covariance(sigma_a), None, 'a'))


def before_worktree(commit: str) -> Path:
    """Return a detached git worktree of ``commit`` under /tmp (made once, reused)."""
    path = Path(tempfile.gettempdir()) / f'coreg_before_{commit}'
    if not (path / 'coreg_ros').is_dir():
        subprocess.run(['git', '-C', str(ROOT), 'worktree', 'add', '--detach', str(path),
                        commit], check=True, capture_output=True)
    return path


def _child(tree: Path, path: str, cap: float) -> dict:
    """One timed ``calibrate`` of the code in ``tree`` on the pickled pairs, in a child process."""
    try:
        out = subprocess.run([sys.executable, '-c', _BEFORE_SCRIPT, str(tree), path, '1'],
                             capture_output=True, text=True, timeout=cap)
    except subprocess.TimeoutExpired:
        return {'status': f'skipped (> {cap:.0f} s cap)'}
    if out.returncode != 0:
        return {'status': f'failed: {out.stderr.strip().splitlines()[-1:]}'}
    return {'status': 'ok', **json.loads(out.stdout.strip().splitlines()[-1])}


def time_before(pairs, settings: Settings, commit: str, repeats: int, cap: float) -> tuple:
    """
    Best times of ``calibrate`` at ``commit`` and at this tree, on the same pairs.

    Both run in child processes of the same kind, their repeats alternating, so that neither
    gains from a warm heap or from a quieter moment of the machine.

    Returns
    -------
    before, now : dict
        ``seconds`` (best), ``iterations``, ``rejected``, ``params``, ``status``.

    """
    trees = {'before': before_worktree(commit), 'now': ROOT}
    with tempfile.NamedTemporaryFile(suffix='.pkl', delete=False) as f:
        pickle.dump((pairs, settings), f)
        path = f.name
    best = {}
    try:
        for _ in range(repeats):
            for key, tree in trees.items():
                run = _child(tree, path, cap)
                if run['status'] != 'ok':
                    best[key] = run
                elif best.get(key, {}).get('seconds', float('inf')) > run['seconds']:
                    best[key] = run
    finally:
        Path(path).unlink(missing_ok=True)
    return best['before'], best['now']


def _scipy(problem: Problem, method: str, start, cap: float) -> dict:
    """Scipy's time on the same problem (``estimator_bench``'s formulations), capped."""
    if method == 'ols':
        def job():
            t, (_, res) = eb.best_time(lambda: eb.scipy_ols(problem, start), 1)
            return t, int(res.nfev)
    else:
        def job():
            tls = eb.ScipyTLS(problem, start)
            t, (_, res) = eb.best_time(tls.solve, 1)
            return t, int(res.nfev)
    out, reason = eb.run_capped(job, cap)
    if out is None:
        return {'seconds': None, 'status': reason}
    return {'seconds': out[0], 'nfev': out[1], 'status': 'ok'}


def bench_case(n: int, noise: str, repeats: int = 3, scipy_cap: float = 120.0,
               before_commit: Optional[str] = BEFORE_COMMIT, with_scipy: bool = True) -> dict:
    """Every figure for one N and noise; rows keyed by method."""
    pairs = make_pairs(n, noise)
    sigma_a, sigma_b = NOISE[noise]
    problem = _problem(pairs, noise)
    start = initialize(problem.spec, problem.pos_a, problem.quat_a, problem.pos_b,
                       problem.quat_b)
    rows = {}
    ols_fit = None
    for method in ('ols', 'tls'):
        settings = Settings(sigma_a=sigma_a, sigma_b=sigma_b, method=method)

        def whole(settings=settings):
            return calibrate(pairs, settings)

        seconds, result = eb.best_time(whole, repeats)
        peak = eb.peak_bytes(whole)
        if method == 'ols':
            solver_s, ols_fit = eb.best_time(lambda: solve_ols(problem, start), repeats)
            sol = ols_fit
        else:
            tls_start = ols_fit.params
            solver_s, sol = eb.best_time(lambda s=tls_start: solve_tls(problem, s), repeats)
        row = {'n': n, 'noise': noise, 'method': method, 'calibrate_seconds': seconds,
               'calibrate_us_per_pair': 1e6 * seconds / n,
               'iterations': int(result.iterations), 'rejected': int((~result.inliers).sum()),
               'peak_bytes_per_pair': peak / n, 'solver_seconds': solver_s,
               'solver_iterations': int(sol.iterations)}
        log(f'  {noise} {method.upper()} N={n}: calibrate {seconds:.3f} s '
            f'(solver alone {solver_s:.3f} s), {peak / n:.0f} B/pair')
        if before_commit:
            before, now = time_before(pairs, settings, before_commit, repeats,
                                      cap=max(600.0, 60 * seconds))
            row['before'], row['now_in_child'] = before, now
            if before.get('seconds') and now.get('seconds'):
                row['speedup_vs_before'] = before['seconds'] / now['seconds']
                sd = np.sqrt(np.diag(result.param_cov))
                row['max_diff_vs_before_sigma'] = float(
                    np.max(np.abs(np.asarray(before['params']) - result.params) / sd))
            log(f'  {noise} {method.upper()} N={n}: before ({before_commit}) '
                f'{before.get("seconds", float("nan")):.3f} s {before["status"]}')
        if with_scipy:
            scipy_start = start if method == 'ols' else ols_fit.params
            row['scipy'] = _scipy(problem, method, scipy_start, scipy_cap)
            if row['scipy']['seconds']:
                row['speedup_vs_scipy'] = row['scipy']['seconds'] / seconds
            log(f'  {noise} {method.upper()} N={n}: scipy {row["scipy"]["status"]} '
                f'{row["scipy"]["seconds"] or float("nan"):.3f} s')
        rows[method] = row
    return rows


def run(sizes=(100_000, 1_000_000), noises=('realistic', 'bench'), repeats: int = 3,
        scipy_cap: float = 120.0, before_commit: Optional[str] = BEFORE_COMMIT,
        with_scipy: bool = True) -> dict:
    """
    All cases; returns the rows, the goals and whether they are met.

    Parameters
    ----------
    sizes : sequence of int
        Numbers of pairs N.
    noises : sequence of str
        Keys of NOISE.
    repeats : int
        Best of this many calls.
    scipy_cap : float
        Seconds after which a scipy run is abandoned (reported as capped).
    before_commit : str or None
        Commit whose calibrate() is timed on the same pairs (None: not measured).
    with_scipy : bool
        Also time scipy on the same problem.

    """
    cases = []
    for n in sizes:
        for noise in noises:
            cases.extend(bench_case(n, noise, repeats, scipy_cap, before_commit,
                                    with_scipy).values())
    at_1m = {(r['method'], r['noise']): r['calibrate_seconds'] for r in cases
             if r['n'] == 1_000_000}
    met = {}
    if ('tls', 'realistic') in at_1m:
        met['tls_seconds_1m'] = at_1m[('tls', 'realistic')] < GOALS['tls_seconds_1m']
    if ('ols', 'realistic') in at_1m:
        met['ols_seconds_1m'] = at_1m[('ols', 'realistic')] < GOALS['ols_seconds_1m']
    return {'cases': cases, 'goals': GOALS, 'goals_met': met, 'before_commit': before_commit,
            'repeats': repeats, 'scipy_cap_seconds': scipy_cap, 'blas_threads': 1,
            'noise': {k: {'sigma_a': list(a), 'sigma_b': list(b)} for k, (a, b) in NOISE.items()}}


#: What ``profile`` reports: (label, function name, file) whose cumulative time it sums.
_PHASES = (
    ('validation', 'validated_arrays', 'pair_input.py'),
    ('motion check', 'check_motion', 'observability.py'),
    ('start (closed form + OLS, subsample)', '_start', 'calibrate.py'),
    ('OLS passes (normal equations)', 'ols_normal', 'normal_equations.py'),
    ('TLS passes (reduced system)', 'tls_schur', 'normal_equations_tls.py'),
    ('TLS input steps (back-substitution)', 'closed_form_back_substitute',
     'normal_equations_tls.py'),
    ('TLS input steps (rotations)', 'rotated', 'pair_algebra.py'),
    ('robust statistic d² (screening)', 'normalised_squares', 'screening.py'),
    ('subsets of the pairs', 'problem', 'calibrate.py'),
    ('observability', 'check_observability', 'observability.py'),
    ('posterior, χ², result', '_result', 'calibrate.py'),
)


def profile(n: int = 1_000_000, noise: str = 'realistic', method: str = 'tls',
            model: str = 'full_pose') -> dict:
    """
    Where one ``calibrate()`` spends its time: cProfile's cumulative seconds per phase.

    cProfile adds its own overhead (about 1.5× here); the shares, not the sums, are the point.
    Returns {phase: {'seconds': s, 'calls': k}} plus 'total'.
    """
    import cProfile
    import pstats

    sigma_a, sigma_b = NOISE[noise]
    pairs = make_pairs(n, noise, model)
    settings = Settings(model=model, sigma_a=sigma_a, sigma_b=sigma_b, method=method)
    prof = cProfile.Profile()
    prof.enable()
    calibrate(pairs, settings)
    prof.disable()
    stats = pstats.Stats(prof).stats
    out = {}
    for label, name, file in _PHASES:
        hits = [(v[1], v[3]) for (f, _, fn), v in stats.items()
                if fn == name and f.endswith(file)]
        out[label] = {'seconds': sum(h[1] for h in hits), 'calls': sum(h[0] for h in hits)}
    total = [v[3] for (f, _, fn), v in stats.items()
             if fn == 'calibrate' and f.endswith('calibrate.py')]
    out['total'] = {'seconds': max(total) if total else float('nan'), 'calls': 1}
    return out


def _s(v) -> str:
    return '–' if v is None else f'{v:.2f}'


def table(result: dict) -> str:
    """Markdown table of ``run``'s result."""
    lines = [
        '| N | noise | method | calibrate() s | µs/pair | it | rejected | solver alone s | '
        f'child: now / before ({result.get("before_commit") or "–"}) s | × before | scipy s | '
        '× scipy | peak B/pair |',
        '|---|---|---|---|---|---|---|---|---|---|---|---|---|',
    ]
    for r in result['cases']:
        before = r.get('before', {})
        scipy = r.get('scipy', {})
        scipy_s = _s(scipy.get('seconds')) if scipy.get('seconds') else scipy.get('status', '–')
        before_s = (_s(before.get('seconds')) if before.get('seconds')
                    else before.get('status', '–'))
        now = r.get('now_in_child', {})
        before_s = f"{_s(now.get('seconds')) if now.get('seconds') else '–'} / {before_s}"
        lines.append(
            f'| {r["n"]:,} | {r["noise"]} | {r["method"].upper()} | {r["calibrate_seconds"]:.2f} '
            f'| {r["calibrate_us_per_pair"]:.2f} | {r["iterations"]} | {r["rejected"]} '
            f'| {r["solver_seconds"]:.2f} | {before_s} | {_s(r.get("speedup_vs_before"))} '
            f'| {scipy_s} | {_s(r.get("speedup_vs_scipy"))} | {r["peak_bytes_per_pair"]:.0f} |')
    goals = ', '.join(f'{k} < {v:g} s: {"met" if result["goals_met"].get(k) else "not met"}'
                      for k, v in result['goals'].items())
    lines.append('')
    lines.append(f'Goals at 1M pairs, realistic noise (0.5° on A): {goals}. Best of '
                 f'{result["repeats"]}; BLAS one thread; scipy capped at '
                 f'{result["scipy_cap_seconds"]:.0f} s.')
    return '\n'.join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[100_000, 1_000_000])
    ap.add_argument('--noises', nargs='+', default=['realistic', 'bench'], choices=list(NOISE))
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--scipy-cap', type=float, default=120.0)
    ap.add_argument('--no-scipy', action='store_true')
    ap.add_argument('--before-commit', default=BEFORE_COMMIT,
                    help="commit whose calibrate() is timed too ('' to skip)")
    ap.add_argument('--profile', action='store_true',
                    help='only print where calibrate() spends its time at the first size')
    args = ap.parse_args(argv)
    if args.profile:
        for model in ('full_pose', 'position_only'):
            for method in ('tls', 'ols'):
                print(f'## {model} {method.upper()} N={args.sizes[0]:,} {args.noises[0]}')
                for label, v in profile(args.sizes[0], args.noises[0], method, model).items():
                    print(f'- {label}: {v["seconds"]:.3f} s ({v["calls"]} calls)')
        return
    result = run(args.sizes, args.noises, args.repeats, args.scipy_cap,
                 args.before_commit or None, not args.no_scipy)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / 'calibrate_speed_bench.json').write_text(json.dumps(result, indent=1))
    print(table(result))


if __name__ == '__main__':
    main()
