"""
Restricted rigs (issue 22): calibrate() on SCARA, mobile robot, gantry and turntable motion.

The baseline is the same call on the ``diverse`` motion (every direction determined), same
pairs, noise, method and truth, in the same run; CPU time, best of ``repeats``. Goal: a
restricted rig costs at most ``GOAL`` × the full-rank calibration (the observability check,
the gauge and the held directions' second look included).

    python bench/restricted_bench.py [--pairs 100000] [--repeats 7]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

#: The largest restricted / full-rank time ratio the issue allows.
GOAL = 1.2
RIGS = ('scara', 'planar', 'gantry', 'turntable')


def _pairs(motion: str, n: int, seed: int = 5):
    from coreg_ros.sim import make_motion, random_truth, simulate_pairs
    truth = random_truth(np.random.default_rng(seed), 'full_pose')
    motion = make_motion(np.random.default_rng(seed + 1), motion)
    pairs, _, _ = simulate_pairs(np.random.default_rng(seed + 2), n, 'full_pose',
                                 sigma_a=(5e-5, 2e-4), sigma_b=(2e-4, 1e-3), truth=truth,
                                 motion=motion)
    return pairs


def run(n: int = 100_000, repeats: int = 7, methods=('ols', 'tls')) -> dict:
    """
    Time calibrate() per rig and method against the full-rank recording; return the rows.

    CPU time of this process (``time.process_time``), best of ``repeats``, the rigs and the
    baseline interleaved: on a shared machine the wall time of a 0.1 s call varies by tens of
    per cent with the other processes' load, its CPU time far less.
    """
    from coreg_ros.core.calibration.calibrate import calibrate
    from coreg_ros.core.settings import Settings
    rows = []
    recordings = {rig: _pairs(rig, n) for rig in ('diverse',) + RIGS}
    for method in methods:
        settings = Settings(method=method, sigma_a=(5e-5, 2e-4), sigma_b=(2e-4, 1e-3))
        best = dict.fromkeys(recordings, float('inf'))
        results = {}
        for _ in range(repeats):
            for rig, pairs in recordings.items():
                t = time.process_time()
                results[rig] = calibrate(pairs, settings)
                best[rig] = min(best[rig], time.process_time() - t)
        base = best['diverse']
        for rig in RIGS:
            rows.append({'rig': rig, 'method': method, 'n_pairs': n, 'seconds': best[rig],
                         'full_rank_seconds': base, 'ratio': best[rig] / base,
                         'held': len(results[rig].held), 'success': bool(results[rig].success),
                         'full_rank_success': bool(results['diverse'].success), 'goal': GOAL,
                         'met': best[rig] / base <= GOAL})
    return {'rows': rows, 'repeats': repeats}


def table(results: dict) -> str:
    """Markdown table of ``run``'s rows."""
    lines = ['| rig | method | pairs | held | calibrate() CPU s | full rank CPU s | × full rank '
             f'(goal ≤ {GOAL:g}) |', '|---|---|---|---|---|---|---|']
    for r in results['rows']:
        lines.append(f'| {r["rig"]} | {r["method"].upper()} | {r["n_pairs"]:,} | {r["held"]} '
                     f'| {r["seconds"]:.3f} | {r["full_rank_seconds"]:.3f} | {r["ratio"]:.2f}'
                     f'{"" if r["met"] else " **over**"} |')
    return '\n'.join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--pairs', type=int, default=100_000)
    parser.add_argument('--repeats', type=int, default=7)
    parser.add_argument('--json', help='also write the rows here')
    args = parser.parse_args(argv)
    from threadpoolctl import threadpool_limits
    with threadpool_limits(1):
        results = run(args.pairs, args.repeats)
    print(table(results))
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
