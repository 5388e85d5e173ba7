"""
What estimating the clock offset costs: ``calibrate_streams`` at 100k pairs.

τ estimated (``--time-offset auto``) against τ fixed at its true value, in the same run
(issue 10: ≤ 1.5×).

Times the whole function users call (pairing, validation, fit, robust pass), best of ``repeats``.
"""

from __future__ import annotations

import time

from coreg_ros.core.calibration.pipeline import calibrate_streams
from coreg_ros.core.settings import Settings
from coreg_ros.sim import parse_effect, simulate_recording

#: Goal of issue 10: estimated / fixed wall time at 100k pairs.
RATIO_GOAL = 1.5


def _best(fn, repeats: int) -> tuple:
    best, out = float('inf'), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def bench_time_offset(n_pairs: int = 100_000, tau: float = 0.012, repeats: int = 5,
                      seed: int = 5) -> dict:
    """Return the fixed and estimated times, their ratio and the estimate."""
    rec = simulate_recording(seed, n_pairs / 50.0, 'full_pose', rate_a=100.0, rate_b=50.0,
                             effects=[parse_effect(f'time_offset={tau}')])
    a = rec.streams[rec.topics_a]
    bs = [rec.streams[t] for t in rec.topics_b]
    fixed_s, (fixed, _) = _best(lambda: calibrate_streams(
        a, bs, Settings(estimate_time_offset=False, time_offset=tau)), repeats)
    auto_s, (auto, _) = _best(lambda: calibrate_streams(a, bs, Settings()), repeats)
    t = auto.time_offset
    return {'n_pairs': auto.n_pairs, 'true_offset_s': tau, 'fixed_seconds': fixed_s,
            'estimated_seconds': auto_s, 'ratio': auto_s / fixed_s, 'goal_ratio': RATIO_GOAL,
            'estimate_s': t.value_s, 'sigma_s': t.sigma_s,
            'error_sigmas': abs(t.value_s - tau) / t.sigma_s, 'fixed_success': fixed.success,
            'estimated_success': auto.success}


if __name__ == '__main__':
    import json

    print(json.dumps(bench_time_offset(), indent=1))
