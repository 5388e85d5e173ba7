"""
The clock offset on random draws of model, duration, noise of both devices and offset.

The offset ranges from ms to minutes. Prints each case and, at the end, how many were not
recovered within 4σ and the mean z² of the estimated offsets (1 when σ_τ is calibrated).

    python bench/offset_sweep.py --seed 6 --cases 60 [--workers N] [--scheduler ADDRESS]

Every case is drawn up front and carries its own simulator seed, so the numbers are the same
whatever the workers (``coreg_ros.parallel``).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import sys
import time
from typing import Optional

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from coreg_ros.cli.argtypes import add_parallel_arguments  # noqa: E402
from coreg_ros.core.calibration.pipeline import calibrate_streams  # noqa: E402
from coreg_ros.core.settings import Settings  # noqa: E402
from coreg_ros.parallel import CaseFailure, run_cases  # noqa: E402
from coreg_ros.sim import simulate_recording  # noqa: E402
import numpy as np  # noqa: E402


def draw_cases(seed: int, cases: int) -> list:
    """
    Draw every case up front from ``seed`` (model, duration, offset, noise, simulator seed).

    The draws are those the sweep always made, in the same order, so a seed names the same
    cases as before; each case then runs on its own (any worker, any order).
    """
    rng = np.random.default_rng(seed)
    out = []
    for k in range(cases):
        model = str(rng.choice(['full_pose', 'full_pose', 'position_only', 'three_marker']))
        dur = float(rng.uniform(8, 60))
        tau = float(rng.choice([rng.uniform(-0.05, 0.05), rng.uniform(-1, 1),
                                rng.uniform(-200, 200)]))
        sa = (float(10 ** rng.uniform(-4.5, -3)), float(10 ** rng.uniform(-3.5, -2.5)))
        sb = (float(10 ** rng.uniform(-4, -2.5)), float(10 ** rng.uniform(-3, -1.7)))
        out.append({'k': k, 'model': model, 'duration': dur, 'tau': tau, 'sigma_a': sa,
                    'sigma_b': sb, 'seed': int(rng.integers(1e6))})
    return out


def run_case(case: dict) -> dict:
    """Simulate one case with B's stamps shifted by tau and estimate the offset back."""
    k, model, dur, tau = case['k'], case['model'], case['duration'], case['tau']
    sa, sb = case['sigma_a'], case['sigma_b']
    rec = simulate_recording(case['seed'], dur, model, sigma_a=sa, sigma_b=sb)
    a = rec.streams[rec.topics_a]
    bs = [replace(rec.streams[t], stamps=rec.streams[t].stamps + np.int64(round(tau * 1e9)))
          for t in rec.topics_b]
    t0 = time.perf_counter()
    try:
        r, _ = calibrate_streams(a, bs, Settings(model=model, sigma_a=sa, sigma_b=sb))
    except Exception as e:  # noqa: BLE001 - a refusal counts as a miss, with its reason
        return {'ok': False, 'z': None,
                'line': f'{k:3d} {model:13s} tau {tau:10.4f} REFUSED {type(e).__name__}: {e}'}
    t = r.time_offset
    zz = (t.value_s - tau) / t.sigma_s if t.estimated else float('nan')
    ok = bool(t.estimated and abs(zz) < 4)
    line = (f'{k:3d} {model:13s} dur {dur:5.1f} tau {tau:10.4f} est {t.value_s:10.4f} '
            f'sd {t.sigma_s or 0:.2e} z {zz:6.2f} rejected {r.n_rejected} '
            f'{time.perf_counter() - t0:.2f} s' + ('' if ok else f'  <<< {t.message}'))
    return {'ok': ok, 'z': float(zz) if t.estimated else None, 'line': line}


def run(seed: int, cases: int, log=print, workers: int = 1,
        scheduler: Optional[str] = None) -> dict:
    """Draw ``cases`` recordings and calibrate each with the offset estimated."""
    drawn = draw_cases(seed, cases)
    results = run_cases(run_case, drawn, workers=workers, scheduler=scheduler,
                        label=lambda c: f'case {c["k"]} (simulator seed {c["seed"]})',
                        title='offset sweep')
    bad, z, failed = 0, [], []
    for res in results:
        if isinstance(res, CaseFailure):
            bad += 1
            failed.append(res.as_dict())
            log(f'FAILED {res}')
            continue
        bad += not res['ok']
        if res['z'] is not None:
            z.append(res['z'])
        log(res['line'])
    z = np.asarray(z)
    out = {'cases': cases, 'missed': bad, 'mean_z2': float(np.mean(z ** 2)) if z.size else None,
           'failed': failed}
    log(f'missed {bad} of {cases}; mean z^2 '
        + ('n/a' if out['mean_z2'] is None else f'{out["mean_z2"]:.3f}'))
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--seed', type=int, default=6)
    parser.add_argument('--cases', type=int, default=60)
    add_parallel_arguments(parser)
    args = parser.parse_args(argv)
    out = run(args.seed, args.cases, workers=args.workers, scheduler=args.scheduler)
    return 1 if out['failed'] else 0


if __name__ == '__main__':
    sys.exit(main())
