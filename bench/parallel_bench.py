"""
Many cases in parallel (issue 15): ``coreg validate-diagnosis`` on 1 and 2 local workers.

1. The validation workload (``validate``, what ``coreg validate-diagnosis`` calls: simulate,
   diagnose blind, score), the same cases (fixed seed) once with 1 worker (in this process, the
   baseline) and once with 2 spawned workers, in the same run; wall-clock seconds, speedup
   (goal >= 1.8x on 2 cores), per-case time, and whether the results are identical.
2. The per-task overhead of a Dask cluster: a LocalCluster (2 worker processes, 1 thread each)
   started here runs no-op tasks through the same engine (``coreg_ros.parallel.run_cases``).
3. On paper: 10,000 cases on 100 workers = ceil(10,000 / 100) x the per-case time + 10,000 x
   the per-task overhead (the scheduler handles tasks one after another), assuming workers as
   fast as one core here.

Run alone: ``python bench/parallel_bench.py [--cases 40] [--seed 2024] [--short]`` prints the
table and writes bench/results/parallel_bench.json. Speedups need a quiet machine: other
processes on the two cores take from the two workers first.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
import sys
import time
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

GOAL_SPEEDUP = 1.8
#: The estimate on paper.
PAPER_CASES, PAPER_WORKERS = 10_000, 100
#: No-op tasks timed on the LocalCluster.
OVERHEAD_TASKS = 400


def noop(case: int) -> int:
    """Do nothing: what is left of the task's time is the engine's overhead."""
    return case


def _quiet(fraction: float, text: str = '') -> None:
    """No progress output (the bench prints its table)."""


def _outcomes(results: list) -> list:
    return [{k: v for k, v in r.items() if k != 'seconds'} if isinstance(r, dict) else str(r)
            for r in results]


def time_validation(cases: int, seed: int, workers: int,
                    duration: Optional[tuple] = None) -> dict:
    """Wall-clock time of ``validate`` with ``workers`` local processes."""
    from coreg_ros.parallel import failures
    from coreg_ros.sim.validation import validate

    t0 = time.perf_counter()
    out = validate(cases, seed, _quiet, workers=workers, duration=duration)
    seconds = time.perf_counter() - t0
    ok = [r for r in out['results'] if isinstance(r, dict)]
    return {'workers': workers, 'cases': cases, 'seconds': seconds,
            'per_case_s': seconds / cases,
            'diagnosis_mean_s': sum(r['seconds'] for r in ok) / max(len(ok), 1),
            'failed': len(failures(out['results'])), 'outcomes': _outcomes(out['results'])}


def dask_overhead(tasks: int = OVERHEAD_TASKS) -> dict:
    """Seconds per no-op task through ``run_cases`` on a 2-worker LocalCluster."""
    from coreg_ros.parallel import run_cases
    from distributed import LocalCluster

    t0 = time.perf_counter()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        start = time.perf_counter() - t0
        run_cases(noop, range(20), scheduler=cluster.scheduler_address, progress=_quiet)
        t0 = time.perf_counter()
        res = run_cases(noop, range(tasks), scheduler=cluster.scheduler_address,
                        progress=_quiet)
        seconds = time.perf_counter() - t0
    assert res == list(range(tasks))
    return {'tasks': tasks, 'seconds': seconds, 'per_task_s': seconds / tasks,
            'cluster_start_s': start}


def estimate(per_case_s: float, per_task_s: float, cases: int = PAPER_CASES,
             workers: int = PAPER_WORKERS) -> dict:
    """Wall-clock estimate of ``cases`` on ``workers``: rounds of cases plus scheduler time."""
    rounds = math.ceil(cases / workers)
    compute = rounds * per_case_s
    overhead = cases * per_task_s
    return {'cases': cases, 'workers': workers, 'compute_s': compute,
            'scheduler_overhead_s': overhead, 'seconds': compute + overhead,
            'one_worker_s': cases * per_case_s}


def run(cases: int = 40, seed: int = 2024, short: bool = False, dask: bool = True) -> dict:
    """Return the two local runs, the Dask overhead and the estimate as a JSON-friendly dict."""
    duration = (15.0, 20.0) if short else None
    one = time_validation(cases, seed, 1, duration)
    two = time_validation(cases, seed, 2, duration)
    identical = one.pop('outcomes') == two.pop('outcomes')
    out = {'cases': cases, 'seed': seed, 'short_recordings': short, 'baseline': one,
           'two_workers': two, 'speedup': one['seconds'] / two['seconds'],
           'goal_speedup': GOAL_SPEEDUP, 'identical_results': identical}
    out['within_goal'] = out['speedup'] >= GOAL_SPEEDUP
    if dask:
        try:
            out['dask'] = dask_overhead()
        except ImportError:
            out['dask'] = None
    per_task = out['dask']['per_task_s'] if out.get('dask') else 0.0
    out['estimate'] = estimate(one['per_case_s'], per_task)
    return out


def _dur(seconds: float) -> str:
    if seconds >= 3600:
        return f'{seconds / 3600:.1f} h'
    return f'{seconds / 60:.1f} min' if seconds >= 120 else f'{seconds:.1f} s'


def table(result: dict) -> str:
    """Markdown table of the bench."""
    one, two = result['baseline'], result['two_workers']
    lines = ['| run | workers | cases | wall time | per case | speedup (goal) |',
             '|---|---|---|---|---|---|',
             f'| validate, local (baseline) | 1 | {one["cases"]} | {one["seconds"]:.1f} s '
             f'| {one["per_case_s"]:.2f} s (diagnosis {one["diagnosis_mean_s"]:.2f} s) '
             '| 1.00 |',
             f'| validate, local spawned processes | 2 | {two["cases"]} | {two["seconds"]:.1f} s '
             f'| {two["per_case_s"]:.2f} s | {result["speedup"]:.2f}x '
             f'(≥ {result["goal_speedup"]:g}x{"" if result["within_goal"] else ", not met"}) |']
    d = result.get('dask')
    if d:
        lines.append(f'| no-op tasks, Dask LocalCluster | 2 | {d["tasks"]} | '
                     f'{d["seconds"]:.2f} s | {d["per_task_s"] * 1e3:.2f} ms overhead per task '
                     f'(cluster start {d["cluster_start_s"]:.1f} s) | |')
    e = result['estimate']
    lines.append(f'| estimate on paper: {e["cases"]:,} cases | {e["workers"]} | {e["cases"]:,} '
                 f'| {_dur(e["seconds"])} ({_dur(e["compute_s"])} compute + '
                 f'{_dur(e["scheduler_overhead_s"])} scheduler) | {one["per_case_s"]:.2f} s '
                 f'| {e["one_worker_s"] / e["seconds"]:.0f}x vs 1 worker '
                 f'({_dur(e["one_worker_s"])}) |')
    lines += ['', f'Seed {result["seed"]}; results of 1 and 2 workers identical: '
              f'{"yes" if result["identical_results"] else "NO"}. Estimate: '
              f'ceil(cases / workers) x per-case time + cases x per-task overhead, workers as '
              f'fast as one core here.']
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--cases', type=int, default=40)
    parser.add_argument('--seed', type=int, default=2024)
    parser.add_argument('--short', action='store_true',
                        help='15-20 s recordings instead of the 40-120 s of the validation')
    parser.add_argument('--no-dask', action='store_true', help='skip the LocalCluster')
    parser.add_argument('--json', default=str(ROOT / 'bench' / 'results' / 'parallel_bench.json'))
    args = parser.parse_args(argv)
    result = run(args.cases, args.seed, args.short, dask=not args.no_dask)
    print(table(result))
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1) + '\n')
    return 0 if result['identical_results'] else 1


if __name__ == '__main__':
    sys.exit(main())
