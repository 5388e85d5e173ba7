"""
What estimating the clock offset costs: ``calibrate_streams`` at 100k pairs.

τ estimated (``--time-offset auto``) against τ fixed at its true value (issue 10, issue 25
item 5: ≤ 1.5×), for this tree and for the code at ``BEFORE_COMMIT`` (a git worktree under /tmp,
before issue 25's work), each in a child process of the same kind, BLAS pinned to one thread.

Times the whole function users call (pairing, validation, fit, robust pass), the fixed and the
estimated call alternating, best of ``repeats`` each, wall and CPU time; the goal is judged on
CPU time (the machine is shared: another process's burst lengthens the wall time of either
call, not the work it does). ``python bench/spatiotemporal_bench.py`` prints the JSON.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import subprocess
import sys
import time
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
#: Goal of issues 10 and 25: estimated / fixed time at 100k pairs.
RATIO_GOAL = 1.5
#: The code before issue 25's work on the offset search.
BEFORE_COMMIT = 'c1de503'
_PINNING = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')


def measure(n_pairs: int = 100_000, tau: float = 0.012, repeats: int = 5,
            seed: int = 5) -> dict:
    """Time fixed and estimated τ in this process (the ``coreg_ros`` first on sys.path)."""
    from coreg_ros.core.calibration.pipeline import calibrate_streams
    from coreg_ros.core.settings import Settings
    from coreg_ros.sim import parse_effect, simulate_recording

    rec = simulate_recording(seed, n_pairs / 50.0, 'full_pose', rate_a=100.0, rate_b=50.0,
                             effects=[parse_effect(f'time_offset={tau}')])
    a = rec.streams[rec.topics_a]
    bs = [rec.streams[t] for t in rec.topics_b]
    cases = {'fixed': Settings(estimate_time_offset=False, time_offset=tau),
             'estimated': Settings()}
    best = {k: [float('inf'), float('inf')] for k in cases}
    out = {}
    for _ in range(repeats):
        for key, settings in cases.items():
            wall, cpu = time.perf_counter(), time.process_time()
            out[key] = calibrate_streams(a, bs, settings)[0]
            cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
            best[key] = [min(best[key][0], wall), min(best[key][1], cpu)]
    t = out['estimated'].time_offset
    return {'n_pairs': out['estimated'].n_pairs, 'true_offset_s': tau,
            'fixed_seconds': best['fixed'][0], 'estimated_seconds': best['estimated'][0],
            'fixed_cpu_s': best['fixed'][1], 'estimated_cpu_s': best['estimated'][1],
            'wall_ratio': best['estimated'][0] / best['fixed'][0],
            'ratio': best['estimated'][1] / best['fixed'][1], 'goal_ratio': RATIO_GOAL,
            'estimate_s': t.value_s, 'sigma_s': t.sigma_s,
            'error_sigmas': abs(t.value_s - tau) / t.sigma_s,
            'fixed_success': out['fixed'].success, 'estimated_success': out['estimated'].success}


def _in_child(tree: Path, repeats: int) -> dict:
    env = {**os.environ, **dict.fromkeys(_PINNING, '1')}
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), '--tree', str(tree),
                          '--repeats', str(repeats)], capture_output=True, text=True, env=env,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def bench_time_offset(repeats: int = 5, before_commit: Optional[str] = BEFORE_COMMIT) -> dict:
    """
    Return this tree's fixed and estimated times, their ratio and the estimate.

    With ``before_commit``, ``before`` holds the same figures for the code at that commit,
    measured in the same run.
    """
    result = _in_child(ROOT, repeats)
    if before_commit:
        sys.path.insert(0, str(ROOT))
        from bench.calibrate_speed_bench import before_worktree
        result['before'] = _in_child(before_worktree(before_commit), repeats)
        result['before']['commit'] = before_commit
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--tree', type=Path, help='measure the coreg_ros of this tree, here')
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--before-commit', default=BEFORE_COMMIT)
    args = parser.parse_args()
    if args.tree is None:
        print(json.dumps(bench_time_offset(args.repeats, args.before_commit or None), indent=1))
        return
    sys.path.insert(0, str(args.tree.resolve()))
    print(json.dumps(measure(repeats=args.repeats)))


if __name__ == '__main__':
    main()
