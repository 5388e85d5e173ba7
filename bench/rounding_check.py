"""
How far a change moved the calibrations, for a change that may move rounding but nothing else.

``bench/fingerprint.py`` proves a change left every number identical to the bit. A change that
reorders or removes a rounding step (normalising a quaternion once instead of twice) changes
last bits everywhere; this says by how much. 54 calibrations of simulated recordings (full
pose, position only, three markers; offsets, outliers, drift; fixed and estimated offsets,
OLS, noise auto) are run and their numbers compared with those of another tree::

    python bench/rounding_check.py --out /tmp/before.pkl      # on the tree before
    python bench/rounding_check.py --compare /tmp/before.pkl  # on the tree after

The comparison prints, per quantity, the largest difference over the runs: φ and the
residuals in posterior or noise standard deviations, the rest relative. Exit 1 if any is above
``--limit`` (1e-6 by default: far below anything a statistic sees), or an outcome changed.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import pickle
import sys

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # before numpy: one summation order

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

MODELS = ('full_pose', 'full_pose', 'position_only', 'three_marker')
EFFECTS = ('time_offset=0.012', 'outliers=0.02', 'time_offset=-0.2', None, 'clock_drift=40',
           'time_offset=0.003')
SETTINGS = (('fixed', {'estimate_time_offset': False, 'time_offset': 0.0}), ('est', {}),
            ('ols', {'method': 'ols'}), ('auto', {'noise': 'auto'}),
            ('drift', {'estimate_clock_drift': True}))


def numbers() -> dict:
    """Run the calibrations; return, per run, its numbers or the error it raised."""
    from coreg_ros.core.calibration.pipeline import calibrate_streams
    from coreg_ros.core.errors import CoregError
    from coreg_ros.core.settings import Settings
    from coreg_ros.sim import parse_effect, simulate_recording

    rng = np.random.default_rng(2026)
    out = {}
    for seed in range(12):
        model, effect = MODELS[seed % 4], EFFECTS[seed % 6]
        n = int(rng.integers(3000, 40000))
        rec = simulate_recording(100 + seed, n / 50.0, model, rate_a=100.0, rate_b=50.0,
                                 effects=[parse_effect(effect)] if effect else [])
        a, bs = rec.streams[rec.topics_a], [rec.streams[t] for t in rec.topics_b]
        for key, kwargs in SETTINGS:
            if model != 'full_pose' and key == 'auto':
                continue
            name = f'{seed}/{model}/{effect}/{key}'
            try:
                r, _ = calibrate_streams(a, bs, Settings(model=model, **kwargs))
            except CoregError as e:
                out[name] = f'{type(e).__name__}: {e}'
                continue
            offset = r.time_offset
            out[name] = {
                'params': r.params, 'sigma': np.sqrt(np.abs(np.diag(r.param_cov))),
                'cov': r.param_cov, 'chi2': r.chi2, 'p': r.p_value,
                'residuals': r.residuals, 'inliers': r.inliers,
                'tau': 0.0 if offset is None else offset.value_s,
                'tau_sigma': 0.0 if offset is None or offset.sigma_s is None else offset.sigma_s}
    return out


def compare(before: dict, after: dict) -> tuple[dict, list]:
    """Largest difference per quantity (φ, residuals in σ; others relative) and changed runs."""
    worst, changed = {}, []
    for name, old in before.items():
        new = after.get(name)
        if isinstance(old, str) or isinstance(new, str) or new is None:
            if old != new:
                changed.append(name)
            continue
        for key in ('params', 'residuals', 'cov', 'chi2', 'p', 'tau', 'tau_sigma', 'inliers'):
            x, y = np.asarray(old[key], float), np.asarray(new[key], float)
            if x.shape != y.shape:
                changed.append(f'{name}: {key} shape')
                continue
            d = np.abs(x - y)
            if key == 'params':
                d = d / old['sigma']
            elif key != 'residuals':  # whitened: already in σ
                d = d / np.maximum(np.abs(x), np.finfo(float).tiny)
            worst[key] = max(worst.get(key, 0.0), float(np.max(d)) if d.size else 0.0)
    return worst, changed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', type=Path, help="write this tree's numbers here")
    parser.add_argument('--compare', type=Path, help='compare this tree with numbers written')
    parser.add_argument('--limit', type=float, default=1e-6)
    args = parser.parse_args(argv)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        got = numbers()
    if args.out:
        args.out.write_bytes(pickle.dumps(got))
        print(f'{len(got)} runs written to {args.out}')
    if not args.compare:
        return 0
    worst, changed = compare(pickle.loads(args.compare.read_bytes()), got)
    for key, value in worst.items():
        print(f'{key:10s} {value:.3g}' + ('  (σ)' if key in ('params', 'residuals') else ''))
    for name in changed:
        print(f'outcome changed: {name}')
    return int(bool(changed) or any(v > args.limit for v in worst.values()))


if __name__ == '__main__':
    sys.exit(main())
