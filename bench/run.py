"""
All benchmarks in one command (``make bench``).

Estimators against scipy, pairing, bags, node, the full-size Monte Carlo, the watchdog, the fuzz,
the blind diagnosis validation and the real recordings. Prints the tables, writes
bench/results/estimator.json, and regenerates docs/benchmarks.md (speed and memory) and
docs/validation.md (the statistical evidence): those two files are written here, never by hand.

BLAS/OpenMP are pinned to one thread before numpy is imported, so that timings are stable on a
shared machine; every timing is the best of a few repeats.
"""

import argparse
import datetime
import json
import os
from pathlib import Path
import platform
import sys
import time
import traceback

# Before numpy is imported (the standard library above does not load BLAS).
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ[_var] = '1'

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import estimator_bench as eb  # noqa: E402
from bench import montecarlo as mc  # noqa: E402
from coreg_ros.core import quaternion as quat  # noqa: E402
from coreg_ros.core.calibration.pairing import pair_streams  # noqa: E402
from coreg_ros.core.types import PoseStream  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402

RESULTS = ROOT / 'bench' / 'results'
TARGETS = {
    'ols_speedup_100k': 6.0, 'tls_speedup_100k': 20.0, 'tls_seconds_100k': 1.5,
    'peak_bytes_per_pair': 1024.0,
}


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------------
# Pairing and bags
# ----------------------------------------------------------------------------------------------

def _streams(n: int, seed: int = 3):
    """Two 1 kHz streams of n samples each, B's stamps 0.37 ms after A's, smooth poses."""
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000_000_000_000
    stamps_a = t0 + np.arange(n, dtype=np.int64) * 1_000_000
    stamps_b = stamps_a + 370_000
    s = np.arange(n) * 1e-3
    pos = np.stack([0.1 * np.sin(0.3 * s), 0.1 * np.cos(0.2 * s), 0.3 + 0.05 * np.sin(s)], 1)
    rot = np.stack([0.8 * np.sin(0.11 * s), 0.7 * np.sin(0.13 * s + 1), 0.6 * np.cos(0.07 * s)],
                   1)
    q = quat.exp(rot)
    a = PoseStream(stamps_a, pos + 1e-4 * rng.standard_normal(pos.shape), q, 'a_base')
    b = PoseStream(stamps_b, pos + 1e-4 * rng.standard_normal(pos.shape), q, 'b_base')
    return a, b


def bench_pairing(n: int = 1_000_000, repeats: int = 3) -> dict:
    a, b = _streams(n)
    t, (pairs, report) = eb.best_time(lambda: pair_streams(a, b, max_gap_ns=5_000_000),
                                      repeats)
    return {'n_a': n, 'n_b': n, 'n_paired': int(report.n_paired), 'seconds': t,
            'ns_per_sample': 1e9 * t / n}


# ----------------------------------------------------------------------------------------------
# Tables
# ----------------------------------------------------------------------------------------------

def _f(x, fmt='.3f', none='–'):
    return none if x is None else format(x, fmt)


def estimator_table(rows: list) -> str:
    lines = ['| N | estimator | ours (s) | µs/pair | iterations | peak B/pair | scipy | '
             'scipy (s) | speed-up | max diff (σ) |', '|' + '---|' * 10]
    for r in rows:
        scipy_name = 'lm (dense, analytic J)' if r['method'] == 'ols' else 'trf (sparse J, lsmr)'
        status = r['scipy_status']
        lines.append(
            f'| {r["n"]:,} | {r["method"].upper()} | {r["seconds"]:.3f} '
            f'| {r["us_per_pair"]:.1f} | {r["iterations"]} | {r["peak_bytes_per_pair"]:.0f} '
            f'| {scipy_name} | {_f(r["scipy_seconds"]) if r["scipy_seconds"] else status} '
            f'| {_f(r["speedup"], ".1f")}{"×" if r["speedup"] else ""} '
            f'| {_f(r["max_diff_sigma"], ".1e")} |')
    return '\n'.join(lines)


def targets_table(rows: list, results: dict) -> tuple:
    by = {(r['n'], r['method']): r for r in rows}
    checks = []
    ols, tls = by.get((100_000, 'ols')), by.get((100_000, 'tls'))
    if ols and ols['speedup']:
        checks.append(('OLS 100k: speed-up over scipy lm', f'≥ {TARGETS["ols_speedup_100k"]:g}×',
                       f'{ols["speedup"]:.1f}×', ols['speedup'] >= TARGETS['ols_speedup_100k']))
    if tls:
        if tls['speedup']:
            checks.append(('TLS 100k: speed-up over scipy trf',
                           f'≥ {TARGETS["tls_speedup_100k"]:g}×', f'{tls["speedup"]:.1f}×',
                           tls['speedup'] >= TARGETS['tls_speedup_100k']))
        checks.append(('TLS 100k: solve time', f'< {TARGETS["tls_seconds_100k"]:g} s',
                       f'{tls["seconds"]:.2f} s', tls['seconds'] < TARGETS['tls_seconds_100k']))
    for method in ('ols', 'tls'):
        mine = [r for r in rows if r['method'] == method]
        if mine:
            for r in mine:
                if r['n'] >= 100_000:
                    checks.append((f'{method.upper()} {r["n"]:,}: peak memory above the pairs',
                                   '≤ 1 KB/pair', f'{r["peak_bytes_per_pair"]:.0f} B/pair',
                                   r['peak_bytes_per_pair'] <= TARGETS['peak_bytes_per_pair']))
            big = [r for r in mine if r['n'] >= 10_000]
            if len(big) >= 2:
                lo, hi = big[0], big[-1]
                ratio = hi['us_per_pair'] / lo['us_per_pair']
                checks.append((f'{method.upper()} time linear in N (µs/pair {lo["n"]:,} → '
                               f'{hi["n"]:,})', 'ratio ≤ 1.5',
                               f'{lo["us_per_pair"]:.1f} → {hi["us_per_pair"]:.1f} '
                               f'({ratio:.2f})', ratio <= 1.5))
    mc_reports = results.get('montecarlo')
    if mc_reports:
        for r in mc_reports:
            for method, m in r['methods'].items():
                e = m['efficiency']
                if 'efficient' in mc.Scenario(**r['scenario']).expected(method):
                    checks.append((f'MC {r["scenario"]["name"]} {method.upper()}: MSE/CRLB '
                                   f'(trace)', '0.95-1.05', f'{e["trace_ratio"]:.3f} '
                                   f'± {e["trace_ratio_se"]:.3f}',
                                   0.95 <= e['trace_ratio'] <= 1.05))
                checks.append((f'MC {r["scenario"]["name"]} {method.upper()}: all claims',
                               ', '.join(dict(r['scenario']['expect']).get(method, ())),
                               'pass' if m['passed'] else 'FAIL: ' + '; '.join(
                                   c['check'] for c in m['checks'] if not c['passed']),
                               m['passed']))
    nz = results.get('noise')
    if isinstance(nz, dict) and isinstance(nz.get('speed'), dict):
        from bench import noise_bench
        for method, v in nz['speed']['methods'].items():
            checks.append((f'calibrate {nz["speed"]["pairs"]:,} pairs, {method.upper()}: noise '
                           f'auto / stated (whole call)', f'≤ {noise_bench.SPEED_GOAL:g}×',
                           f'{v["ratio"]:.2f}×', v['ratio'] <= noise_bench.SPEED_GOAL))
    st = results.get('time_offset')
    if isinstance(st, dict):
        before = st.get('before')
        was = f' (before: {before["ratio"]:.2f}×)' if before else ''
        checks.append(('calibrate 100k: τ estimated / τ fixed (whole call, CPU)',
                       f'≤ {st["goal_ratio"]:g}×', f'{st["ratio"]:.2f}×{was}',
                       st['ratio'] <= st['goal_ratio']))
    bags = results.get('bags')
    if isinstance(bags, dict):
        from bench.bag_bench import GOAL_CALIBRATE_S, GOAL_PEAK_BYTES
        for r in bags.get('calibrate', []):
            checks.append((f'coreg calibrate, {r["messages"]:,} messages, {r["storage"]}',
                           f'≤ {GOAL_CALIBRATE_S:g} s, ≤ {GOAL_PEAK_BYTES / 2**30:g} GiB',
                           f'{r["calibrate_after_s"]:.1f} s (CPU {r["calibrate_after_cpu_s"]:.1f}'
                           f' s), {r["peak_rss_after_bytes"] / 2**30:.2f} GiB',
                           r['goal_met']))
    lines = ['| target | goal | measured | met |', '|---|---|---|---|']
    lines += [f'| {a} | {b} | {c} | {"yes" if d else "**no**"} |' for a, b, c, d in checks]
    return '\n'.join(lines), [{'target': a, 'goal': b, 'measured': c, 'met': bool(d)}
                              for a, b, c, d in checks]


def other_table(results: dict) -> str:
    lines = ['| benchmark | size | time | rate |', '|---|---|---|---|']
    p = results.get('pairing')
    if p:
        lines.append(f'| pairing (interpolate A at B) | {p["n_a"]:,} × {p["n_b"]:,} samples '
                     f'| {p["seconds"]:.2f} s | {p["ns_per_sample"]:.0f} ns/sample |')
    fz = results.get('fuzz')
    if isinstance(fz, dict):
        t = fz['totals']
        lines.append(f'| fuzz: params, csv, bag, signals (seed {fz["seed"]}) '
                     f'| {t["tried"]} inputs | {fz["seconds"]:.0f} s '
                     f'| {t["traceback"]} tracebacks, {t["hang"]} hangs, '
                     f'{t["wrong"]} known-wrong |')
    st = results.get('time_offset')
    if isinstance(st, dict):
        rows = [('now', st)]
        if st.get('before'):
            rows.append((f'before ({st["before"]["commit"]})', st['before']))
        for label, r in rows:
            lines.append(f'| calibrate, τ estimated vs fixed, {label} | {r["n_pairs"]:,} pairs '
                         f'| CPU {r["estimated_cpu_s"]:.2f} s vs {r["fixed_cpu_s"]:.2f} s '
                         f'(×{r["ratio"]:.2f}, goal ≤ {r["goal_ratio"]:g}); wall '
                         f'{r["estimated_seconds"]:.2f} s vs {r["fixed_seconds"]:.2f} s '
                         f'| τ {r["estimate_s"] * 1e3:.3f} ± {r["sigma_s"] * 1e3:.4f} ms '
                         f'(true {r["true_offset_s"] * 1e3:g}) |')
    return '\n'.join(lines)


BENCHMARKS_INTRO = """\
Every speed goal is measured against a baseline of the same run: scipy solving the *same*
whitened problems from the same closed-form start (`least_squares(method='lm')` with our analytic
Jacobian for OLS, `method='trf'` with the explicit sparse Jacobian over all input poses and φ for
TLS), the code of an earlier commit in a git worktree ("before"), rosbags' own per-message path,
one worker, or the node's plain rclpy path. Timings are the best of a few repeats; peak memory is
the tracemalloc peak above the loaded pairs. "max diff" is the largest difference of our and
scipy's solutions in units of our posterior σ."""

VALIDATION_INTRO = """\
The statistical claims of the package, each shown by simulation with fixed seeds (the test
suite runs the same checks at a reduced size) or on real recordings:
- the estimators (`bench/montecarlo.py`): one truth and motion per scenario, noise redrawn per
  trial: bias (Hotelling), efficiency (MSE against the Cramér-Rao bound of the errors-in-variables
  model, `coreg_ros.core.planning.crlb`, written independently of the estimator), NEES and 95 %
  coverage of the reported covariance, uniformity of the χ² p-values;
- the blind diagnosis validation (`coreg validate-diagnosis`): random effect or none, random
  size, noise, duration and model, the effect withheld from the diagnosis;
- the watchdog (`bench/watchdog_bench.py`): false alarms on long stable streams, detection
  delay and attribution of changes;
- the fuzz (`bench/fuzz.py`): careless and adversarial inputs to every command and the node;
- the real recordings (`bench/real_recordings.py`), as a user would run them;
- each device's noise (`bench/noise_bench.py`): measured on still recordings, estimated with
  the calibration (`--noise auto`), and both on the real recordings (also docs/noise.md)."""


def validation_sections(results: dict, args) -> list:
    """Return the sections of docs/validation.md from this run's results (markdown lines)."""
    out = []
    mc_reports = results.get('montecarlo')
    if isinstance(mc_reports, list):
        out += [f'## Monte Carlo of the estimators (scale {args.mc_scale:g})', '',
                mc.markdown_table(mc_reports), '']
        mc_targets = [t for t in results.get('targets', []) if t['target'].startswith('MC ')]
        if mc_targets:
            out += ['| target | goal | measured | met |', '|---|---|---|---|']
            out += [f'| {t["target"]} | {t["goal"]} | {t["measured"]} | '
                    f'{"yes" if t["met"] else "**no**"} |' for t in mc_targets]
            out += ['']
    else:
        out += ['## Monte Carlo of the estimators', '', f'not measured: {mc_reports}', '']
    val = results.get('diagnosis', {}).get('validation') if isinstance(
        results.get('diagnosis'), dict) else None
    out += ['## Blind diagnosis validation', '']
    if val:
        from coreg_ros.sim.validation import format_validation
        out += [f'`coreg validate-diagnosis --cases {val["cases"]} --seed {val["seed"]}` '
                f'({val["seconds"]:.0f} s):', '', '```console',
                format_validation(val['summary']).rstrip(), '```', '']
    else:
        out += ['not measured in this run (`--diagnosis-cases 0`)', '']
    wd = results.get('watchdog')
    out += ['## Watchdog (stable streams and steps at 100 Hz)', '',
            wd['table'] if isinstance(wd, dict) else f'not measured: {wd}', '']
    fz = results.get('fuzz')
    if isinstance(fz, dict):
        from bench import fuzz
        fz_text = fuzz.table(fz)
    else:
        fz_text = f'not measured: {fz}'
    out += ['## Fuzz', '', fz_text, '']
    from bench import real_recordings
    real = results.get('real')
    out += ['## Real recordings', '',
            real_recordings.table(real) if isinstance(real, dict) else f'not measured: {real}',
            '']
    from bench import noise_bench
    nz = results.get('noise')
    out += ['## Noise you do not have to know (measured still, estimated moving)', '',
            noise_bench.table(nz) if isinstance(nz, dict) else f'not measured: {nz}', '']
    return out


# ----------------------------------------------------------------------------------------------
# Main
# ----------------------------------------------------------------------------------------------

def _section(results: dict, key: str, fn, *args, **kw):
    t = time.perf_counter()
    try:
        results[key] = fn(*args, **kw)
    except Exception as e:  # one failing benchmark must not lose the others
        traceback.print_exc()
        results[key] = f'failed: {type(e).__name__}: {e}'
    log(f'[{key}] {time.perf_counter() - t:.1f} s')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--sizes', type=int, nargs='+', default=[1_000, 10_000, 100_000])
    parser.add_argument('--ols-extra', type=int, nargs='*', default=[1_000_000],
                        help='sizes run for OLS only')
    parser.add_argument('--scipy-cap', type=float, default=120.0,
                        help='abandon a scipy run after this many seconds')
    parser.add_argument('--no-scipy', action='store_true')
    parser.add_argument('--no-mc', action='store_true', help='skip the Monte Carlo')
    parser.add_argument('--mc-scale', type=float, default=1.0, help='Monte Carlo trials × this')
    parser.add_argument('--mc-workers', type=int, default=2)
    parser.add_argument('--node-duration', type=float, default=10.0,
                        help='node benchmark streaming time per rate and path, s (0 skips it)')
    parser.add_argument('--bag-messages', type=int, default=500_000,
                        help='PoseStamped messages per topic in the bag benchmark (0 skips it)')
    parser.add_argument('--no-bag-calibrate', action='store_true',
                        help='skip coreg calibrate on the 2M-pair recording (before/after)')
    parser.add_argument('--parallel-cases', type=int, default=40,
                        help='validation cases run with 1 and 2 workers (0 skips it)')
    parser.add_argument('--no-calibrate-speed', action='store_true',
                        help='skip the whole calibrate() at 100k and 1M pairs')
    parser.add_argument('--rig-samples', type=int, default=250_000,
                        help='samples per device of the rig benchmark (0 skips it)')
    parser.add_argument('--diagnosis-cases', type=int, default=500,
                        help='cases of the blind diagnosis validation (0: skip; the 60k-pair '
                             'diagnosis timing always runs)')
    parser.add_argument('--diagnosis-seed', type=int, default=2026)
    parser.add_argument('--no-diagnosis', action='store_true', help='skip the diagnosis timing')
    parser.add_argument('--no-profile', action='store_true')
    parser.add_argument('--fuzz-n', type=int, default=60, help='fuzz inputs per kind (0: skip)')
    parser.add_argument('--watchdog-hours', type=float, default=72.0,
                        help='stable hours simulated for the watchdog false-alarm rate (0: skip)')
    parser.add_argument('--no-noise', action='store_true',
                        help='skip the noise benchmark (noise auto speed, still and auto Monte '
                             'Carlo, the noise of the real recordings)')
    parser.add_argument('--real-data', help='folder holding eth_hand_eye (default: '
                                            'COREG_REAL_DATA or ../shared/data/real)')
    parser.add_argument('--docs', type=Path, default=ROOT / 'docs',
                        help='write benchmarks.md and validation.md here (default docs/)')
    parser.add_argument('--no-docs', action='store_true',
                        help='print and write the JSON only (a partial run)')
    args = parser.parse_args(argv)
    started = time.perf_counter()
    date = datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')
    env = {'date': date, 'python': platform.python_version(), 'numpy': np.__version__,
           'scipy': scipy.__version__, 'machine': platform.machine(), 'cpus': os.cpu_count(),
           'load_average_at_start': os.getloadavg(),
           'threads': 'OPENBLAS_NUM_THREADS=OMP_NUM_THREADS=MKL_NUM_THREADS=1',
           'command': ' '.join(['python bench/run.py', *_shown_args(argv)])}
    log(f'coreg_ros benchmarks, {date}; BLAS/OpenMP pinned to 1 thread; '
        f'load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs')
    results = {'environment': env}

    rows = []
    t = time.perf_counter()
    for n in sorted(set(args.sizes) | set(args.ols_extra)):
        methods = ('ols', 'tls') if n in args.sizes else ('ols',)
        try:
            got = eb.bench_size(n, methods, scipy_cap=args.scipy_cap,
                                with_scipy=not args.no_scipy, log=log)
            rows.extend(got[m] for m in methods)
        except Exception:
            traceback.print_exc()
    results['estimators'] = rows
    log(f'[estimators] {time.perf_counter() - t:.1f} s')
    from spatiotemporal_bench import bench_time_offset
    _section(results, 'time_offset', bench_time_offset)
    if not args.no_profile and 100_000 in args.sizes:
        _section(results, 'tls_profile_100k', eb.profile_tls, 100_000)
    _section(results, 'pairing', bench_pairing)
    # scale and speed: each module measures its goal against a baseline of the same run
    scale = []  # (key, title, module)
    if not args.no_calibrate_speed:
        from bench import calibrate_speed_bench
        _section(results, 'calibrate_speed', calibrate_speed_bench.run,
                 with_scipy=not args.no_scipy, scipy_cap=args.scipy_cap)
        scale.append(('calibrate_speed', 'Whole calibrate() at 100k and 1M pairs',
                      calibrate_speed_bench))
    if args.rig_samples > 0:
        from bench import rig_bench
        _section(results, 'rig', rig_bench.run, args.rig_samples)
        scale.append(('rig', 'A rig: A + 3 devices with their own clocks against one pair',
                      rig_bench))
    if not args.no_calibrate_speed:
        from bench import restricted_bench
        _section(results, 'restricted', restricted_bench.run)
        scale.append(('restricted', 'Restricted rigs: calibrate() against a full-rank '
                      'recording of the same size', restricted_bench))
    if args.bag_messages > 0:
        from bench import bag_bench
        _section(results, 'bags', bag_bench.run, n=args.bag_messages,
                 calibrate=not args.no_bag_calibrate, calibrate_storages=('sqlite3', 'mcap'))
        scale.append(('bags', 'Bags: bulk read/write vs rosbags per message', bag_bench))
    if not args.no_diagnosis:
        from bench import bench_diagnosis
        _section(results, 'diagnosis', bench_diagnosis.run, args.diagnosis_cases,
                 args.diagnosis_seed, jobs=2, timing=True)
        scale.append(('diagnosis', 'Diagnosis of a 60k-pair recording, every candidate model',
                      bench_diagnosis))
    if args.parallel_cases > 0:
        from bench import parallel_bench
        _section(results, 'parallel', parallel_bench.run, args.parallel_cases)
        scale.append(('parallel', 'Many cases in parallel (validate-diagnosis)', parallel_bench))
    if args.node_duration > 0:
        try:
            from bench import bench_node
        except Exception as e:  # the node benchmark needs rclpy and a working ROS setup
            results['node'] = f'not available: {type(e).__name__}: {e}'
        else:
            _section(results, 'node', bench_node.run, args.node_duration)
            scale.append(('node', 'The node under 2 × 2, 5 and 10 kHz', bench_node))
    if not args.no_mc:
        _section(results, 'montecarlo', mc.run_all, args.mc_scale, args.mc_workers, log=log)
    if args.fuzz_n > 0:
        from bench import fuzz
        _section(results, 'fuzz', fuzz.run, args.fuzz_n, 12, with_ros=args.node_duration > 0,
                 log=log)
    if args.watchdog_hours > 0:
        from bench import watchdog_bench
        _section(results, 'watchdog', watchdog_bench.run, args.watchdog_hours)
    from bench import real_recordings
    _section(results, 'real', real_recordings.run, args.real_data)
    if not args.no_noise:
        from bench import noise_bench
        _section(results, 'noise', noise_bench.run, data=args.real_data)
    results['total_seconds'] = time.perf_counter() - started

    speed = ['## Estimators (full pose, default noise; ours vs scipy.optimize.least_squares)',
             '', estimator_table(rows), '',
             '## Pairing, bags, node', '', other_table(results), '']
    for key, title, module in scale:
        body = module.table(results[key]) if isinstance(results.get(key), dict) else (
            f'not measured: {results.get(key)}')
        speed += [f'## {title}', '', body, '']
    target_md, target_rows = targets_table(rows, results)
    results['targets'] = target_rows
    speed += ['## Targets', '', target_md, '']
    evidence = validation_sections(results, args)
    text = '\n'.join(speed + evidence)
    print(f'coreg_ros benchmarks — {date} — `{env["command"].strip()}` — '
          f'{env["threads"]} — {os.cpu_count()} CPUs, shared (best of repeats)\n')
    print(text)
    if isinstance(results.get('tls_profile_100k'), str):
        print('### solve_tls profile at N = 100,000 (cProfile, by internal time)\n')
        print('```\n' + results['tls_profile_100k'].strip() + '\n```')
    print(f'\ntotal {results["total_seconds"]:.0f} s')
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / 'estimator.json'
    out.write_text(json.dumps(results, indent=1, default=_json_default) + '\n')
    (RESULTS / 'tables.md').write_text(text + '\n')
    log(f'written to {out}')
    if not args.no_docs:
        run_line = (f'Regenerated by `make bench` ({date}, `{env["command"].strip()}`) on '
                    f'{os.cpu_count()} shared CPUs (load average '
                    f'{env["load_average_at_start"][0]:.1f} at the start, '
                    f'{os.getloadavg()[0]:.1f} at the end), {env["threads"]}, Python '
                    f'{env["python"]}, numpy {env["numpy"]}, scipy {env["scipy"]}. '
                    f'Total {results["total_seconds"]:.0f} s. Written by bench/run.py: do not '
                    f'edit by hand.')
        args.docs.mkdir(parents=True, exist_ok=True)
        (args.docs / 'benchmarks.md').write_text(
            '# Benchmarks\n\n' + run_line + '\n\n' + BENCHMARKS_INTRO + '\n\n'
            + '\n'.join(speed))
        (args.docs / 'validation.md').write_text(
            '# Validation\n\n' + run_line + '\n\n' + VALIDATION_INTRO + '\n\n'
            + '\n'.join(evidence))
        log(f'written {args.docs / "benchmarks.md"} and {args.docs / "validation.md"}')
        if isinstance(results.get('noise'), dict):
            from bench import noise_bench
            noise_bench.write_docs(results['noise'], args.docs / 'noise.md', run_line)
    return 0


def _shown_args(argv) -> list:
    """Command-line arguments as shown in the output."""
    return list(sys.argv[1:] if argv is None else argv)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


if __name__ == '__main__':
    sys.exit(main())
