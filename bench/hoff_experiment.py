"""
Hoff & Vincent's fusion experiment, reproduced with our simulator.

Two trackers follow one rigidly linked body with complementary weaknesses, as in Hoff &
Vincent (2000) §5: device A, a fixed tracker with good position but weak orientation (an
optical tracker deriving orientation from a small marker pattern); device B, a tracker with good
orientation but weak position (a head-mounted camera). For each of several random truths:

1. calibrate on a recording (``simulate_pairs``, diverse motion, TLS) to get T0, T1 and their
   joint covariance;
2. on a second, independent recording of the same rig, carry every A sample into B's base
   frame through the calibration (``T0 · T_A · T1``, calibration and A noise included), take
   B's own sample, and fuse the two on the tangent space (``coreg_ros.core.uncertainty``);
3. compare each of the three streams with the true marker pose in B's base frame, per axis
   (position mm, rotation mrad about B's base axes), and the predicted σ with the errors
   (mean NEES, share inside the 95 % ellipsoid).

The fused stream beats both inputs on every axis: B's accurate orientation also corrects the
position of A-through-calibration, whose position error is dominated by A's rotation error
times the lever arm from the tool to the marker (Hoff's ΔP = d Δθ).

Run: ``python bench/hoff_experiment.py [--calibrations 100] [--workers N] [--scheduler ADDRESS]
[--json out.json] [--markdown out.md]`` (about 20 s on one core).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional

from coreg_ros.cli.argtypes import add_parallel_arguments
from coreg_ros.core import uncertainty as unc
from coreg_ros.core.calibration.calibrate import calibrate
from coreg_ros.core.estimator import noise_covariance
from coreg_ros.core.settings import Settings
from coreg_ros.parallel import CaseFailure, failures, run_cases
from coreg_ros.sim import simulate_pairs
import numpy as np
from scipy import stats

#: Device A: fixed tracker, position 0.1 mm, orientation 2 mrad (0.11°).
SIGMA_A = (1.0e-4, 2.0e-3)
#: Device B: complementary, position 2 mm, orientation 0.8 mrad (0.046°).
SIGMA_B = (2.0e-3, 8.0e-4)
AXES = ('x', 'y', 'z', 'rx', 'ry', 'rz')
SCALE = np.array([1e3] * 3 + [1e3] * 3)  # m -> mm, rad -> mrad


def one_rig(seed: int, n_cal: int, n_test: int) -> dict:
    """Calibrate one random rig and score the three streams on an independent recording."""
    rng = np.random.default_rng(seed)
    cal_pairs, _, truth = simulate_pairs(rng, n_cal, sigma_a=SIGMA_A, sigma_b=SIGMA_B)
    settings = Settings(sigma_a=SIGMA_A, sigma_b=SIGMA_B, method='tls')
    result = calibrate(cal_pairs, settings)
    test, clean, _ = simulate_pairs(rng, n_test, sigma_a=SIGMA_A, sigma_b=SIGMA_B, truth=truth)
    cov_a, cov_b = noise_covariance(SIGMA_A), noise_covariance(SIGMA_B)
    p_a, q_a, c_a = unc.through_calibration_arrays(result, test.pos_a, test.quat_a, cov_a)
    c_b = np.broadcast_to(cov_b, c_a.shape)
    p_f, q_f, c_f, _ = unc.fuse_arrays(p_a, q_a, c_a, test.pos_b, test.quat_b, c_b)
    out = {'seed': seed, 'chi2_per_dof': result.reduced_chi2}
    for name, (p, q, c) in {'a_through_calibration': (p_a, q_a, c_a),
                            'b_alone': (test.pos_b, test.quat_b, c_b),
                            'fused': (p_f, q_f, c_f)}.items():
        err = unc.pose_error(clean.pos_b, clean.quat_b, p, q)
        e = unc.nees(err, c)
        out[name] = {'sq_err': np.sum(err ** 2, axis=0), 'pred_var': np.sum(
            np.diagonal(c, axis1=-2, axis2=-1), axis=0), 'n': len(err),
            'nees_sum': float(np.sum(e)),
            'inside95': int(np.sum(e <= stats.chi2.ppf(0.95, 6)))}
    return out


def run(calibrations: int, n_cal: int, n_test: int, seed: int, workers: int = 1,
        scheduler: Optional[str] = None) -> dict:
    """
    Pool ``calibrations`` rigs; per-axis RMS error and predicted σ of each stream.

    Rig k has seed ``seed + k`` and runs on its own (``coreg_ros.parallel``: local processes or
    a Dask cluster), so the numbers do not depend on the workers. A rig that raises is left
    out of the pool and listed under ``failed``.
    """
    results = run_cases(one_rig, [seed + k for k in range(calibrations)], args=(n_cal, n_test),
                        workers=workers, scheduler=scheduler, title='rigs')
    rigs = [r for r in results if not isinstance(r, CaseFailure)]
    table = {}
    for name in ('a_through_calibration', 'b_alone', 'fused'):
        n = sum(r[name]['n'] for r in rigs)
        rms = np.sqrt(sum(r[name]['sq_err'] for r in rigs) / n) * SCALE
        pred = np.sqrt(sum(r[name]['pred_var'] for r in rigs) / n) * SCALE
        table[name] = {'rms': dict(zip(AXES, rms.tolist(), strict=True)),
                       'predicted_sigma': dict(zip(AXES, pred.tolist(), strict=True)),
                       'mean_nees': sum(r[name]['nees_sum'] for r in rigs) / n,
                       'coverage95': sum(r[name]['inside95'] for r in rigs) / n}
    return {'sigma_a': SIGMA_A, 'sigma_b': SIGMA_B, 'calibrations': calibrations,
            'calibration_pairs': n_cal, 'test_pairs': n_test, 'seed': seed,
            'chi2_per_dof': [r['chi2_per_dof'] for r in rigs], 'streams': table,
            'failed': [f.as_dict() for f in failures(results)]}


LABELS = {'a_through_calibration': 'A through calibration (T0·T_A·T1)', 'b_alone': 'B alone',
          'fused': 'fused (A-through-calibration ⊕ B)'}


def markdown(res: dict) -> str:
    """Format the result as a markdown table (RMS error per axis, predicted σ in brackets)."""
    head = ('| stream | x mm | y mm | z mm | rx mrad | ry mrad | rz mrad | NEES (6) | in 95 % |\n'
            '|---|---|---|---|---|---|---|---|---|')
    rows = []
    for name, label in LABELS.items():
        s = res['streams'][name]
        cells = [f"{s['rms'][a]:.3f} ({s['predicted_sigma'][a]:.3f})" for a in AXES]
        rows.append(f'| {label} | ' + ' | '.join(cells)
                    + f" | {s['mean_nees']:.2f} | {100 * s['coverage95']:.1f} % |")
    note = (f"A: σ = {res['sigma_a'][0] * 1e3:g} mm, {res['sigma_a'][1] * 1e3:g} mrad; "
            f"B: σ = {res['sigma_b'][0] * 1e3:g} mm, {res['sigma_b'][1] * 1e3:g} mrad. "
            f"{res['calibrations']} random rigs, each calibrated (TLS) on "
            f"{res['calibration_pairs']} pairs and scored on {res['test_pairs']} independent "
            "pairs; RMS error against the truth in B's base frame, predicted σ in brackets.")
    return '\n'.join([head, *rows, '', note])


def plot(res: dict, path: str) -> None:
    """Draw grouped bars of the per-axis RMS error of the three streams (predicted σ as ticks)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.8), dpi=110)
    FigureCanvasAgg(fig)
    colours = {'a_through_calibration': '#1f77b4', 'b_alone': '#ff7f0e', 'fused': '#2ca02c'}
    for k, (axes, unit) in enumerate(((AXES[:3], 'position error, mm'),
                                      (AXES[3:], 'rotation error, mrad'))):
        ax = fig.add_subplot(1, 2, k + 1)
        x = np.arange(3)
        for j, (name, colour) in enumerate(colours.items()):
            s = res['streams'][name]
            vals = [s['rms'][a] for a in axes]
            pred = [s['predicted_sigma'][a] for a in axes]
            ax.bar(x + (j - 1) * 0.27, vals, 0.27, color=colour, label=LABELS[name])
            ax.plot(x + (j - 1) * 0.27, pred, '_', color='k', ms=14, mew=2)
        ax.set_xticks(x, [f'about {a[1]}' if a.startswith('r') else a for a in axes])
        ax.set_ylabel(f'RMS {unit}')
        for j, name in enumerate(colours):
            for i, a in enumerate(axes):
                v = res['streams'][name]['rms'][a]
                ax.text(i + (j - 1) * 0.27, v, f'{v:.2f}', ha='center', va='bottom', fontsize=7)
        ax.set_title(unit.split(',')[0].capitalize() + ' (black ticks: predicted σ)',
                     fontsize=10)
    handles, labels = fig.axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc='lower center', ncol=3, fontsize=9, frameon=False)
    fig.suptitle(f"Hoff & Vincent's experiment with our simulator: A {res['sigma_a'][0] * 1e3:g} "
                 f"mm / {res['sigma_a'][1] * 1e3:g} mrad, B {res['sigma_b'][0] * 1e3:g} mm / "
                 f"{res['sigma_b'][1] * 1e3:g} mrad", fontsize=11)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--calibrations', type=int, default=100)
    parser.add_argument('--calibration-pairs', type=int, default=2000)
    parser.add_argument('--test-pairs', type=int, default=500)
    parser.add_argument('--seed', type=int, default=2000)
    parser.add_argument('--json', help='write the numbers as JSON')
    parser.add_argument('--markdown', help='write the table as markdown')
    parser.add_argument('--plot', help='write a bar chart of the per-axis errors (PNG)')
    add_parallel_arguments(parser)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    res = run(args.calibrations, args.calibration_pairs, args.test_pairs, args.seed,
              workers=args.workers, scheduler=args.scheduler)
    for f in res['failed']:
        print(f'rig failed: seed {f["seed"]}: {f["error"]}', file=sys.stderr)
    table = markdown(res)
    print(table)
    print(f'\n({time.perf_counter() - t0:.1f} s)')
    if args.json:
        with open(args.json, 'w') as f:
            json.dump(res, f, indent=1)
    if args.markdown:
        with open(args.markdown, 'w') as f:
            f.write(table + '\n')
    if args.plot:
        plot(res, args.plot)
    fused, a, b = (res['streams'][k]['rms'] for k in ('fused', 'a_through_calibration',
                                                      'b_alone'))
    better = all(fused[x] < min(a[x], b[x]) for x in AXES)
    print('fused better than both on every axis:', better)
    return 0 if better and not res['failed'] else 1


if __name__ == '__main__':
    sys.exit(main())
