"""
Noise you don't have to know (issue 24): speed, the Monte Carlo at full size, the real recordings.

- **Speed**: ``calibrate_streams`` (what ``coreg calibrate`` and ``coreg_ros.calibrate`` run) on
  a 1000 s recording at 100 Hz (100k pairs, clock offset estimated), with the noise stated and
  with ``noise='auto'``, OLS and TLS, repeats alternating, best of each: the ratio against the
  goal of at most 2×.
- **Still recordings** (``sim.still``, 30 s at 100 Hz; ``SEEDS`` seeds each): isotropic,
  anisotropic (depth 3×), distance-dependent (three places, σ ∝ r²), white noise with a random
  walk: the largest error of the σ per axis and of the Allan white level, the largest angle of
  the principal axis, against 10 %, 10 % and 5°; the spread of the standard errors' z-scores.
- **noise auto** (``sim.noise_trials``, ``TRIALS`` trials of ``PAIRS`` pairs per scenario):
  identifiable components within 15 %, NEES of (T0, T1) in its 99 % band, verdicts naming
  exactly what was misstated.
- **Real recordings** (the ETH ASL hand-eye data, converted as ``real_recordings`` does): the
  noise measured in the still parts (``coreg noise``) and estimated from the moving parts
  (``coreg calibrate --noise auto``, camera stated at 5 mm / 20 mrad, both methods).

``python bench/noise_bench.py [--quick] [--docs]`` prints the tables (``--docs`` also writes
docs/noise.md); ``run()``, ``table()`` and ``write_docs()`` serve ``bench/run.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
from pathlib import Path
import sys
import tempfile
import time

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

#: Goal: noise auto over the stated noise, whole calibrate_streams at 100k pairs.
SPEED_GOAL = 2.0
SEEDS = 50
TRIALS, PAIRS = 40, 5000
STILL_CASES = ('isotropic', 'anisotropic', 'distance', 'random_walk')


def _best(fn, repeats: int) -> float:
    best = float('inf')
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def speed(repeats: int = 3, duration: float = 1000.0) -> dict:
    """Return ``calibrate_streams`` seconds, stated and auto, OLS and TLS, at 100k pairs."""
    from coreg_ros.core.calibration.pipeline import calibrate_streams
    from coreg_ros.core.settings import Settings
    from coreg_ros.sim import simulate_recording

    rec = simulate_recording(24, duration, rate_a=100.0, rate_b=100.0)
    out = {'pairs': None, 'methods': {}}
    for method in ('ols', 'tls'):
        times = {'stated': float('inf'), 'auto': float('inf')}
        for _ in range(repeats):  # alternating, so that load hits both alike
            for noise in ('stated', 'auto'):
                s = Settings(method=method, noise=noise)
                t = _best(lambda s=s: calibrate_streams(rec.stream_a, list(rec.streams_b), s), 1)
                times[noise] = min(times[noise], t)
        r, _ = calibrate_streams(rec.stream_a, list(rec.streams_b), Settings(method=method))
        out['pairs'] = r.n_pairs
        out['methods'][method] = {**times, 'ratio': times['auto'] / times['stated']}
    return out


def still(seeds: int = SEEDS) -> dict:
    """Return the still-recording Monte Carlo (module docstring)."""
    from coreg_ros.core.noise.measure import measure_device
    from coreg_ros.core.noise.still import segments_of, still_mask
    from coreg_ros.core.noise_model import DeviceNoise, principal_axes
    from coreg_ros.sim.still import anisotropic_noise, simulate_still

    lateral = (3e-4, 1.5e-3)
    places = np.array([[0.2, 0.0, 0.2], [0.35, 0.1, 0.3], [0.55, 0.2, 0.45]])
    out = {}
    for case in STILL_CASES:
        sig_err, white_err, angle, z = [], [], [], []
        for seed in range(seeds):
            rng = np.random.default_rng([24, seed])
            if case == 'anisotropic':
                rec = simulate_still(seed, anisotropic_noise(rng, lateral, 3.0))
            elif case == 'distance':
                rec = simulate_still(seed, DeviceNoise.isotropic(lateral), places=places,
                                     exponent=2.0)
            elif case == 'random_walk':
                rec = simulate_still(seed, DeviceNoise.isotropic(lateral),
                                     random_walk=(1e-4, 5e-4))
            else:
                rec = simulate_still(seed, DeviceNoise.isotropic(lateral))
            s = rec.stream
            segs = segments_of(s.stamps, still_mask(s.stamps, s.position, s.quat_wxyz))
            m = measure_device(s, segs[:1], 'a')  # the first place (its own noise)
            for kind in ('position', 'rotation'):
                ch, truth = m.channels[kind], rec.noise_at(0).channel(kind)
                sd = np.sqrt(np.diag(truth))
                sig_err.append(float(np.max(np.abs(ch.sigma_axes / sd - 1))))
                white_err.append(float(np.max(np.abs(ch.allan.white / sd - 1))))
                z += list((ch.sigma_axes - sd) / ch.sigma_axes_se)
                if case == 'anisotropic':
                    _, axes = principal_axes(truth)
                    cos = min(1.0, abs(float(axes[0] @ ch.principal_axes[0])))
                    angle.append(float(np.degrees(np.arccos(cos))))
        out[case] = {'max_sigma_error': max(sig_err), 'max_white_error': max(white_err),
                     'max_axis_angle_deg': max(angle) if angle else None,
                     'z_spread': float(np.std(z)), 'seeds': seeds}
    return out


def auto(trials: int = TRIALS, pairs: int = PAIRS) -> list:
    """Return the noise-auto Monte Carlo of every scenario (``sim.noise_trials``)."""
    from coreg_ros.sim.noise_trials import run_scenario, scenarios
    return [run_scenario(sc, trials, pairs) for sc in scenarios()]


def _coreg(*args) -> tuple[int, str]:
    from coreg_ros.cli.main import main
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        code = main([str(a) for a in args])
    return code, buf.getvalue()


def real(data=None) -> dict:
    """Return each real recording's noise: still parts measured, moving parts estimated."""
    from bench import real_recordings as rr
    root = rr.data_folder(data)
    if root is None:
        return {'available': False}
    rows = []
    with tempfile.TemporaryDirectory(prefix='coreg_noise_') as tmp:
        work = Path(tmp)
        for name, folder, csv_a, csv_b, flags in rr.RECORDINGS:
            src = root / 'eth_hand_eye' / folder
            bag = work / folder
            row = {'name': name}
            code, text = _coreg('convert', *flags, src / csv_a, src / csv_b, bag)
            if code != 0:
                rows.append({**row, 'error': text.strip().splitlines()[-1]})
                continue
            code, text = _coreg('noise', bag, '--json', work / 'n.json', '--out',
                                work / 'n.yaml')
            row['still'] = (json.loads((work / 'n.json').read_text()) if code == 0 else
                            {'error': text.strip().splitlines()[-1]})
            for method in ('tls', 'ols'):
                out = work / f'{method}.json'
                code, text = _coreg('calibrate', bag, '--sigma-b', *rr.SIGMA_B, '--noise',
                                    'auto', '--method', method, '--json', out)
                row[method] = json.loads(out.read_text()) if out.exists() else {
                    'error': text.strip().splitlines()[-1]}
                out.unlink(missing_ok=True)
            for f in ('n.json', 'n.yaml'):
                (work / f).unlink(missing_ok=True)
            rows.append(row)
    return {'available': True, 'sigma_b': rr.SIGMA_B, 'recordings': rows}


def run(quick: bool = False, data=None) -> dict:
    """Run every part (``quick``: a tenth of the Monte Carlo, a shorter speed recording)."""
    out = {}
    t = time.perf_counter()
    out['speed'] = speed(repeats=2 if quick else 3, duration=300.0 if quick else 1000.0)
    out['still'] = still(SEEDS // 5 if quick else SEEDS)
    out['auto'] = auto(TRIALS // 8 if quick else TRIALS, PAIRS // 2 if quick else PAIRS)
    out['real'] = real(data)
    out['seconds'] = time.perf_counter() - t
    return out


def _mm(v) -> str:
    return ', '.join(f'{x * 1e3:.3g}' for x in v)


def _estimated_cell(doc: dict, device: str) -> str:
    if 'error' in doc:
        return doc['error']
    d = doc['noise'][f'device_{device}']
    parts = []
    for kind, unit in (('position', 'mm'), ('rotation', 'mrad')):
        status = d['channels'][kind]['status']
        key = f'{kind}_sigma_{"m" if kind == "position" else "rad"}'
        if status == 'estimated':
            se = d['sigma_of_estimate'][key]
            parts.append(f'{kind} {_mm(d[key])} ± {_mm([max(se)])} {unit}')
        elif status == 'held':
            parts.append(f'{kind} held ({d["channels"][kind]["note"].split(" (")[0]})')
    return '; '.join(parts)


def table(result: dict) -> str:
    """Markdown: speed, still Monte Carlo, noise-auto Monte Carlo, real recordings."""
    lines = []
    sp = result.get('speed')
    if isinstance(sp, dict):
        lines += [f'`calibrate_streams` on {sp["pairs"]} pairs (100 Hz, clock offset '
                  f'estimated), best of the repeats; goal: noise auto at most {SPEED_GOAL:g}× '
                  f'the stated noise', '', '| method | stated noise, s | noise auto, s | ratio '
                  '| goal met |', '|---|---|---|---|---|']
        for m, v in sp['methods'].items():
            lines.append(f'| {m.upper()} | {v["stated"]:.2f} | {v["auto"]:.2f} | '
                         f'{v["ratio"]:.2f} | {"yes" if v["ratio"] <= SPEED_GOAL else "**no**"} |')
        lines.append('')
    st = result.get('still')
    if isinstance(st, dict):
        lines += ['Still recordings, 30 s at 100 Hz (`sim.still`); goals: σ per axis and Allan '
                  'white level within 10 %, principal axes within 5°', '',
                  '| case | seeds | largest σ error | largest white-level error | largest axis '
                  'angle | spread of z = (σ̂ - σ)/SE |', '|---|---|---|---|---|---|']
        for case, v in st.items():
            ang = '–' if v['max_axis_angle_deg'] is None else f'{v["max_axis_angle_deg"]:.2f}°'
            lines.append(f'| {case} | {v["seeds"]} | {v["max_sigma_error"]:.1%} | '
                         f'{v["max_white_error"]:.1%} | {ang} | {v["z_spread"]:.2f} |')
        lines.append('')
    au = result.get('auto')
    if isinstance(au, list):
        lines += ['`--noise auto` on simulated pairs whose stated noise is off (`sim.noise_trials`'
                  '); goals: identifiable components within 15 %, mean NEES of (T0, T1) in its '
                  '99 % band, the verdict naming exactly what was misstated', '',
                  '| scenario | trials × pairs | largest error per component | mean NEES '
                  '(99 % band) | verdicts naming it | held as undetermined |',
                  '|---|---|---|---|---|---|']
        for r in au:
            errs = ', '.join(f'{k} {v:.1%}' for k, v in r['max_error'].items())
            lo, hi = r['nees_band']
            held = ', '.join(f'{k} {v:.0%}' for k, v in r.get('held_share', {}).items()) or '–'
            lines.append(f'| {r["name"]} | {r["trials"]} × {r["n_pairs"]} | {errs} | '
                         f'{r["mean_nees"]:.2f} ({lo:.2f}-{hi:.2f}) | {r["named_share"]:.0%} | '
                         f'{held} |')
        lines.append('')
    lines.append(real_table(result.get('real') or {}))
    return '\n'.join(lines)


def real_table(real: dict) -> str:
    """Markdown table of the real recordings' noise (measured still, estimated moving)."""
    if not real.get('available'):
        return 'Real recordings: not measured (the data are not on this machine)'
    lines = [f'Real recordings (ETH ASL hand-eye): `coreg noise` on the still parts; `coreg '
             f'calibrate --noise auto` on the moving parts, camera stated at '
             f'{real["sigma_b"][0]} m, {real["sigma_b"][1]} rad, A at the default '
             f'(0.2 mm, 0.5 mrad); principal σ ± the largest SE', '',
             '| recording (A / B) | still parts (`coreg noise`) | method | A estimated | '
             'B estimated | χ²/dof at the estimate | verdict on the noise |',
             '|---|---|---|---|---|---|---|']
    for rec in real['recordings']:
        if 'error' in rec:
            lines.append(f'| {rec["name"]} | {rec["error"]} | | | | | |')
            continue
        still = rec['still']
        still_text = still.get('error', 'measured').replace('coreg noise: error: ', '')
        still_text = still_text.split('; hold')[0]
        for method in ('tls', 'ols'):
            doc = rec[method]
            chi = (f'{doc["chi2"] / doc["dof"]:.2f}' if 'chi2' in doc and doc.get('dof')
                   else '–')
            verdict = doc.get('noise', {}).get('verdict', doc.get('error', '')) or 'as stated'
            lines.append(f'| {rec["name"] if method == "tls" else ""} | '
                         f'{still_text if method == "tls" else ""} | {method.upper()} | '
                         f'{_estimated_cell(doc, "a")} | {_estimated_cell(doc, "b")} | {chi} | '
                         f'{verdict} |')
    return '\n'.join(lines)


DOCS_INTRO = """\
Every calibration rests on each device's noise: the TLS weights, the covariance of (T0, T1), the
χ² verdict, the diagnosis' floor, the guidance targets and the watchdog's threshold. Two ways to
know it without a datasheet:

- `coreg noise RECORDING` measures it where each device stands still (found, or `--window T0
  T1`): 3×3 position and rotation covariances in the device's base frame with per-axis and
  principal σ and their standard errors, the Allan deviation (white level, where random walk or
  drift take over), noise against distance, the sampling; `--json`, `--plot PNG`, and a noise
  file (`--out`, default `RECORDING.noise.yaml`) that `calibrate`, `diagnose`, `plan`,
  `validate-diagnosis` (`--noise FILE`), the node (`noise_file`) and `coreg_ros.calibrate(noise=
  FILE)` read.
- `--noise auto` (and the node's `noise: auto`) estimates it jointly with the calibration from a
  moving recording (variance components by REML Fisher scoring): what the motion cannot tell
  apart (OLS: A's noise from B's; A's and B's position noise, which reach the pairs as a sum) is
  held at the stated value and said; the verdict names the device and channel misstated.

What a calibration's model does not hold is, to `--noise auto`, noise: a fit consistent with the
estimated noise says that the rest looks like noise, not that the model is right (the Vicon /
RGB camera recording below, refused at the stated noise for the camera's scale error, becomes
consistent at a camera noise 1.76× the stated in position). `coreg diagnose --noise auto` takes
the estimate as its floor and still looks for the structure an effect leaves. A camera's pose
from a target has position and rotation errors correlated (0.84-0.96 below) beyond any 3×3
covariance per channel: the verdict says so, and the χ² and covariance are then approximate.

The tables below are written by `bench/noise_bench.py` (also run by `make bench`): do not edit
by hand."""


def write_docs(result: dict, path: Path, run_line: str = '') -> None:
    """Write docs/noise.md: what the two ways are, then this run's tables."""
    head = ['# Noise you do not have to know', '']
    if run_line:
        head += [run_line, '']
    path.write_text('\n'.join(head + [DOCS_INTRO, '', table(result), '']))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='a tenth of the Monte Carlo')
    parser.add_argument('--real-only', action='store_true', help='the real recordings only')
    parser.add_argument('--data', help='folder holding eth_hand_eye')
    parser.add_argument('--json', help='also write the results here')
    parser.add_argument('--docs', action='store_true', help='also write docs/noise.md')
    args = parser.parse_args(argv)
    result = {'real': real(args.data)} if args.real_only else run(args.quick, args.data)
    print(table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1, default=str) + '\n')
    if args.docs:
        command = ' '.join(['python bench/noise_bench.py', *(argv or sys.argv[1:])])
        date = time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())
        write_docs(result, ROOT / 'docs' / 'noise.md',
                   f'Regenerated by `{command}` ({date}, {os.cpu_count()} shared CPUs, BLAS one '
                   f'thread); Monte Carlo with fixed seeds.')
    return 0


if __name__ == '__main__':
    sys.exit(main())
